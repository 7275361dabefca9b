"""Tidy statistics tables of the track stage (``stats/*.parquet``, see docs/formats.md)."""
from __future__ import annotations

import numpy as np
import pandas as pd

from drivetrack.tracks.core import ObjectTracks
from drivetrack.outputs import (OBJECT_COLUMNS, REJECTION_COLUMNS, REJECTION_REASONS, SEGMENT_COLUMNS,
                                SPEED_ERR_COLUMNS, SPEED_PERCENTILES, SegmentStatus)
from drivetrack.tracks.plan import SegmentPlan
from drivetrack.waymo.schema import BoxType, CameraName

__all__ = ["object_stats", "segment_stats", "rejection_stats", "write_table"]


def _object_row(t: ObjectTracks, file: str) -> dict:
    visible = t.visibles
    errors = t.speed_error_mps[np.isfinite(t.speed_error_mps)]
    pct = (np.percentile(errors, SPEED_PERCENTILES) if errors.size
           else np.full(len(SPEED_PERCENTILES), np.nan))
    row = {
        "split": t.split, "segment": t.segment, "camera": t.camera_name, "object_id": t.object_id,
        "object_type": t.object_type_name, "file": file, "num_tracks": t.num_tracks,
        "num_frames": t.num_frames, "first_frame": int(t.frames[0]) if t.num_frames else -1,
        "visible_fraction": float(visible.mean()) if visible.size else float("nan"),
        "min_camera_distance_m": float(t.min_camera_distance_m),
        "box_speed_mean_mps": float(t.box_speed_mps),
        # counted by the job on its tracks (ObjectTracks docstring): tracks are never materialised here
        "num_nonfinite_visible": int(t.num_nonfinite_visible),
        "num_visible_outside_image": int(t.num_visible_outside_image),
        "num_candidates": int(t.num_candidates), "num_dropped_invisible": int(t.num_dropped_invisible),
        "num_dropped_speed": int(t.num_dropped_speed), "projection": t.projection,
        "time_model": t.time_model, "label_time": t.label_time, "time_residual_m": float(t.time_residual_m),
        "num_unreliable_normals": int(t.num_unreliable_normals),
        "num_ambiguous_occlusion": int(t.num_ambiguous_occlusion),
        "ambiguous_occlusion_fraction": (float(t.num_ambiguous_occlusion / visible.size) if visible.size
                                         else float("nan")),
    }
    row.update({c: float(v) for c, v in zip(SPEED_ERR_COLUMNS, pct)})
    return row


def object_stats(results: list[ObjectTracks], files: dict[tuple[int, str], str] | None = None) -> pd.DataFrame:
    """One row per annotated clip (rejected clips are skipped: they are in the rejections table).

    Args:
        results: outputs of ``run_object_job``.
        files: (camera value, object_id) -> URL of the DriveTrack file written for the clip.
    """
    files = files or {}
    rows = [_object_row(t, files.get((t.camera, t.object_id), "")) for t in results if t.rejection is None]
    return pd.DataFrame(rows, columns=list(OBJECT_COLUMNS))


def rejection_stats(plan: SegmentPlan, results: list[ObjectTracks] = ()) -> pd.DataFrame:
    """One row per rejected (segment, camera, object, reason), planning and track stages."""
    scene = plan.scene
    rows = [{"split": scene.split, "segment": scene.segment, "camera": CameraName(r["camera"]).name,
             "object_id": r["object_id"], "object_type": BoxType(r["object_type"]).name,
             "reason": r["reason"], "detail": r["detail"]} for r in plan.rejections]
    for t in results:
        if t.rejection is not None:
            rows.append({"split": t.split, "segment": t.segment, "camera": t.camera_name,
                         "object_id": t.object_id, "object_type": t.object_type_name,
                         "reason": t.rejection,
                         "detail": f"{t.num_candidates} candidates, {t.num_dropped_invisible} never visible, "
                                   f"{t.num_dropped_speed} dropped by the speed filter"})
    return pd.DataFrame(rows, columns=list(REJECTION_COLUMNS))


def segment_stats(split: str, segment: str, plan: SegmentPlan | None = None,
                  results: list[ObjectTracks] = (), status: str = SegmentStatus.DONE, error: str = "") -> pd.DataFrame:
    """One row for a segment; ``plan`` may be None when the segment failed before planning."""
    if status not in (SegmentStatus.DONE, SegmentStatus.FAILED):
        raise ValueError(f"segment {segment!r}: status must be '{SegmentStatus.DONE}' or '{SegmentStatus.FAILED}', "
                         f"got {status!r}")
    row = {"split": split, "segment": segment, "status": status, "error": error,
           "num_frames": plan.scene.num_frames if plan else 0,
           "num_objects_labelled": plan.num_objects_labelled if plan else 0,
           "num_object_clips_considered": plan.num_clips_considered if plan else 0,
           "num_object_clips_annotated": sum(1 for t in results if t.rejection is None),
           "num_tracks": sum(t.num_tracks for t in results if t.rejection is None)}
    counts = dict.fromkeys(REJECTION_REASONS, 0)
    if plan is not None:
        for table_row in rejection_stats(plan, results).itertuples():
            counts[table_row.reason] += 1
    row.update({f"rejected_{r}": int(c) for r, c in counts.items()})
    row.update(_label_time_row(plan))
    row.update(_depth_lookup_row(plan))
    return pd.DataFrame([row], columns=list(SEGMENT_COLUMNS))


def _depth_lookup_row(plan: SegmentPlan | None) -> dict:
    """The labels' jitter the segment measured (``label_jitter_m``, metres; NaN without a plan or
    a still object) and the depth map look-up's growth its clips used (``depth_lookup_px``;
    :func:`drivetrack.tracks.core.depth_lookup_grow_px`)."""
    if plan is None:
        return {"label_jitter_m": float("nan"), "depth_lookup_px": 0}
    from drivetrack.tracks.core import depth_lookup_grow_px, segment_label_jitter_m

    return {"label_jitter_m": float(segment_label_jitter_m(plan)), "depth_lookup_px": depth_lookup_grow_px(plan)}


def _label_time_row(plan: SegmentPlan | None) -> dict:
    """The segment's label-time decision (:func:`drivetrack.tracks.trajectory.segment_trajectory`):
    ``label_time`` ("" when the segment has no plan or uses ``time_model="velocity"``, which
    takes labels at the frame time), the two conventions' residuals (NaN unless ``auto``) and
    ``num_synced_samples``, the box rows whose ``lidar_camera_synced_box`` is a trajectory sample
    (:func:`drivetrack.tracks.trajectory.synced_samples`; 0 with ``synced_boxes`` off)."""
    row = {"label_time": "", "label_time_residual_frame_m": float("nan"),
           "label_time_residual_sweep_m": float("nan"), "num_synced_samples": 0}
    if plan is None:
        return row
    if plan.config.time_model != "trajectory":
        return {**row, "label_time": "frame"}
    from drivetrack.tracks.trajectory import segment_trajectory, synced_samples

    decision = segment_trajectory(plan, plan.config.label_time)[1]
    synced = int(np.isfinite(synced_samples(plan.scene)[0]).sum()) if plan.config.synced_boxes else 0
    return {"label_time": decision["label_time"], "label_time_residual_frame_m": decision["residual_frame_m"],
            "label_time_residual_sweep_m": decision["residual_sweep_m"], "num_synced_samples": synced}


def write_table(url: str, table: pd.DataFrame) -> str:
    """Write ``table`` as parquet at ``url`` (any fsspec URL), atomically; returns url."""
    from drivetrack.storage import write_parquet

    return write_parquet(url, table)
