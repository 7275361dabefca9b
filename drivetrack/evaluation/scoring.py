"""Evaluation: score point-track annotations against exact synthetic truth, and trackers against a release.

Two uses, one set of definitions (docs/evaluation.md):

1. **Annotations vs exact truth** (:func:`evaluate_annotations`, :func:`evaluate_tracks`,
   :func:`evaluate_clips`). Each annotated track names the LiDAR return that produced it
   (``query_frames`` = clip frame, ``lidar_sources`` = (laser, return, row, col)). The clip frame
   becomes a segment frame by matching the clip's ``timestamps_micros`` to the truth's, and the
   key (segment frame, laser, return, row, col) is looked up in the truth's ``lidar_hits``. A
   matched track is scored against that hit's exact ``pixels`` and ``visible`` in the clip's camera
   and frames, at the annotation's own resolution. Per clip:

   - TAP-Vid metrics (:func:`drivetrack.evaluation.metrics.compute_tapvid_metrics`) in query modes ``first``
     and ``strided``, queries built from the *truth* (:func:`~drivetrack.evaluation.metrics.queries_first`,
     :func:`~drivetrack.evaluation.metrics.queries_strided`), over the matched tracks;
   - pixel error (median, mean; px) over frames where the truth is visible;
   - purity: share of the clip's tracks whose return truly lies on the annotated object (a return
     that is not in ``lidar_hits`` hit the ground or background: impure);
   - recall: share of the object's truth hits in the clip's frames that became tracks
     (``recall``: of all its hits, every laser and return; ``recall_visible``: of the hits visible
     in this camera in at least one clip frame, the ones the method is meant to keep).

2. **A tracker vs a release** (:func:`score_predictions`): the release's (or an annotation
   folder's) tracks and visibility are the ground truth, a tracker's npz per clip (same file
   names; ``tracks`` [N, T, 2] and ``visibles`` or ``occluded`` [N, T]) the prediction.

The pieces: :mod:`.clips` (reading clips), :mod:`.truth` (ground-truth look-up), this
module (scoring, aggregation), :mod:`.predictions` (trackers vs a release), :mod:`.metrics`
(TAP-Vid metrics).

Results come as an :class:`Evaluation`: ``clips`` (one row per clip and query mode), ``objects``
(one row per (split, segment, object, query mode), metrics averaged over the object's clips) and
a JSON-able ``summary`` (metrics averaged over clips per query mode, as TAP-Vid averages over
videos; purity, recall and pixel errors pooled over all tracks).

Pixels (x, y), pixel i covers [i, i+1), as everywhere in drivetrack.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np
import pandas as pd

from drivetrack.evaluation.clips import Clip, clip_from_tracks, find_annotation_files, read_clip
from drivetrack.evaluation.metrics import QUERY_MODES, THRESHOLDS_PX, compute_tapvid_metrics, queries_first, \
    queries_strided
from drivetrack.evaluation.truth import TruthIndex

__all__ = ["METRIC_KEYS", "DEFAULT_MAX_QUERIES", "Evaluation", "score_clip", "evaluate_clips", "evaluate_tracks",
           "evaluate_annotations", "tapvid_scores", "pixel_error_stats"]

#: TAP-Vid metric names, in table order.
METRIC_KEYS = (("occlusion_accuracy",) + tuple(f"pts_within_{d}" for d in THRESHOLDS_PX)
               + tuple(f"jaccard_{d}" for d in THRESHOLDS_PX) + ("average_jaccard", "average_pts_within_thresh"))

#: Default cap on the queries scored per clip and mode (evenly spaced subset beyond it): bounds the
#: [Q, T, 2] float64 temporaries of the metric (a full-size clip can have 10^5 tracks x 40 strides).
DEFAULT_MAX_QUERIES = 20_000


def _subsample(count: int, limit: int | None) -> np.ndarray:
    if limit is None or count <= limit:
        return np.arange(count)
    return np.unique(np.linspace(0, count - 1, limit).round().astype(np.int64))


def pixel_error_stats(errors: np.ndarray) -> dict[str, float]:
    """Median, mean and p95 (px) of pixel errors, a non-finite error counting as +inf.

    A prediction that is NaN or inf where the truth is visible is infinitely wrong, never
    "no error": it sorts above every finite error, so the median and p95 become inf once that
    share of errors is non-finite, and the mean is inf as soon as one is. NaN when ``errors`` is
    empty. ``errors``: float [E].
    """
    errors = np.asarray(errors, dtype=np.float64).reshape(-1)
    if errors.size == 0:
        return {"pixel_error_median": math.nan, "pixel_error_mean": math.nan, "pixel_error_p95": math.nan}
    ordered = np.sort(np.where(np.isfinite(errors), errors, np.inf))

    def quantile(q: float) -> float:                       # numpy's "linear" method, inf-safe
        position = q * (ordered.size - 1)
        low, frac = int(math.floor(position)), position - math.floor(position)
        if frac == 0 or math.isinf(ordered[low + 1]):
            return float(ordered[low]) if frac == 0 else math.inf
        return float(ordered[low] + (ordered[low + 1] - ordered[low]) * frac)

    mean = math.inf if math.isinf(ordered[-1]) else float(np.mean(ordered))
    return {"pixel_error_median": quantile(0.5), "pixel_error_mean": mean, "pixel_error_p95": quantile(0.95)}


def tapvid_scores(gt_tracks: np.ndarray, gt_visibles: np.ndarray, pred_tracks: np.ndarray,
                  pred_visibles: np.ndarray, query_mode: str, stride: int = 5,
                  max_queries: int | None = DEFAULT_MAX_QUERIES) -> dict[str, float]:
    """TAP-Vid metrics of one clip, queries from the truth.

    Args:
        gt_tracks, pred_tracks: float [N, T, 2] pixels (x, y).
        gt_visibles, pred_visibles: bool [N, T].
        query_mode: ``first`` (each track's first visible truth point) or ``strided`` (every
            visible truth point at frames 0, stride, ...; the track's one prediction is scored
            against each of its queries).
        max_queries: score an evenly spaced subset of at most this many queries (None = all).
    Returns:
        ``{metric: float}`` for :data:`METRIC_KEYS` (NaN when no query exists) plus
        ``num_queries`` and ``num_queries_scored``.
    """
    if query_mode == "first":
        queries, index = queries_first(gt_visibles, gt_tracks)
    elif query_mode == "strided":
        queries, index = queries_strided(gt_visibles, gt_tracks, stride)
    else:
        raise ValueError(f"unknown query_mode {query_mode!r}; expected one of {QUERY_MODES}")
    out: dict[str, float] = {"num_queries": int(index.size)}
    keep = _subsample(index.size, max_queries)
    out["num_queries_scored"] = int(keep.size)
    if keep.size == 0:
        return {**{k: math.nan for k in METRIC_KEYS}, **out}
    queries, index = queries[keep], index[keep]
    metrics = compute_tapvid_metrics(queries[None], ~np.asarray(gt_visibles, bool)[index][None],
                                     np.asarray(gt_tracks)[index][None], ~np.asarray(pred_visibles, bool)[index][None],
                                     np.asarray(pred_tracks)[index][None], query_mode)
    return {**{k: float(metrics[k][0]) for k in METRIC_KEYS}, **out}


def errors_at_visible(pred_tracks: np.ndarray, gt_tracks: np.ndarray,
                       gt_visibles: np.ndarray) -> tuple[np.ndarray, int]:
    """(float64 [E] distance at every truth-visible point, +inf where the prediction is not
    finite; count of those non-finite predictions)."""
    pred = pred_tracks[gt_visibles]
    with np.errstate(invalid="ignore", over="ignore"):
        errors = np.linalg.norm(pred - gt_tracks[gt_visibles], axis=-1)
    bad = ~np.isfinite(pred).all(axis=-1)
    errors[bad | ~np.isfinite(errors)] = np.inf
    return errors, int(bad.sum())


def score_clip(clip: Clip, index: TruthIndex, query_modes: tuple[str, ...] = QUERY_MODES, stride: int = 5,
               max_queries: int | None = DEFAULT_MAX_QUERIES) -> tuple[list[dict], np.ndarray]:
    """Score one annotated clip against the exact truth of its segment.

    Returns ``(rows, errors)``: one dict per query mode (identity, counts, purity, recall, pixel
    error and TAP-Vid metrics; see the module docstring) and float64 [E] the pixel error of every
    matched track at every frame where the truth sees it (+inf where the track is not finite).
    """
    clip.check()
    where = clip.where
    if clip.segment != index.truth.segment:
        raise ValueError(f"{where}: scored against the ground truth of segment {index.truth.segment!r}")
    frames = index.segment_frames(clip.timestamps_micros, where)
    try:
        camera_axis = index.truth.camera_axis(clip.camera)
    except KeyError as error:
        raise ValueError(f"{where}: {error.args[0]}") from None
    object_k = index.object_index(clip.object_id, where)
    n, t = clip.visibles.shape
    hit = index.match(frames[clip.query_frames], clip.lidar_sources, where)
    matched = hit >= 0
    hits = index.truth.hits
    on_object = np.zeros(n, dtype=bool)
    on_object[matched] = hits["object_index"][hit[matched]] == object_k

    hm = hit[matched]
    gt_tracks = hits["pixels"][hm[:, None], camera_axis, frames[None, :]].astype(np.float64)       # [M, T, 2]
    gt_visibles = hits["visible"][hm[:, None], camera_axis, frames[None, :]]                      # [M, T]
    pred_tracks = np.asarray(clip.tracks[matched], dtype=np.float64)
    pred_visibles = clip.visibles[matched]
    errors, nonfinite = errors_at_visible(pred_tracks, gt_tracks, gt_visibles)

    object_hits = index.object_hits(object_k, frames)
    visible_hits = object_hits[hits["visible"][object_hits[:, None], camera_axis, frames[None, :]].any(axis=1)] \
        if object_hits.size else object_hits
    tracked = np.unique(hit[on_object])
    base = {
        "split": clip.split, "segment": clip.segment, "camera": clip.camera, "object_id": clip.object_id,
        "file": clip.file, "num_frames": int(t), "num_tracks": int(n), "num_matched": int(matched.sum()),
        "num_on_object": int(on_object.sum()), "num_unmatched": int((~matched).sum()),
        "num_other_object": int((matched & ~on_object).sum()),
        "purity": float(on_object.mean()) if n else math.nan,
        "num_object_hits": int(object_hits.size), "num_object_hits_visible": int(visible_hits.size),
        "num_hits_tracked": int(tracked.size), "num_visible_hits_tracked": int(np.isin(visible_hits, tracked).sum()),
        "recall": float(tracked.size / object_hits.size) if object_hits.size else math.nan,
        "recall_visible": (float(np.isin(visible_hits, tracked).sum() / visible_hits.size)
                           if visible_hits.size else math.nan),
        "num_gt_visible_points": int(gt_visibles.sum()),
        "num_pred_visible_points": int(pred_visibles.sum()),
        **pixel_error_stats(errors),
        "num_nonfinite_at_visible": nonfinite,
    }
    rows = [{**base, "query_mode": mode,
             **tapvid_scores(gt_tracks, gt_visibles, pred_tracks, pred_visibles, mode, stride, max_queries)}
            for mode in query_modes]
    return rows, errors


@dataclass
class Evaluation:
    """Result of an evaluation.

    Attributes:
        clips: one row per (clip, query mode).
        objects: one row per (split, segment, object_id, query mode): TAP-Vid metrics and pixel
            errors averaged over the object's clips (cameras), counts summed, purity/recall pooled.
        summary: JSON-able dict: ``kind``, counts, pooled purity/recall/pixel errors, and per
            query mode the metrics averaged over clips (``modes``).
    """
    clips: pd.DataFrame
    objects: pd.DataFrame
    summary: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        """Summary plus the per-object and per-clip tables as lists of records (NaN -> None)."""
        def records(frame: pd.DataFrame) -> list[dict]:
            return [{k: _jsonable(v) for k, v in row.items()} for row in frame.to_dict("records")]

        return {"summary": _jsonable(self.summary), "objects": records(self.objects), "clips": records(self.clips)}


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return None if not math.isfinite(float(value)) else float(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


_SUM_COLUMNS = ("num_frames", "num_tracks", "num_matched", "num_on_object", "num_unmatched", "num_other_object",
                "num_object_hits", "num_object_hits_visible", "num_hits_tracked", "num_visible_hits_tracked",
                "num_gt_visible_points", "num_pred_visible_points", "num_nonfinite_at_visible", "num_queries",
                "num_queries_scored")
_MEAN_COLUMNS = METRIC_KEYS + ("pixel_error_median", "pixel_error_mean", "pixel_error_p95")


def aggregate_objects(clips: pd.DataFrame) -> pd.DataFrame:
    keys = ["split", "segment", "object_id", "query_mode"]
    if clips.empty:
        return pd.DataFrame(columns=keys)
    sums = [c for c in _SUM_COLUMNS if c in clips.columns]
    means = [c for c in _MEAN_COLUMNS if c in clips.columns]
    grouped = clips.groupby(keys, sort=True, dropna=False)
    out = grouped[sums].sum().join(grouped[means].mean())
    out.insert(0, "num_clips", grouped.size())
    out.insert(1, "cameras", grouped["camera"].agg(lambda c: ",".join(sorted(set(c)))))
    if {"num_on_object", "num_tracks"} <= set(out.columns):
        out["purity"] = _pooled(out["num_on_object"], out["num_tracks"])
        out["recall"] = _pooled(out["num_hits_tracked"], out["num_object_hits"])
        out["recall_visible"] = _pooled(out["num_visible_hits_tracked"], out["num_object_hits_visible"])
    return out.reset_index()


def _pooled(numerator, denominator):
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(np.asarray(denominator) > 0, np.asarray(numerator, float) / np.asarray(denominator, float),
                        np.nan)


def summarise(kind: str, clips: pd.DataFrame, errors: list[np.ndarray], extra: dict) -> dict:
    first = clips.drop_duplicates(["split", "segment", "camera", "object_id"]) if not clips.empty else clips
    summary = {"kind": kind, **extra, "num_clips": int(len(first)),
               "num_objects": int(first[["split", "segment", "object_id"]].drop_duplicates().shape[0]) if len(first) else 0,
               "num_segments": int(first[["split", "segment"]].drop_duplicates().shape[0]) if len(first) else 0,
               "num_tracks": int(first["num_tracks"].sum()) if len(first) else 0}
    if "num_on_object" in first.columns:
        for name in ("num_matched", "num_on_object", "num_unmatched", "num_other_object", "num_object_hits",
                     "num_hits_tracked", "num_object_hits_visible", "num_visible_hits_tracked"):
            summary[name] = int(first[name].sum()) if len(first) else 0
        summary["purity"] = float(_pooled(summary["num_on_object"], summary["num_tracks"]))
        summary["recall"] = float(_pooled(summary["num_hits_tracked"], summary["num_object_hits"]))
        summary["recall_visible"] = float(_pooled(summary["num_visible_hits_tracked"],
                                                  summary["num_object_hits_visible"]))
    summary.update(pixel_error_stats(np.concatenate(errors) if errors else np.zeros(0)))
    # non-finite predictions at truth-visible points: errors, in the headline as well as per clip
    nonfinite = first["num_nonfinite_at_visible"] if "num_nonfinite_at_visible" in first.columns else None
    summary["num_gt_visible_points"] = int(first["num_gt_visible_points"].sum()) if len(first) else 0
    summary["num_nonfinite_at_visible"] = int(nonfinite.sum()) if nonfinite is not None else 0
    summary["num_clips_nonfinite"] = int((nonfinite > 0).sum()) if nonfinite is not None else 0
    modes = {}
    for mode, part in (clips.groupby("query_mode", sort=False) if not clips.empty else []):
        modes[mode] = {"num_queries": int(part["num_queries"].sum()),
                       **{k: float(part[k].mean()) for k in METRIC_KEYS}}
    summary["modes"] = modes
    return summary


def evaluate_clips(clips: Iterable[Clip], truth_root: str, query_modes: tuple[str, ...] = QUERY_MODES,
                   stride: int = 5, max_queries: int | None = DEFAULT_MAX_QUERIES,
                   default_split: str = "training", truths: dict | None = None) -> Evaluation:
    """Score clips against the synthetic truth under ``truth_root`` (see the module docstring).

    The truth of a segment is loaded when its first clip arrives and released when a clip of
    another segment comes (feed clips grouped by segment to load each truth once). A caller that
    scores the same segments repeatedly may pass ``truths``, a dict kept across calls:
    ``(split, segment) -> TruthIndex`` (filled here; never released).
    """
    rows: list[dict] = []
    errors: list[np.ndarray] = []
    current: tuple[str, str] | None = None
    index: TruthIndex | None = None
    for clip in clips:
        key = (clip.split or default_split, clip.segment)
        if key != current:
            index = None                      # release the previous truth first
            if truths is not None and key in truths:
                index = truths[key]
            else:
                index = TruthIndex.load(truth_root, *key)
                if truths is not None:
                    truths[key] = index
            current = key
        clip_rows, clip_errors = score_clip(clip, index, query_modes, stride, max_queries)
        rows.extend(clip_rows)
        errors.append(clip_errors.astype(np.float32))
    frame = pd.DataFrame(rows)
    return Evaluation(frame, aggregate_objects(frame),
                      summarise("annotations_vs_truth", frame, errors, {"truth": str(truth_root),
                                                                       "query_modes": list(query_modes),
                                                                       "stride": stride}))


def evaluate_tracks(tracks: Iterable, truth_root: str, **kwargs) -> Evaluation:
    """:func:`evaluate_clips` of in-memory ``ObjectTracks`` (rejected / empty clips skipped)."""
    clips = (clip_from_tracks(t) for t in tracks if getattr(t, "rejection", None) is None and t.num_tracks > 0)
    return evaluate_clips(clips, truth_root, **kwargs)


def evaluate_annotations(out_url: str, truth_root: str, split: str | None = None,
                         query_modes: tuple[str, ...] = QUERY_MODES, stride: int = 5,
                         max_queries: int | None = DEFAULT_MAX_QUERIES,
                         storage_options: dict | None = None) -> Evaluation:
    """Score every clip file of an annotation folder against the synthetic truth of its segment."""
    files = find_annotation_files(out_url, split, storage_options)
    if not files:
        raise FileNotFoundError(f"no clips (clips/*/*.parquet tables or waymo_*.npz files) under {out_url}"
                                + (f" for split {split!r}" if split else ""))
    files.sort(key=lambda f: (f.split, f.segment, f.relpath))
    result = evaluate_clips((read_clip(f, storage_options) for f in files), truth_root, query_modes, stride,
                            max_queries, default_split=split or "training")
    result.summary["annotations"] = str(out_url)
    return result

