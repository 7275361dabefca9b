"""Assemble the release folder from the work folder: every done segment's files (hard links
when local), the per-segment statistics tables merged into ``stats/*.parquet`` (failed segments
added to ``stats/segments.parquet`` as ``status=failed`` rows with their error), ``run.json``
(:func:`release_run_record`)."""
from __future__ import annotations

import os
import shutil

import fsspec
import pyarrow as pa
import pyarrow.parquet as pq

from drivetrack.storage import atomic_local_path, is_local, write_json, write_parquet
from drivetrack.release.work import DONE


def release_run_record(*, config: dict, config_fingerprint: str, code_fingerprint: str, release_fingerprint: str,
                       dataset: str, version: str, source: str, splits: list[str], plan: list[dict],
                       done: set, code_version: dict) -> dict:
    """The release folder's ``run.json``: configuration, code, fingerprints and every planned
    segment (``plan`` rows: split, segment, key, checksums) with ``done`` or ``failed`` (``done``:
    the (split, segment) pairs that finished)."""
    return {"config": config, "config_fingerprint": config_fingerprint, "code_version": code_version,
            "code_fingerprint": code_fingerprint, "release_fingerprint": release_fingerprint, "dataset": dataset,
            "version": version, "source": source, "splits": splits,
            "segments": [{"split": p["split"], "segment": p["segment"], "key": p["key"],
                          "source_checksums": p["checksums"],
                          "status": "done" if (p["split"], p["segment"]) in done else "failed"}
                         for p in plan]}


def assemble_release_folder(out: str, records: list[dict], failed: list[dict], run: dict, work: str) -> dict:
    """``records``: completion records with ``dir`` (their segment folder). Returns counts."""
    ofs, oroot = fsspec.core.url_to_fs(str(out))
    oroot = oroot.rstrip("/")
    tables: dict[str, list[pa.Table]] = {}
    placed: dict[str, str] = {}
    n_files = 0
    for rec in records:
        sfs, sroot = fsspec.core.url_to_fs(rec["dir"])
        sroot = sroot.rstrip("/")
        for rel in sorted(rec.get("files") or {}):
            if rel == DONE:
                continue
            src = f"{sroot}/{rel}"
            if rel.startswith("stats/") and rel.endswith(".parquet") and rel.count("/") == 1:
                with sfs.open(src, "rb") as f:
                    tables.setdefault(rel, []).append(pq.read_table(f))
                continue
            if rel in placed:
                raise ValueError(f"{rel} is written by two segments ({placed[rel]} and "
                                 f"{rec['split']}/{rec['segment']}): file names must be unique per segment")
            placed[rel] = f"{rec['split']}/{rec['segment']}"
            dst = f"{oroot}/{rel}"
            if is_local(sfs) and is_local(ofs):
                ofs.makedirs(dst.rsplit("/", 1)[0], exist_ok=True)
                try:
                    os.link(src, dst)
                    n_files += 1
                    continue
                except OSError:
                    pass
            with sfs.open(src, "rb") as fi, atomic_local_path(ofs.unstrip_protocol(dst)) as tmp, \
                    open(tmp, "wb") as fo:
                shutil.copyfileobj(fi, fo, 1 << 23)
            n_files += 1
    # every table exists, with its schema, even when no segment is done; failed segments are rows
    from drivetrack.annotate import SegmentResult, write_tables
    from drivetrack.tracks import segment_stats

    failed_results = []
    for f in failed:
        r = SegmentResult(split=f["split"], segment=f["segment"], status="failed", error=f["error"],
                          stage=f.get("stage") or "")
        r.segment_row = segment_stats(f["split"], f["segment"], None, (), status="failed",
                                      error=f"[{f.get('stage') or 'segment'}] {f['error']}")
        failed_results.append(r)
    base_url = out if "://" in str(out) else oroot
    for name, url in write_tables(base_url, failed_results).items():
        rel = f"stats/{name}.parquet"
        with ofs.open(f"{oroot}/{rel}", "rb") as f:
            base = pq.read_table(f)
        tables[rel] = tables.get(rel, []) + ([base] if base.num_rows or rel not in tables else [])
    for rel, parts in sorted(tables.items()):
        merged = pa.concat_tables(parts, promote_options="permissive")
        write_parquet(ofs.unstrip_protocol(f"{oroot}/{rel}"), merged)
        n_files += 1
    write_json(ofs.unstrip_protocol(f"{oroot}/run.json"), run, indent=1, sort_keys=True, default=str)
    return {"files": n_files + 1, "segments": len(records), "failed": len(failed),
            "tables": {rel: sum(t.num_rows for t in parts) for rel, parts in tables.items()}}
