"""DriveTrack Release: long-range point-track annotations from driving logs, as versioned releases."""
from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__ = _version("drivetrack")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"


def load_clip(release_or_out: str, clip: str, storage_options: dict | None = None):
    """One clip of a release or annotation output folder: video (decoded lazily), tracks, visibility
    (:func:`drivetrack.compact.read.load_clip`; docs/formats.md)."""
    from drivetrack.compact.read import load_clip as _load_clip

    return _load_clip(release_or_out, clip, storage_options)
