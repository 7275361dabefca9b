"""A picture of a synthetic frame with its ground truth, for documentation and eyeballing."""
from __future__ import annotations

import numpy as np

from drivetrack.synth.ground_truth import load_ground_truth
from drivetrack.waymo.schema import COMPONENTS, KEY_CAMERA, KEY_TIMESTAMP, CameraName, LaserName

__all__ = ["render_preview"]


def _images(root: str, split: str, segment: str, frame: int) -> dict[int, np.ndarray]:
    import cv2
    import pyarrow.parquet as pq

    comp = COMPONENTS["camera_image"]
    table = pq.read_table(f"{str(root).rstrip('/')}/{split}/camera_image/{segment}.parquet",
                          columns=[KEY_TIMESTAMP, KEY_CAMERA, comp.col("image")])
    stamps = sorted(set(table.column(KEY_TIMESTAMP).to_pylist()))
    if not 0 <= frame < len(stamps):
        raise IndexError(f"segment {segment}: frame {frame} out of range 0..{len(stamps) - 1}")
    out = {}
    for ts, cam, jpeg in zip(*(table.column(i).to_pylist() for i in range(3))):
        if ts == stamps[frame]:
            out[cam] = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    return out


def render_preview(root: str, split: str, segment: str, frame: int, source_frame: int = 0) -> np.ndarray:
    """uint8 [2 H, 3 W, 3] RGB: top row the three front cameras at ``frame``; bottom row the
    FRONT exact depth (colour = inverse depth, black = sky), FRONT with the TOP-lidar object
    points of ``source_frame`` carried to ``frame`` (green visible, red occluded), and FRONT with
    their tracks from ``source_frame`` to ``frame``."""
    import cv2

    truth = load_ground_truth(root, split, segment)
    images = _images(root, split, segment, frame)
    front = int(CameraName.FRONT)
    cams = [int(CameraName.FRONT_LEFT), front, int(CameraName.FRONT_RIGHT)]
    top = [images[c] for c in cams if c in images]
    base = images[front]
    H, W = base.shape[:2]
    depth = truth.depth(front)[frame]
    inv = np.where(depth > 0, 1.0 / np.maximum(depth, 1e-3), 0.0)
    scaled = np.clip(inv / max(np.percentile(inv[depth > 0], 99), 1e-6) * 255, 0, 255).astype(np.uint8)
    depth_rgb = cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO)[..., ::-1].copy()
    depth_rgb[depth == 0] = 0
    h = truth.hits
    ci = truth.camera_axis(front)
    sel = np.flatnonzero((h["frame"] == source_frame) & (h["laser"] == int(LaserName.TOP))
                         & (h["return_index"] == 1))
    px = h["pixels"][sel, ci, frame]
    vis = h["visible"][sel, ci, frame]
    dots = base.copy()
    radius = max(1, W // 320)
    for (x, y), v in zip(px, vis):
        if np.isfinite(x) and 0 <= x < W and 0 <= y < H:
            cv2.circle(dots, (int(x), int(y)), radius, (40, 220, 60) if v else (230, 40, 40), -1)
    tracks = base.copy()
    rng = np.random.default_rng(0)
    for i in rng.permutation(sel.size)[:150]:
        path = h["pixels"][sel[i], ci, source_frame:frame + 1]
        ok = np.isfinite(path[:, 0])
        if ok.sum() >= 2 and h["visible"][sel[i], ci, frame]:
            cv2.polylines(tracks, [path[ok].astype(np.int32)], False, (255, 230, 0), radius)
    bottom = [depth_rgb, dots, tracks]
    return np.concatenate([np.concatenate(top, 1), np.concatenate(bottom, 1)], 0)
