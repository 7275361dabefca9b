"""The error view: a clip's tracks against the exact synthetic ground truth, and its colours.

Each point is coloured by its pixel distance to the truth (TAP-Vid thresholds 1, 2, 4, 8 px); a
ring marks points whose occlusion flag disagrees with the truth.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivetrack.evaluation.clips import Clip
from drivetrack.show.clips import SPLITS, scene_frames

__all__ = ["ERROR_BINS_PX", "ERROR_COLORS", "WRONG_FLAG_COLOR", "ErrorView", "error_view", "error_colors",
           "error_legend"]

#: Upper bounds (px) of the error colour bins; the last bin is everything above.
ERROR_BINS_PX = (1.0, 2.0, 4.0, 8.0)
#: RGB colour per error bin: < 1, < 2, < 4, < 8, >= 8 px.
ERROR_COLORS = ((40, 200, 60), (160, 220, 40), (250, 220, 30), (250, 140, 20), (230, 30, 30))
WRONG_FLAG_COLOR = (255, 0, 255)


@dataclass
class ErrorView:
    """A clip's tracks compared with the exact synthetic ground truth.

    Attributes:
        matched: bool [N], the track's LiDAR return was found in the ground truth.
        gt_tracks: float32 [N, T, 2] true pixels (NaN where unmatched or not projectable).
        gt_visibles: bool [N, T] true visibility (False where unmatched).
        error_px: float32 [N, T] |tracks - gt_tracks| (NaN where either is not finite).
        wrong_flag: bool [N, T] matched and ``visibles != gt_visibles``.
    """
    matched: np.ndarray
    gt_tracks: np.ndarray
    gt_visibles: np.ndarray
    error_px: np.ndarray
    wrong_flag: np.ndarray

    def summary(self, frames: np.ndarray | None = None) -> dict[str, float]:
        """Median / p90 pixel error where both say visible, and the wrong-flag rate (matched tracks)."""
        sel = slice(None) if frames is None else np.asarray(frames)
        m = self.matched
        err = self.error_px[m][:, sel]
        both = (self.gt_visibles[m] & ~self.wrong_flag[m])[:, sel] & np.isfinite(err)
        vals = err[both]
        return {"matched_fraction": float(m.mean()) if m.size else float("nan"),
                "median_error_px": float(np.median(vals)) if vals.size else float("nan"),
                "p90_error_px": float(np.percentile(vals, 90)) if vals.size else float("nan"),
                "wrong_flag_fraction": float(self.wrong_flag[m][:, sel].mean()) if m.any() else float("nan")}


def error_view(clip: Clip, truth_root: str, split: str | None = None) -> ErrorView:
    """Match the clip's tracks to the synthetic ground truth under ``truth_root``.

    A track is matched by its LiDAR return: (segment frame of ``query_frames``, laser, return,
    range-image row, column) = ``lidar_sources`` against ``lidar_hits.npz``; clip frames are
    matched to segment frames on ``timestamps_micros``.
    """
    from drivetrack.synth.ground_truth import load_ground_truth
    from drivetrack.waymo.lidar import return_keys

    split = split or (clip.split if clip.split in SPLITS else None)
    if split is None:
        raise ValueError(f"{clip.url}: cannot tell the split from the folder {clip.split!r}; pass --split")
    if clip.lidar_sources is None or clip.query_frames is None:
        raise ValueError(f"{clip.url}: the error view needs lidar_sources and query_frames in the clip")
    truth = load_ground_truth(truth_root, split, clip.segment)
    seg_frames = scene_frames(truth.objects["timestamps_micros"], clip.timestamps_micros,
                               f"{clip.url} vs ground truth {truth.url}")
    h = truth.hits
    num_frames_gt = int(truth.objects["timestamps_micros"].shape[0])

    gt_keys = return_keys(h["frame"], h["laser"], h["return_index"], h["row"], h["col"], f"ground truth {truth.url}")
    order = np.argsort(gt_keys, kind="stable")
    src = clip.lidar_sources.astype(np.int64)
    ours = return_keys(seg_frames[clip.query_frames.astype(np.int64)], src[:, 0], src[:, 1], src[:, 2], src[:, 3],
                       clip.url)
    pos = np.clip(np.searchsorted(gt_keys[order], ours), 0, max(gt_keys.size - 1, 0))
    matched = (gt_keys[order][pos] == ours) if gt_keys.size else np.zeros(ours.shape, bool)
    hit = order[pos]
    axis = truth.camera_axis(clip.camera)
    n, t = clip.visibles.shape
    gt_tracks = np.full((n, t, 2), np.nan, np.float32)
    gt_vis = np.zeros((n, t), bool)
    if np.any(seg_frames >= num_frames_gt):
        raise ValueError(f"{clip.url}: clip frames beyond the ground truth's {num_frames_gt} frames")
    gt_tracks[matched] = h["pixels"][hit[matched]][:, axis][:, seg_frames]
    gt_vis[matched] = h["visible"][hit[matched]][:, axis][:, seg_frames]
    with np.errstate(invalid="ignore"):
        err = np.linalg.norm(clip.tracks.astype(np.float64) - gt_tracks, axis=-1).astype(np.float32)
    wrong = matched[:, None] & (clip.visibles != gt_vis)
    return ErrorView(matched=matched, gt_tracks=gt_tracks, gt_visibles=gt_vis, error_px=err, wrong_flag=wrong)


def error_colors(error_px: np.ndarray) -> np.ndarray:
    """uint8 [..., 3] RGB bin colour of each pixel error (grey where NaN)."""
    err = np.asarray(error_px, np.float64)
    bins = np.digitize(np.nan_to_num(err, nan=0.0), ERROR_BINS_PX)
    out = np.asarray(ERROR_COLORS, np.uint8)[bins]
    out[~np.isfinite(err)] = (150, 150, 150)
    return out


def error_legend(width: int) -> np.ndarray:
    """uint8 [h, width, 3] legend strip of the error colours."""
    import cv2

    scale = float(np.clip(width / 1400, 0.4, 0.6))
    h = int(round(70 * scale))
    strip = np.full((h, width, 3), 30, np.uint8)
    labels = ["<1 px", "<2 px", "<4 px", "<8 px", ">=8 px", "no truth", "wrong occlusion flag"]
    colors = list(ERROR_COLORS) + [(150, 150, 150), WRONG_FLAG_COLOR]
    x = 6
    for text, color in zip(labels, colors):
        cv2.circle(strip, (x + 6, h // 2), 6, tuple(int(c) for c in color), -1 if text != labels[-1] else 2)
        cv2.putText(strip, text, (x + 16, h // 2 + 5), cv2.FONT_HERSHEY_SIMPLEX, scale, (235, 235, 235), 1, cv2.LINE_AA)
        x += 16 + cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] + 14
    return strip

