"""The one place that knows where clip files live in an annotation output folder or a release.

    tracks/{split}/waymo_{segment}_{CAMERA}_{object_id}.npz     DriveTrack-compatible clips
    tapvid3d/{split}/waymo_{segment}_{CAMERA}_{object_id}.npz   the same clips, TAPVid-3D layout

Split folders sit under a layout folder because Waymo has a split called ``validation`` and the
top-level ``validation/`` folder holds the gate reports. Paths here are relative, ``/``-separated.
"""
from __future__ import annotations

from drivetrack.names import check_name

__all__ = ["LAYOUTS", "DRIVETRACK", "TAPVID3D", "clip_path", "clip_glob", "parse_clip_path", "splits_of",
           "clips_of"]

DRIVETRACK = "drivetrack"
TAPVID3D = "tapvid3d"
#: layout name -> top-level folder
LAYOUTS = {DRIVETRACK: "tracks", TAPVID3D: "tapvid3d"}
CLIP_PREFIX = "waymo_"


def clip_path(layout: str, split: str, stem: str) -> str:
    """Relative path of clip ``stem`` (``waymo_{segment}_{CAMERA}_{object_id}``) of ``split``."""
    try:
        folder = LAYOUTS[layout]
    except KeyError:
        raise ValueError(f"unknown clip layout {layout!r}; known: {sorted(LAYOUTS)}") from None
    check_name("split", split, f"clip path of {stem!r}")
    return f"{folder}/{split}/{stem}.npz"


def clip_glob(layout: str, split: str) -> str:
    """Glob of ``layout``'s clip files of ``split`` (e.g. for Hugging Face ``data_files``)."""
    return f"{LAYOUTS[layout]}/{split}/{CLIP_PREFIX}*.npz"


def parse_clip_path(path: str) -> tuple[str, str] | None:
    """``(layout, split)`` of a relative clip path, or None when ``path`` is not a clip file."""
    parts = path.split("/")
    if len(parts) != 3 or not parts[2].startswith(CLIP_PREFIX) or not parts[2].endswith(".npz"):
        return None
    for layout, folder in LAYOUTS.items():
        if parts[0] == folder and parts[1]:
            return layout, parts[1]
    return None


def splits_of(paths, layout: str | None = None) -> list[str]:
    """Sorted splits that have clip files (of ``layout``, or of any layout) among ``paths``."""
    out = set()
    for path in paths:
        parsed = parse_clip_path(path)
        if parsed and (layout is None or parsed[0] == layout):
            out.add(parsed[1])
    return sorted(out)


def clips_of(paths, layout: str, split: str) -> list[str]:
    """Sorted clip paths of ``layout`` and ``split`` among ``paths``."""
    return sorted(p for p in paths if parse_clip_path(p) == (layout, split))
