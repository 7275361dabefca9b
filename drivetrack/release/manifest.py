"""Manifests: semantic versions, streaming sha256, the canonical manifest and its hash, SHA256SUMS,
and what a release records about its inputs (run.json, stats/*.parquet).

The manifest (``{dataset}/{version}/manifest.json``) is the commit record of a release: a version
exists exactly when its manifest exists. Its ``manifest_sha256`` is the sha256 of the canonical
JSON (keys sorted, separators ``(",", ":")``, ASCII) of the manifest without that key.
"""
from __future__ import annotations

import hashlib
import io
import json
import re
import subprocess
from dataclasses import dataclass
from functools import total_ordering
from pathlib import Path

from drivetrack.outputs import DRIVETRACK, TAPVID3D, data_splits_of, parse_clip_path, parse_table_path
from drivetrack.names import InvalidNameError, check_name
from drivetrack.release.errors import (InvalidDatasetError, InvalidSourceError, InvalidVersionError,
                                       ManifestError)
from drivetrack.release.store import CHUNK_BYTES, iter_chunks

MANIFEST_FORMAT = "drivetrack-release-manifest/1"
MANIFEST_NAME = "manifest.json"
SUMS_NAME = "SHA256SUMS"
CARD_NAME = "README.md"
CROISSANT_NAME = "croissant.json"
RESERVED_NAMES = (MANIFEST_NAME, SUMS_NAME, CARD_NAME, CROISSANT_NAME)
"""Top-level names the release writes itself; a source folder may not contain them."""

# ---- semantic versions (https://semver.org 2.0.0) -----------------------------------------

_SEMVER = re.compile(
    r"(0|[1-9]\d*)\.(0|[1-9]\d*)\.(0|[1-9]\d*)"
    r"(?:-((?:0|[1-9]\d*|\d*[A-Za-z-][0-9A-Za-z-]*)(?:\.(?:0|[1-9]\d*|\d*[A-Za-z-][0-9A-Za-z-]*))*))?"
    r"(?:\+([0-9A-Za-z-]+(?:\.[0-9A-Za-z-]+)*))?")
"""Applied with :meth:`re.Pattern.fullmatch` only: ``match`` with ``$`` accepts a trailing newline."""


@total_ordering
@dataclass(frozen=True)
class SemVer:
    """A parsed semantic version; ordering is semver precedence (build metadata ignored)."""

    major: int
    minor: int
    patch: int
    prerelease: tuple = ()
    build: str = ""

    @classmethod
    def parse(cls, text: str) -> "SemVer":
        m = _SEMVER.fullmatch(text) if isinstance(text, str) else None
        if not m:
            raise InvalidVersionError(
                f"version {text!r} is not a semantic version MAJOR.MINOR.PATCH[-PRERELEASE][+BUILD] "
                f"(e.g. 1.0.0, 1.2.0-rc.1)")
        pre = tuple(int(p) if p.isdigit() else p for p in m.group(4).split(".")) if m.group(4) else ()
        return cls(int(m.group(1)), int(m.group(2)), int(m.group(3)), pre, m.group(5) or "")

    def _key(self):
        # A release sorts after its pre-releases; numeric identifiers sort before alphanumeric ones.
        pre = tuple((0, p, "") if isinstance(p, int) else (1, 0, p) for p in self.prerelease)
        return (self.major, self.minor, self.patch, 0 if self.prerelease else 1, pre)

    def __lt__(self, other: "SemVer") -> bool:
        return self._key() < other._key()

    def __eq__(self, other) -> bool:
        return isinstance(other, SemVer) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    def __str__(self) -> str:
        s = f"{self.major}.{self.minor}.{self.patch}"
        if self.prerelease:
            s += "-" + ".".join(str(p) for p in self.prerelease)
        if self.build:
            s += "+" + self.build
        return s


def check_version(version: str) -> str:
    """Return ``version`` if it is a semantic version without build metadata, else raise
    :class:`InvalidVersionError` (``1.0.0+a`` and ``1.0.0+b`` have equal precedence: ambiguous)."""
    if SemVer.parse(version).build:
        raise InvalidVersionError(
            f"version {version!r}: build metadata ('+...') is not allowed in release versions, because "
            f"versions differing only in it have equal precedence; use a pre-release tag (1.0.0-rc.1)")
    return version


def check_dataset(name: str) -> str:
    """Return ``name`` if it may be a dataset name (it becomes a folder name), else raise
    :class:`InvalidDatasetError`. The one check every release command uses, before any path is built;
    the rule is :func:`drivetrack.names.check_name` ``("dataset", ...)`` (full match, no ``.``/``..``,
    no leading ``.`` or ``_``, no separators or control characters)."""
    try:
        return check_name("dataset", name)
    except InvalidNameError as e:
        raise InvalidDatasetError(str(e)) from None


# ---- hashing -------------------------------------------------------------------------

@dataclass(frozen=True)
class FileEntry:
    """One file of a release: ``path`` relative to the version folder, ``size`` bytes, hex ``sha256``."""

    path: str
    size: int
    sha256: str

    def to_json(self) -> dict:
        return {"path": self.path, "size": self.size, "sha256": self.sha256}


def sha256_stream(f, chunk_bytes: int = CHUNK_BYTES) -> tuple[str, int]:
    """sha256 hex digest and byte count of an open binary file, read in chunks."""
    h = hashlib.sha256()
    n = 0
    for chunk in iter_chunks(f, chunk_bytes):
        h.update(chunk)
        n += len(chunk)
    return h.hexdigest(), n


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def check_release_path(path: str, where: str) -> str:
    """Reject paths that cannot be written into SHA256SUMS or a store safely."""
    bad = [c for c in ("\n", "\r", "\\") if c in path]
    parts = path.split("/")
    if bad or any(p in ("", ".", "..") for p in parts):
        raise InvalidSourceError(
            f"{where}: file name {path!r} cannot be published (no newlines, backslashes, "
            f"empty, '.' or '..' components)")
    return path


# ---- canonical manifest -----------------------------------------------------------------

def canonical_json(obj) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True,
                      allow_nan=False).encode("ascii")


def manifest_hash(manifest: dict) -> str:
    """sha256 of the canonical manifest without its ``manifest_sha256`` key."""
    body = {k: v for k, v in manifest.items() if k != "manifest_sha256"}
    return hashlib.sha256(canonical_json(body)).hexdigest()


def seal_manifest(manifest: dict) -> dict:
    """Return the manifest with ``manifest_sha256`` set."""
    out = {k: v for k, v in manifest.items() if k != "manifest_sha256"}
    out["manifest_sha256"] = manifest_hash(out)
    return out


def dump_manifest(manifest: dict) -> bytes:
    return (json.dumps(manifest, indent=1, sort_keys=True, ensure_ascii=True, allow_nan=False)
            + "\n").encode("ascii")


def parse_manifest(data: bytes, where: str) -> dict:
    """Parse a manifest and check its top-level hash; raise :class:`ManifestError` naming ``where``."""
    try:
        manifest = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ManifestError(f"{where}: not valid JSON ({e})") from e
    if not isinstance(manifest, dict) or manifest.get("format") != MANIFEST_FORMAT:
        raise ManifestError(f"{where}: not a {MANIFEST_FORMAT} manifest "
                            f"(format={manifest.get('format') if isinstance(manifest, dict) else None!r})")
    for key in ("files", "version", "dataset", "manifest_sha256"):
        if key not in manifest:
            raise ManifestError(f"{where}: missing key {key!r}")
    found = manifest_hash(manifest)
    if found != manifest["manifest_sha256"]:
        raise ManifestError(f"{where}: manifest_sha256 is {manifest['manifest_sha256']} but the "
                            f"manifest content hashes to {found}: the manifest was modified")
    return manifest


def manifest_entries(manifest: dict) -> dict[str, FileEntry]:
    return {f["path"]: FileEntry(f["path"], int(f["size"]), f["sha256"]) for f in manifest["files"]}


# ---- SHA256SUMS ---------------------------------------------------------------------------

def render_sha256sums(entries: list[FileEntry]) -> bytes:
    """``sha256sum`` output format (hash, two spaces, path; binary-safe for ``sha256sum -c``)."""
    return "".join(f"{e.sha256}  {e.path}\n" for e in sorted(entries, key=lambda e: e.path)).encode()


# ---- what the release records about its inputs ---------------------------------------------

from drivetrack.provenance import code_version  # noqa: E402,F401  (re-exported: publish imports it here)


def read_run_json(data: bytes | None, where: str) -> dict | None:
    """Parse ``run.json`` (config, code_version, seed, segments with source checksums)."""
    if data is None:
        return None
    try:
        run = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InvalidSourceError(f"{where}: run.json is not valid JSON ({e})") from e
    if not isinstance(run, dict):
        raise InvalidSourceError(f"{where}: run.json must hold a JSON object, found {type(run).__name__}")
    segs = run.get("segments")
    if segs is not None and not isinstance(segs, list):
        raise InvalidSourceError(f"{where}: run.json 'segments' must be a list, found {type(segs).__name__}")
    return run


def _num(x):
    """JSON-safe number (None for NaN)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    if v != v or v in (float("inf"), float("-inf")):
        return None
    return int(v) if float(v).is_integer() and abs(v) < 2**53 else round(v, 6)


def statistics_from_parquet(tables: dict[str, bytes]) -> dict:
    """Release statistics from ``stats/*.parquet`` contents (``{file name: bytes}``).

    Missing files or columns are tolerated: only what is present is summarised, and the
    columns seen are recorded under ``columns``.
    """
    import pyarrow.parquet as pq

    stats: dict = {}
    for name, data in sorted(tables.items()):
        try:
            df = pq.read_table(io.BytesIO(data)).to_pandas()
        except Exception as e:  # pyarrow raises several types for bad files
            raise InvalidSourceError(f"stats/{name}: cannot be read as parquet ({e})") from e
        key = name.rsplit(".", 1)[0]
        entry: dict = {"rows": int(len(df)), "columns": list(map(str, df.columns))}
        if key == "objects":
            for col in ("split", "object_type", "camera"):
                if col in df:
                    entry[f"clips_by_{col}"] = {str(k): int(v) for k, v in
                                                df[col].value_counts().sort_index().items()}
            if "segment" in df:
                entry["segments"] = int(df["segment"].nunique())
            for col in ("num_tracks", "num_nonfinite_visible", "num_visible_outside_image"):
                if col in df:
                    entry[f"{col}_total"] = _num(df[col].sum())
            for col in ("num_frames", "visible_fraction", "min_camera_distance_m", "box_speed_mean_mps",
                        "speed_err_p50", "speed_err_p95"):
                if col in df and len(df):
                    entry[f"{col}_median"] = _num(df[col].median())
        elif key == "segments":
            if "status" in df:
                entry["by_status"] = {str(k): int(v) for k, v in df["status"].value_counts().sort_index().items()}
            for col in df.columns:
                if str(col).startswith("rejected_") or str(col) in (
                        "num_object_clips_considered", "num_object_clips_annotated", "num_frames"):
                    entry[f"{col}_total"] = _num(df[col].sum())
        elif key == "rejections":
            if "reason" in df:
                entry["by_reason"] = {str(k): int(v) for k, v in df["reason"].value_counts().sort_index().items()}
        stats[key] = entry
    return stats


def counts_from_files(entries: list[FileEntry], splits: list[str], clip_counts: dict[str, int] | None = None) -> dict:
    """File and byte counts, in total and per split: ``clips`` = rows of the split's clips tables
    (``clip_counts``; DriveTrack npz files without it), ``npz_clips`` / ``tapvid3d_clips`` =
    exported npz files of each layout, ``bytes`` = the split's data files (tables and npz)."""
    out: dict = {"files": len(entries), "bytes": int(sum(e.size for e in entries)), "splits": {}}
    parsed = [(e, parse_clip_path(e.path) or _table_split(e.path)) for e in entries]
    for split in splits:
        mine = [(e, p) for e, p in parsed if p and p[1] == split]
        npz = sum(1 for _, p in mine if p[0] == DRIVETRACK)
        out["splits"][split] = {
            "clips": int(clip_counts.get(split, 0)) if clip_counts is not None else npz,
            "npz_clips": npz,
            "tapvid3d_clips": sum(1 for _, p in mine if p[0] == TAPVID3D),
            "bytes": int(sum(e.size for e, _ in mine))}
    return out


def _table_split(path: str) -> tuple[str, str] | None:
    parsed = parse_table_path(path)
    return (parsed[0], parsed[1]) if parsed else None


def splits_from_paths(paths: list[str]) -> list[str]:
    """Splits holding clips (``clips/{split}/*.parquet`` tables, or exported ``tracks/{split}/*.npz`` /
    ``tapvid3d/{split}/*.npz``).

    Splits are recognised by where their clips are (:mod:`drivetrack.outputs`), never by a folder
    name, so the Waymo split ``validation`` and the gate reports in ``validation/`` cannot mix.
    """
    return data_splits_of(paths)