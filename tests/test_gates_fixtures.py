"""Helpers (no tests): annotation output folders with statistics tables written directly.

``make_output(root, defect=None)`` writes a small, plausible release (2 splits, 4 segments, 3
objects per segment, FRONT camera) whose speed errors sit at the paper's scale, then applies one
defect. The clips tables (release layout v2) hold only the clip ids (other columns null): the
gates read the statistics tables and check that each object's clip is a row of its clips table.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

PAPER = np.array([0.0651, 0.1260, 0.2471, 0.5497, 0.8687])
REASONS = ("camera", "too_few_frames", "no_visible_points")  # a subset of the track stage's

#: The objects a defect touches, as (segment, camera, object_id).
NOISY = [("seg_a0", "FRONT", "obj_0"), ("seg_a0", "FRONT", "obj_1"), ("seg_a1", "FRONT", "obj_2"),
         ("seg_b0", "FRONT", "obj_0"), ("seg_b0", "FRONT", "obj_1"), ("seg_b1", "FRONT", "obj_0"),
         ("seg_b1", "FRONT", "obj_2")]
NONFINITE = ("seg_a1", "FRONT", "obj_1")
OUTSIDE = ("seg_b0", "FRONT", "obj_2")
NAN_SPEED = ("seg_b1", "FRONT", "obj_1")
#: Objects whose refined poses are less consistent than their labels (defect ``refine_worse``).
REFINE_WORSE = [("seg_a0", "FRONT", "obj_2"), ("seg_b1", "FRONT", "obj_0")]
EMPTY_SEGMENT = "seg_a1"

DEFECTS = ("label_noise", "corrupt_tracks", "empty_segment", "nan_speed_err", "refine_worse")


def good_tables(seed: int = 0) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """(objects, segments, rejections) of a release that passes every default gate."""
    rng = np.random.default_rng(seed)
    rows, seg_rows, rej_rows = [], [], []
    for split, tag in (("training", "a"), ("validation", "b")):
        for s in range(2):
            segment = f"seg_{tag}{s}"
            for o in range(3):
                scale = rng.uniform(0.6, 1.4)
                err = PAPER * scale
                rows.append(dict(
                    split=split, segment=segment, camera="FRONT", object_id=f"obj_{o}",
                    object_type="VEHICLE", file=f"clips/{split}/{segment}.parquet",
                    num_tracks=int(rng.integers(200, 2000)), num_frames=int(rng.integers(24, 199)),
                    visible_fraction=float(rng.uniform(0.3, 0.95)),
                    min_camera_distance_m=float(rng.uniform(4, 19)),
                    box_speed_mean_mps=float(rng.uniform(0, 15)),
                    **{f"speed_err_{p}": float(v) for p, v in zip(("p25", "p50", "p75", "p95", "p99"), err)},
                    # the labels' poses: less consistent than the refined ones (label jitter)
                    **{f"label_speed_err_{p}": float(v) * 1.5
                       for p, v in zip(("p25", "p50", "p75", "p95", "p99"), err)},
                    num_nonfinite_visible=0, num_visible_outside_image=0))
            rejected = {r: int(rng.integers(0, 4)) for r in REASONS}
            seg_rows.append(dict(split=split, segment=segment, status="done", error="",
                                 num_frames=199, num_objects_labelled=40,
                                 num_object_clips_considered=3 + sum(rejected.values()),
                                 num_object_clips_annotated=3,
                                 **{f"rejected_{r}": n for r, n in rejected.items()}))
            for r, n in rejected.items():
                rej_rows += [dict(segment=segment, camera="FRONT_LEFT", object_id=f"rej_{r}_{i}",
                                  reason=r) for i in range(n)]
    return pd.DataFrame(rows), pd.DataFrame(seg_rows), pd.DataFrame(rej_rows)


def _match(objects: pd.DataFrame, key: tuple[str, str, str]) -> pd.Series:
    return ((objects["segment"] == key[0]) & (objects["camera"] == key[1])
            & (objects["object_id"] == key[2]))


def apply_defect(objects, segments, rejections, defect):
    objects, segments, rejections = objects.copy(), segments.copy(), rejections.copy()
    cols = [f"speed_err_{p}" for p in ("p25", "p50", "p75", "p95", "p99")]
    if defect == "label_noise":
        # boxes jittered by decimetres per frame: track speeds differ from box speeds by m/s
        for i, key in enumerate(NOISY):
            objects.loc[_match(objects, key), cols] = PAPER * 25 + 0.1 * i
            # ... under the labels as under the poses used (refinement kept the labels)
            objects.loc[_match(objects, key), [f"label_{c}" for c in cols]] = PAPER * 25 + 0.1 * i
    elif defect == "corrupt_tracks":
        objects.loc[_match(objects, NONFINITE), "num_nonfinite_visible"] = 7
        objects.loc[_match(objects, OUTSIDE), "num_visible_outside_image"] = 12
    elif defect == "empty_segment":
        objects = objects[objects["segment"] != EMPTY_SEGMENT].reset_index(drop=True)
        segments.loc[segments["segment"] == EMPTY_SEGMENT, "num_object_clips_annotated"] = 0
    elif defect == "nan_speed_err":
        objects.loc[_match(objects, NAN_SPEED), "speed_err_p75"] = np.nan
        objects.loc[_match(objects, NAN_SPEED), "speed_err_p99"] = np.inf
    elif defect == "refine_worse":
        # the refinement registered to the wrong points: its poses move unlike a rigid body
        label_cols = [f"label_{c}" for c in cols]
        for key in REFINE_WORSE:
            objects.loc[_match(objects, key), label_cols] = objects.loc[_match(objects, key), cols].to_numpy()
            objects.loc[_match(objects, key), cols] += 0.3
    elif defect is not None:
        raise ValueError(f"unknown defect {defect!r}; known {DEFECTS}")
    return objects, segments, rejections


def write_output(root: Path, objects, segments, rejections, files: bool = True) -> Path:
    stats = root / "stats"
    stats.mkdir(parents=True, exist_ok=True)
    objects.to_parquet(stats / "objects.parquet", index=False)
    segments.to_parquet(stats / "segments.parquet", index=False)
    rejections.to_parquet(stats / "rejections.parquet", index=False)
    if files:
        # ``file`` relative, absolute or a file:// URL: one table per path
        where = objects["file"].map(lambda f: str(root / f.removeprefix("file://")))
        for path, rows in objects.groupby(where):
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            Path(path).write_bytes(clips_table_bytes(rows))
    return root


def clips_table_bytes(objects: pd.DataFrame, drop: tuple[str, str, str] | None = None) -> bytes:
    """A clips table (v2 schema) holding a row per object of ``objects`` (but ``drop``), ids only."""
    import io

    import pyarrow as pa
    import pyarrow.parquet as pq

    from drivetrack.compact.layout import CLIPS_SCHEMA

    rows = [{"clip": f"waymo_{s}_{c}_{o}", "segment": s, "camera": c, "object_id": o}
            for s, c, o in zip(objects["segment"], objects["camera"], objects["object_id"]) if (s, c, o) != drop]
    buffer = io.BytesIO()
    pq.write_table(pa.Table.from_pylist(rows, schema=CLIPS_SCHEMA), buffer)
    return buffer.getvalue()


def make_output(root: Path, defect: str | None = None, seed: int = 0) -> Path:
    return write_output(root, *apply_defect(*good_tables(seed), defect))
