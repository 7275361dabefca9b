"""Read the statistics tables of an annotation output folder and derive the columns gates check.

Layout (docs/architecture.md): ``OUT/stats/objects.parquet`` (one row per annotated
(segment, camera, object) clip), ``OUT/stats/segments.parquet`` (one row per segment, with one
``rejected_<reason>`` count per filter), ``OUT/stats/rejections.parquet`` (one row per rejected
(segment, camera, object, reason)). Paths go through fsspec, so ``OUT`` may be local or a URL.
"""
from __future__ import annotations

import hashlib
import io
import posixpath
from dataclasses import dataclass, field

import fsspec
import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from drivetrack.gates.config import PERCENTILES
from drivetrack.outputs import CLIPS, clip_stem, parse_table_path

SPEED_ERR_COLUMNS = tuple(f"speed_err_{p}" for p in PERCENTILES)
#: The same percentiles for the same tracks under the labelled poses (``drivetrack.tracks.consistency``);
#: written by annotate since pose refinement, absent from older outputs.
LABEL_SPEED_ERR_COLUMNS = tuple(f"label_speed_err_{p}" for p in PERCENTILES)
#: Derived: speed_err_p50 - label_speed_err_p50, m/s (what pose refinement did to the consistency).
REFINE_SPEED_ERR_INCREASE = "refine_speed_err_p50_increase_mps"

OBJECT_COLUMNS = ("split", "segment", "camera", "object_id", "file", "num_tracks", "num_frames",
                  "visible_fraction", "min_camera_distance_m", *SPEED_ERR_COLUMNS,
                  "num_nonfinite_visible", "num_visible_outside_image")
SEGMENT_COLUMNS = ("split", "segment", "status", "num_object_clips_considered",
                   "num_object_clips_annotated")
REJECTION_COLUMNS = ("segment", "reason")

#: Columns that identify a row in each table (shown for every failing row).
OBJECT_KEYS = ("split", "segment", "camera", "object_id")
SEGMENT_KEYS = ("split", "segment")
SPLIT_KEYS = ("split",)

REJECTED_PREFIX = "rejected_"
SHARE_PREFIX = "rejected_share_"
REACHED_PREFIX = "reached_"


def filter_order(reasons: list[str]) -> list[str]:
    """``reasons`` in the order the track stage applies its filters (``REJECTION_REASONS``);
    reasons it does not know follow in the given order."""
    from drivetrack.outputs import REJECTION_REASONS

    known = [r for r in REJECTION_REASONS if r in reasons]
    return known + [r for r in reasons if r not in REJECTION_REASONS]


class GateInputError(ValueError):
    """An input table is missing or lacks columns: names the file and the columns."""


@dataclass
class GateTables:
    """The tables the suites validate (pandas DataFrames, one row per entity)."""

    objects: pd.DataFrame
    segments: pd.DataFrame
    splits: pd.DataFrame
    rejection_reasons: list[str] = field(default_factory=list)
    files: dict[str, str] = field(default_factory=dict)  # table name -> path read
    #: ``stats/{name}.parquet`` -> sha256 of the bytes the gates validated (the report's binding)
    sha256: dict[str, str] = field(default_factory=dict)


def _read_table(fs, root: str, name: str, required: tuple[str, ...], digests: dict[str, str],
                optional: bool = False) -> tuple[pd.DataFrame | None, str]:
    """Read ``stats/{name}.parquet`` once (its bytes are hashed into ``digests`` and parsed, so
    the sha256 is that of exactly what is validated)."""
    path = posixpath.join(root, "stats", f"{name}.parquet")
    if not fs.exists(path):
        if optional:
            return None, path
        raise GateInputError(f"statistics table {path} does not exist (expected layout: "
                             f"OUT/stats/{name}.parquet, see docs/architecture.md)")
    try:
        with fs.open(path, "rb") as f:
            data = f.read()
        digests[f"stats/{name}.parquet"] = hashlib.sha256(data).hexdigest()
        table = pq.read_table(io.BytesIO(data))
    except Exception as exc:  # pyarrow raises several types for corrupt files
        raise GateInputError(f"statistics table {path} cannot be read as parquet: {exc}") from exc
    missing = [c for c in required if c not in table.column_names]
    if missing:
        raise GateInputError(f"statistics table {path} lacks column(s) {missing}; "
                             f"found {table.column_names}")
    return table.to_pandas(), path


def _relative(file_value: str, fs, root: str) -> str:
    """The path of ``file_value`` relative to the output folder ``root`` (a path of ``fs``).

    ``file`` may be relative to OUT (``tracks/training/waymo_....npz``), an absolute path or a URL.
    """
    value = str(file_value)
    if "://" in value or value.startswith("/"):
        value = fs._strip_protocol(value)
        prefix = root.rstrip("/") + "/"
        return value[len(prefix):] if value.startswith(prefix) else value
    return value[2:] if value.startswith("./") else value


def _stem_or_none(segment: str, camera: str, object_id: str) -> str | None:
    try:
        return clip_stem(segment, camera, object_id)
    except ValueError:  # an invalid name in the table: no clip can match it
        return None


def _clips_on_disk(fs, root: str, all_files: set[str]) -> dict[str, set[str]]:
    """Clips table (relative path) -> the clip ids it holds; a table that cannot be read raises
    GateInputError naming it."""
    from drivetrack.compact.read import CompactFormatError, clip_ids

    out = {}
    for rel in sorted(all_files):
        parsed = parse_table_path(rel)
        if parsed and parsed[0] == CLIPS:
            try:
                out[rel] = set(clip_ids(fs, f"{root}/{rel}", rel))
            except CompactFormatError as error:
                raise GateInputError(str(error)) from error
    return out


def read_gate_tables(out_dir: str, cfg: dict) -> GateTables:
    """Read ``OUT/stats/*.parquet`` and add the derived columns the gates validate.

    Derived columns:
      objects: ``speed_err_num_nonfinite`` (NaN or infinite speed-error percentiles, 0..5),
        ``refine_speed_err_p50_increase_mps`` (speed_err_p50 - label_speed_err_p50, when the
        table has the labels' percentiles; 0 where the labels' figure is NaN),
        ``file_exists`` (bool: the row's ``file``, its segment's clips table, is in the output
        folder and holds a row for the clip).
      segments: ``reached_<reason>`` (clips that reached the filter: considered minus the clips
        rejected by the filters applied before it, in the track stage's order) and
        ``rejected_share_<reason>`` (rejected_<reason> / reached_<reason>, the filter's rejection
        rate; NaN when fewer than ``rejected_share_min_considered`` clips reached it),
        ``num_object_rows`` (rows of objects.parquet for the segment), ``rejections_mismatch``
        (sum over reasons of |rejected_<reason> - rows of rejections.parquet|).
      splits (built here): ``split``, ``num_segments``, ``num_object_clips``, ``num_tracks``,
        ``num_clips_on_disk`` (rows of the ``clips/{split}/*.parquet`` tables).
    """
    fs, root = fsspec.core.url_to_fs(out_dir)
    root = root.rstrip("/") or "/"
    if not fs.isdir(root):
        raise GateInputError(f"annotation output folder {out_dir} does not exist")
    digests: dict[str, str] = {}
    objects, objects_path = _read_table(fs, root, "objects", OBJECT_COLUMNS, digests)
    segments, segments_path = _read_table(fs, root, "segments", SEGMENT_COLUMNS, digests)
    check_rej = bool(cfg["segment"]["check_rejections_table"]["value"])
    rejections, rejections_path = _read_table(fs, root, "rejections", REJECTION_COLUMNS, digests,
                                              optional=not check_rej)

    for col in ("split", "segment", "camera", "object_id", "file"):
        objects[col] = objects[col].astype(str)
    for col in ("split", "segment", "status"):
        segments[col] = segments[col].astype(str)

    # -- objects ---------------------------------------------------------------------------------
    speed = objects[list(SPEED_ERR_COLUMNS)].apply(pd.to_numeric, errors="coerce")
    objects["speed_err_num_nonfinite"] = (~np.isfinite(speed.to_numpy(dtype=float))).sum(axis=1)
    if set(LABEL_SPEED_ERR_COLUMNS) <= set(objects.columns):
        label_p50 = pd.to_numeric(objects["label_speed_err_p50"], errors="coerce")
        # NaN labels' figure (no label in some clip frame): no comparison, counted as not worse
        objects[REFINE_SPEED_ERR_INCREASE] = (speed["speed_err_p50"] - label_p50).fillna(0.0)
    all_files = {p[len(root):].lstrip("/") for p in fs.find(root)} if root != "/" else set()
    clips_on_disk = _clips_on_disk(fs, root, all_files)
    rel = objects["file"].map(lambda f: _relative(f, fs, root))
    stems = [_stem_or_none(s, c, o) for s, c, o in zip(objects["segment"], objects["camera"], objects["object_id"])]
    objects["file_exists"] = [stem is not None and stem in clips_on_disk.get(r, ()) for r, stem in zip(rel, stems)]

    # -- segments --------------------------------------------------------------------------------
    reasons = filter_order([c[len(REJECTED_PREFIX):] for c in segments.columns
                            if c.startswith(REJECTED_PREFIX) and not c.startswith(SHARE_PREFIX)])
    considered = pd.to_numeric(segments["num_object_clips_considered"], errors="coerce")
    min_reached = max(cfg["segment"]["rejected_share_min_considered"]["value"], 1)
    reached = considered.copy()
    for reason in reasons:  # filters run in order: each sees the clips the earlier ones kept
        count = pd.to_numeric(segments[REJECTED_PREFIX + reason], errors="coerce")
        segments[REACHED_PREFIX + reason] = reached
        segments[SHARE_PREFIX + reason] = (count / reached).where(reached >= min_reached)
        reached = reached - count
    per_segment = objects.groupby("segment").size()
    segments["num_object_rows"] = segments["segment"].map(per_segment).fillna(0).astype(int)
    if rejections is not None:
        rejections["segment"] = rejections["segment"].astype(str)
        rejections["reason"] = rejections["reason"].astype(str)
        listed = rejections.groupby(["segment", "reason"]).size().unstack(fill_value=0)
        listed = listed.reindex(index=segments["segment"], fill_value=0)
        mismatch = np.zeros(len(segments), dtype=np.int64)
        for reason in sorted(set(reasons) | set(listed.columns)):
            stated = (pd.to_numeric(segments[REJECTED_PREFIX + reason], errors="coerce")
                      .fillna(0).to_numpy() if reason in reasons else np.zeros(len(segments)))
            found = listed[reason].to_numpy() if reason in listed.columns else np.zeros(len(segments))
            mismatch += np.abs(stated - found).astype(np.int64)
        segments["rejections_mismatch"] = mismatch

    # -- splits ----------------------------------------------------------------------------------
    split_names = sorted(set(segments["split"]) | set(objects["split"]))
    by_split = objects.groupby("split")
    splits = pd.DataFrame({"split": split_names})
    splits["num_segments"] = splits["split"].map(segments.groupby("split").size()).fillna(0).astype(int)
    splits["num_object_clips"] = splits["split"].map(by_split.size()).fillna(0).astype(int)
    tracks = pd.to_numeric(objects["num_tracks"], errors="coerce").groupby(objects["split"]).sum()
    splits["num_tracks"] = splits["split"].map(tracks).fillna(0).astype(int)
    on_disk = pd.Series([parse_table_path(r)[1] for r, ids in clips_on_disk.items() for _ in ids], dtype=object)
    splits["num_clips_on_disk"] = (splits["split"].map(on_disk.value_counts())
                                   .fillna(0).astype(int))
    paths = {"objects": objects_path, "segments": segments_path}
    if rejections is not None:
        paths["rejections"] = rejections_path
    return GateTables(objects=objects, segments=segments, splits=splits,
                      rejection_reasons=reasons, files=paths, sha256=digests)
