"""The release flow's work folder: where each segment's outputs and records live.

Layout (any fsspec URL; shared storage when the cluster is remote)::

    WORK/segments/{split}/{segment}/{key16}/      one segment's outputs for one content key
        {split}/...npz, stats/*.parquet             (written by the pipeline API)
        _done.json                                  completion record, written last
    WORK/progress/{split}/{segment}.json          live stage states of the running job
    WORK/checksums.json                           source checksum memo (drivetrack.release.keys)

Records are written whole (:func:`drivetrack.storage.write_json`); a damaged one is an error
naming it, never taken for absent.
"""
from __future__ import annotations

import fsspec

from drivetrack import storage

__all__ = ["DONE", "segment_dir", "progress_path", "write_record", "read_record", "completion_record"]

DONE = "_done.json"


def _fs(url: str, storage_options: dict | None):
    fs, path = fsspec.core.url_to_fs(str(url), **(storage_options or {}))
    return fs, path.rstrip("/")


def segment_dir(work: str, split: str, segment: str, key: str) -> str:
    return f"{str(work).rstrip('/')}/segments/{split}/{segment}/{key[:16]}"


def progress_path(work: str, split: str, segment: str) -> str:
    return f"{str(work).rstrip('/')}/progress/{split}/{segment}.json"


def write_record(url: str, doc: dict, storage_options: dict | None = None) -> str:
    """Write a work-folder record (completion, progress, checksum memo) atomically
    (:func:`drivetrack.storage.write_json`: a reader never sees half a record)."""
    return storage.write_json(url, doc, indent=1, default=str, storage_options=storage_options)


def read_record(url: str, storage_options: dict | None = None) -> dict | None:
    """A work-folder record, or None when it does not exist. A record that is not valid JSON
    raises ValueError naming the file (records are written whole, so it was damaged)."""
    return storage.read_json(url, storage_options, missing_ok=True)


def completion_record(work: str, split: str, segment: str, key: str,
                      storage_options: dict | None = None) -> dict | None:
    """The record of a finished job with this key, if it exists, matches the key and every file
    it lists is present with its size; else None (the segment must be computed). A damaged
    record (not JSON) raises ValueError naming it."""
    seg_dir = segment_dir(work, split, segment, key)
    rec = read_record(f"{seg_dir}/{DONE}", storage_options)
    if not rec or rec.get("key") != key or rec.get("status") != "done":
        return None
    fs, root = _fs(seg_dir, storage_options)
    try:
        sizes = {p[len(root) + 1:]: int(i.get("size") or 0) for p, i in fs.find(root, detail=True).items()}
    except FileNotFoundError:
        return None
    for rel, size in (rec.get("files") or {}).items():
        if sizes.get(rel) != size:
            return None
    return rec
