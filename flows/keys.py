"""Content keys for resume and caching: a segment's key is the hash of its source files'
checksums, the configuration's fingerprint and the code's fingerprint; a release's fingerprint
is the hash of its segments' keys and outcomes, the gate configuration and the code.

Same key, same outputs: a re-run reuses every segment whose key has a completion record and
recomputes the rest; a scheduled run whose release fingerprint equals the latest published
one's publishes nothing.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import fsspec

import drivetrack
from drivetrack.waymo.schema import COMPONENTS

PACKAGE = Path(drivetrack.__file__).resolve().parent
NOT_OUTPUT_CODE = ("commands/", "cli.py", "status.py", "release/", "gates/", "synth/", "evaluation/")
"""Package paths whose code does not change a segment's outputs (they still enter the release
fingerprint)."""


def sha256_json(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str).encode()).hexdigest()


def code_fingerprint(*, outputs_only: bool = False) -> str:
    """sha256 over the drivetrack package's ``*.py`` files (relative path + bytes).
    ``outputs_only`` leaves out :data:`NOT_OUTPUT_CODE` (the segment key's code part)."""
    h = hashlib.sha256(f"drivetrack {drivetrack.__version__}\n".encode())
    for p in sorted(PACKAGE.rglob("*.py")):
        rel = p.relative_to(PACKAGE).as_posix()
        if outputs_only and any(rel == x or rel.startswith(x) for x in NOT_OUTPUT_CODE):
            continue
        h.update(rel.encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


def _local_sha256(path: str, memo: dict) -> str:
    st = os.stat(path)
    tag = f"{st.st_size}:{st.st_mtime_ns}"
    hit = memo.get(path)
    if hit and hit[0] == tag:
        return hit[1]
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    memo[path] = (tag, "sha256:" + h.hexdigest())
    return memo[path][1]


def source_checksums(source: str, split: str, segment: str, *, storage_options: dict | None = None,
                     memo: dict | None = None) -> dict[str, str]:
    """Component name -> checksum of ``{source}/{split}/{component}/{segment}.parquet`` for every
    component present. Local files: sha256 of the bytes (memoised on size and mtime in ``memo``);
    object stores: the checksum the store reports (S3 ETag, GCS md5/crc32c) with the size.
    Raises FileNotFoundError naming the segment when no component file exists."""
    fs, base = fsspec.core.url_to_fs(str(source), **(storage_options or {}))
    base = base.rstrip("/")
    local = "file" in (fs.protocol if isinstance(fs.protocol, tuple) else (fs.protocol,))
    memo = {} if memo is None else memo
    out = {}
    for comp in COMPONENTS:
        path = f"{base}/{split}/{comp}/{segment}.parquet"
        try:
            info = fs.info(path)
        except FileNotFoundError:
            continue
        if local:
            out[comp] = _local_sha256(path, memo)
        else:
            tag = info.get("ETag") or info.get("md5Hash") or info.get("crc32c") or info.get("checksum") \
                or info.get("LastModified") or info.get("mtime")
            out[comp] = f"{info.get('size')}:{str(tag).strip(chr(34))}"
    if not out:
        raise FileNotFoundError(f"segment {segment!r}: no component file under {source}/{split}/*/"
                                f"{segment}.parquet")
    return out


def segment_key(split: str, segment: str, checksums: dict[str, str], config_fingerprint: str,
                code: str) -> str:
    """The content key of one segment's outputs (hex sha256)."""
    return sha256_json({"split": split, "segment": segment, "source": checksums, "config": config_fingerprint,
                        "code": code})


def release_fingerprint(dataset: str, segments: list[dict], *, config_fingerprint: str, gates: dict | str | None,
                        code: str) -> str:
    """Hash of what a release would contain: every segment's (split, segment, key, state),
    the configuration, the gate configuration and the full code fingerprint."""
    rows = sorted((s["split"], s["segment"], s.get("key"), s.get("state")) for s in segments)
    return sha256_json({"dataset": dataset, "segments": rows, "config": config_fingerprint, "gates": gates,
                        "code": code})
