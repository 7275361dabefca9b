"""TAP-Vid point-tracking metrics (METHOD.md section 4), vectorised in numpy.

Same definitions and argument conventions as tapnet's ``compute_tapvid_metrics``
(``google-deepmind/tapnet``, ``tapnet/tapvid/evaluation_datasets.py``), so numbers are comparable;
the code is our own. Per video (or per track with ``per_track=True``), over the *evaluated*
frames of each query:

- query modes: ``first`` evaluates the frames strictly after the query frame (the query is the
  first visible point, earlier frames are known to be occluded); ``strided`` evaluates every frame
  except the query frame.
- ``occlusion_accuracy``: fraction of evaluated frames whose predicted occlusion equals the truth.
- ``pts_within_{d}`` (d in 1, 2, 4, 8, 16 px): among evaluated frames where the ground truth is
  visible, the fraction whose predicted position is within d pixels, i.e. squared distance
  *strictly* below d^2 (the predicted occlusion flag is ignored). A non-finite predicted
  position (NaN, inf) is never within any d: it is a miss here and in the Jaccard.
- ``jaccard_{d}``: TP / (TP + FP + FN) with TP = truth visible, predicted visible and within d;
  FP = predicted visible and (truth occluded or not within d); FN = truth visible and (predicted
  occluded or not within d). TP + FN is the number of visible ground-truth points.
- ``average_jaccard`` (AJ) and ``average_pts_within_thresh`` (delta_avg): means over the five d.

Ratios with an empty denominator are NaN. Coordinates are pixels (x, y) of whatever resolution
the caller chose (the TAP-Vid papers rescale to 256 x 256 first; :func:`rescale_points` helps).
"""
from __future__ import annotations

import numpy as np

__all__ = ["THRESHOLDS_PX", "QUERY_MODES", "evaluation_mask", "compute_tapvid_metrics",
           "queries_first", "queries_strided", "rescale_points", "to_tapvid"]

THRESHOLDS_PX = (1, 2, 4, 8, 16)
QUERY_MODES = ("first", "strided")


def evaluation_mask(query_frames: np.ndarray, num_frames: int, query_mode: str) -> np.ndarray:
    """bool [..., N, T]: which frames score each query (frame index int/float [..., N])."""
    if query_mode not in QUERY_MODES:
        raise ValueError(f"unknown query_mode {query_mode!r}; expected one of {QUERY_MODES}")
    query = np.rint(np.asarray(query_frames, dtype=np.float64)).astype(np.int64)[..., None]
    frames = np.arange(num_frames)
    return frames > query if query_mode == "first" else frames != query


def _ratio(numerator: np.ndarray, denominator: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return numerator / denominator


def compute_tapvid_metrics(query_points: np.ndarray, gt_occluded: np.ndarray, gt_tracks: np.ndarray,
                           pred_occluded: np.ndarray, pred_tracks: np.ndarray, query_mode: str,
                           per_track: bool = False) -> dict[str, np.ndarray]:
    """TAP-Vid metrics of a batch of videos.

    Args:
        query_points: float [B, N, 3] as (t, y, x): query frame first (tapnet's order).
        gt_occluded: bool [B, N, T], True = occluded.
        gt_tracks: float [B, N, T, 2] pixels (x, y).
        pred_occluded: bool [B, N, T].
        pred_tracks: float [B, N, T, 2] pixels (x, y).
        query_mode: ``first`` or ``strided``.
        per_track: return one value per track ([B, N]) instead of per video ([B]).
    Returns:
        dict of float64 [B] (or [B, N]): ``occlusion_accuracy``, ``pts_within_{d}``,
        ``jaccard_{d}``, ``average_jaccard``, ``average_pts_within_thresh``.
    """
    gt_occluded = np.asarray(gt_occluded, dtype=bool)
    pred_occluded = np.asarray(pred_occluded, dtype=bool)
    gt_tracks = np.asarray(gt_tracks, dtype=np.float64)
    pred_tracks = np.asarray(pred_tracks, dtype=np.float64)
    query_points = np.asarray(query_points, dtype=np.float64)
    if gt_occluded.ndim != 3:
        raise ValueError(f"gt_occluded must be [B, N, T], got shape {gt_occluded.shape}")
    b, n, t = gt_occluded.shape
    for name, array, shape in (("pred_occluded", pred_occluded, (b, n, t)),
                               ("gt_tracks", gt_tracks, (b, n, t, 2)),
                               ("pred_tracks", pred_tracks, (b, n, t, 2)),
                               ("query_points", query_points, (b, n, 3))):
        if array.shape != shape:
            raise ValueError(f"{name} must have shape {shape} (from gt_occluded), got {array.shape}")
    axes = (2,) if per_track else (1, 2)
    evaluated = evaluation_mask(query_points[..., 0], t, query_mode)
    gt_visible = ~gt_occluded & evaluated
    pred_visible = ~pred_occluded & evaluated

    out = {"occlusion_accuracy": _ratio(np.sum((gt_occluded == pred_occluded) & evaluated, axis=axes),
                                        np.sum(evaluated, axis=axes))}
    with np.errstate(invalid="ignore", over="ignore"):
        squared = np.sum((pred_tracks - gt_tracks) ** 2, axis=-1)
    finite = np.isfinite(pred_tracks).all(axis=-1)
    num_gt_visible = np.sum(gt_visible, axis=axes)
    within_all, jaccard_all = [], []
    for threshold in THRESHOLDS_PX:
        with np.errstate(invalid="ignore"):
            within = finite & (squared < threshold * threshold)   # NaN / inf position -> a miss
        true_positive = np.sum(gt_visible & pred_visible & within, axis=axes)
        false_positive = np.sum(pred_visible & (gt_occluded | ~within), axis=axes)
        pts_within = _ratio(np.sum(gt_visible & within, axis=axes), num_gt_visible)
        jaccard = _ratio(true_positive, num_gt_visible + false_positive)
        out[f"pts_within_{threshold}"] = pts_within
        out[f"jaccard_{threshold}"] = jaccard
        within_all.append(pts_within)
        jaccard_all.append(jaccard)
    out["average_jaccard"] = np.mean(jaccard_all, axis=0)
    out["average_pts_within_thresh"] = np.mean(within_all, axis=0)
    return out


def queries_first(visibles: np.ndarray, tracks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``first``-mode queries: each track's first visible point.

    Args:
        visibles: bool [N, T]; tracks: float [N, T, 2] pixels (x, y).
    Returns:
        ``(query_points float64 [Q, 3] as (t, y, x), track_index int64 [Q])`` for the Q tracks
        visible at least once.
    """
    visibles = np.asarray(visibles, dtype=bool)
    index = np.flatnonzero(visibles.any(axis=1))
    frame = np.argmax(visibles[index], axis=1)
    xy = np.asarray(tracks, dtype=np.float64)[index, frame]
    return np.stack([frame.astype(np.float64), xy[:, 1], xy[:, 0]], axis=-1), index


def queries_strided(visibles: np.ndarray, tracks: np.ndarray, stride: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """``strided``-mode queries: every visible point at frames 0, stride, 2*stride, ...

    Returns ``(query_points float64 [Q, 3] as (t, y, x), track_index int64 [Q])``, ordered by
    query frame then track.
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    visibles = np.asarray(visibles, dtype=bool)
    frames = np.arange(0, visibles.shape[1], stride)
    frame_of, track_of = np.nonzero(visibles[:, frames].T)
    frame = frames[frame_of]
    xy = np.asarray(tracks, dtype=np.float64)[track_of, frame]
    return np.stack([frame.astype(np.float64), xy[:, 1], xy[:, 0]], axis=-1), track_of.astype(np.int64)


def rescale_points(points: np.ndarray, from_size: tuple[int, int], to_size: tuple[int, int]) -> np.ndarray:
    """Pixels (x, y) float [..., 2] from an image of (width, height) ``from_size`` to ``to_size``.

    Pixel i covers [i, i+1) in both, so this is a plain scale of the continuous coordinates.
    """
    scale = np.array([to_size[0] / from_size[0], to_size[1] / from_size[1]], dtype=np.float64)
    return np.asarray(points, dtype=np.float64) * scale


def to_tapvid(tracks: np.ndarray, visibles: np.ndarray, width: int, height: int) -> dict[str, np.ndarray]:
    """TAP-Vid's representation: ``points`` float32 [N, T, 2] (x, y) in [0, 1], ``occluded`` bool [N, T]."""
    points = np.asarray(tracks, dtype=np.float64) / np.array([width, height], dtype=np.float64)
    return {"points": points.astype(np.float32), "occluded": ~np.asarray(visibles, dtype=bool)}
