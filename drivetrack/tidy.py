"""Keep an annotation output folder clean after a run: no temporary files, no clips of failed segments.

:func:`drivetrack.annotate.annotate` calls both at the end of every run (also an interrupted one),
so OUT never keeps a writer's ``.partial-*`` file or a clip of a segment recorded as failed (issue
13 item 6). Run them only when no other run writes into the same folder.
"""
from __future__ import annotations

from collections.abc import Iterable

import fsspec

from drivetrack.outputs import CLIP_PREFIX, LAYOUTS, TABLE_FOLDERS, parse_table_path
from drivetrack.storage import PARTIAL_PREFIX
from drivetrack.waymo.schema import CameraName

__all__ = ["remove_partial_files", "remove_segment_clips"]


def _ls(fs, path: str) -> list[str]:
    try:
        return [p.rstrip("/") for p in fs.ls(path, detail=False)] if fs.isdir(path) else []
    except FileNotFoundError:
        return []


def remove_partial_files(out_url: str, storage_options: dict | None = None) -> list[str]:
    """Remove every temporary ``.partial-*`` file from an output folder; returns their URLs.

    Looks where writers put them: the folder itself, ``stats/`` and every split folder of each
    clip layout (so files left by an earlier killed run go too). Run it only when no other run
    writes into the same folder.
    """
    fs, base = fsspec.core.url_to_fs(out_url, **(storage_options or {}))
    base = base.rstrip("/")
    folders = [base, f"{base}/stats"]
    for folder in (*TABLE_FOLDERS.values(), *LAYOUTS.values()):
        folders += [p for p in _ls(fs, f"{base}/{folder}") if fs.isdir(p)]
    removed = []
    for folder in folders:
        for path in _ls(fs, folder):
            if path.rsplit("/", 1)[-1].startswith(PARTIAL_PREFIX):
                fs.rm(path)
                removed.append(fs.unstrip_protocol(path))
    return removed


def remove_segment_clips(out_url: str, split: str, segments: Iterable[str], keep: Iterable[str] = (),
                         storage_options: dict | None = None) -> list[str]:
    """Remove the clip files of ``segments`` of ``split`` (every layout); returns their URLs.

    The clip files of segment S are its v2 tables ``clips/{split}/S.parquet`` and
    ``frames/{split}/S_{CAMERA}.parquet`` and any npz ``waymo_{S}_{CAMERA}_{object_id}.npz`` with
    CAMERA a Waymo camera name; paths relative to ``out_url`` in ``keep`` (files of segments that
    succeeded) stay.
    """
    fs, base = fsspec.core.url_to_fs(out_url, **(storage_options or {}))
    base = base.rstrip("/")
    keep = set(keep)
    prefixes = tuple(f"{CLIP_PREFIX}{segment}_{camera.name}_" for segment in segments
                     for camera in CameraName if camera != CameraName.UNKNOWN)
    removed = []
    if not prefixes:
        return removed
    wanted = set(segments)
    for folder in TABLE_FOLDERS.values():
        for path in _ls(fs, f"{base}/{folder}/{split}"):
            rel = f"{folder}/{split}/{path.rsplit('/', 1)[-1]}"
            parsed = parse_table_path(rel)
            if parsed and parsed[2] in wanted and rel not in keep:
                fs.rm(path)
                removed.append(fs.unstrip_protocol(path))
    for folder in LAYOUTS.values():
        for path in _ls(fs, f"{base}/{folder}/{split}"):
            leaf = path.rsplit("/", 1)[-1]
            if leaf.startswith(prefixes) and leaf.endswith(".npz") and f"{folder}/{split}/{leaf}" not in keep:
                fs.rm(path)
                removed.append(fs.unstrip_protocol(path))
    return removed
