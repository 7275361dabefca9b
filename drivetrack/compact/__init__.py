"""Release layout v2: clips and frames as Parquet tables (Hugging Face ``datasets`` and Croissant
loadable), the loader :func:`load_clip`, and the npz exports (docs/formats.md)."""
from drivetrack.compact.read import ClipData, CompactFormatError, StoredClip, iter_clips, load_clip, read_clip

__all__ = ["ClipData", "CompactFormatError", "StoredClip", "iter_clips", "load_clip", "read_clip"]
