"""``drivetrack export``: the npz formats of the field, written from the v2 tables clip by clip.

The arrays are those of :func:`drivetrack.tracks.writers.drivetrack_arrays` and
:func:`~drivetrack.tracks.writers.tapvid3d_arrays`, written by
:func:`~drivetrack.tracks.writers.write_npz`, fed a :class:`drivetrack.compact.read.StoredClip`
instead of a freshly tracked clip: the files are byte for byte those the writers produced when
the pipeline wrote npz itself. One clip is held at a time.
"""
from __future__ import annotations

from typing import Callable, Iterable

from drivetrack.compact.read import iter_clips
from drivetrack.outputs import DRIVETRACK, TAPVID3D, clip_path

__all__ = ["FORMATS", "export_clips"]

#: ``--format`` name -> clip layout of :mod:`drivetrack.outputs`.
FORMATS = {"drivetrack-npz": DRIVETRACK, "tapvid3d": TAPVID3D}


def _arrays(layout: str):
    from drivetrack.tracks.writers import drivetrack_arrays, tapvid3d_arrays

    return drivetrack_arrays if layout == DRIVETRACK else tapvid3d_arrays


def export_clips(release_or_out: str, formats: Iterable[str], out_url: str, clips: set[str] | None = None,
                 storage_options: dict | None = None,
                 on_clip: Callable[[str, list[str]], None] | None = None) -> list[str]:
    """Write every clip (or those in ``clips``) of ``release_or_out`` in each of ``formats``
    (:data:`FORMATS` names) under ``out_url`` (``tracks/{split}/...``, ``tapvid3d/{split}/...``).
    Returns the written URLs; ``on_clip(clip, urls)`` hears each clip. ValueError for an unknown
    format; FileNotFoundError when no clip was found."""
    from drivetrack.tracks.writers import write_npz

    formats = list(dict.fromkeys(formats))
    unknown = [f for f in formats if f not in FORMATS]
    if unknown or not formats:
        raise ValueError(f"unknown export format(s) {unknown or formats}; known: {sorted(FORMATS)}")
    root = out_url.rstrip("/")
    written: list[str] = []
    found = 0
    for clip in iter_clips(release_or_out, clips, storage_options):
        found += 1
        urls = [write_npz(f"{root}/{clip_path(FORMATS[f], clip.split, clip.clip)}", _arrays(FORMATS[f])(clip))
                for f in formats]
        written.extend(urls)
        if on_clip:
            on_clip(clip.clip, urls)
    if not found:
        wanted = f" named {sorted(clips)}" if clips else ""
        raise FileNotFoundError(f"{release_or_out}: no clip{wanted} in clips/*/*.parquet (release layout v2)")
    return written
