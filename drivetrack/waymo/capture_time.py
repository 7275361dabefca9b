"""When was each LiDAR return captured? Per-return time offsets from the data the v2 format carries.

A TOP sweep lasts about one frame period (0.1 s) and scans the range image column by column.
The format gives no per-return time, but it gives, per TOP pixel, ``lidar_pose`` = the vehicle
pose (``world_from_vehicle``) *at that pixel's capture time*. Where the ego moves, the pixel
pose's position along the ego trajectory tells the time::

    dt = dot(p_pixel - p_frame, v_ego) / |v_ego|^2

with ``p_frame`` the frame's ``vehicle_pose`` translation and ``v_ego`` the ego velocity from the
frame poses by central differences. ``dt`` is relative to the time of the frame's vehicle pose,
which is the reference of the boxes (``lidar_box`` is in the vehicle frame of that pose). In
Waymo's own files ``key.frame_timestamp_micros`` marks the *start* of the TOP sweep and the pose
is taken around its middle (waymo-open-dataset issues 464 and 541); measuring against the pose is
what compensation needs, whichever convention a producer follows.

Per-pixel values are noisy (float32 world coordinates, acceleration, curvature) and undefined
where the ego stands still, so the segment gets one model, ``dt = a + b * col`` (the sweep is
column-ordered and both ends of a Waymo range image are at the rear, so it does not wrap inside
an image), fitted robustly over the returns of every frame where the ego moves at least
:data:`MIN_EGO_SPEED_MPS`, and applied to every TOP return of every frame (frames where the ego
stands still get times too). Lasers without a per-pixel pose (FRONT, SIDE_LEFT, SIDE_RIGHT,
REAR) get 0: their firing phase relative to the frame is not in the format and cannot be
identified from their data, so they are taken at the frame time (an error of up to half a
sweep times the object speed, if they sweep like TOP). A segment with no usable sample gets 0
everywhere (:attr:`SweepTiming.fitted` False).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivetrack.waymo.schema import LaserName

__all__ = ["MIN_EGO_SPEED_MPS", "MAX_ABS_OFFSET_S", "SweepTiming", "ego_velocity_world",
           "pixel_time_offsets", "fit_sweep_timing", "capture_offsets"]

#: Frames where the ego moves slower than this (m/s) give no timing samples.
MIN_EGO_SPEED_MPS = 2.0
#: Samples whose |dt| exceeds this (s) are not from this frame's sweep (bad pose): ignored.
MAX_ABS_OFFSET_S = 0.25
#: Cap on the samples the robust fit uses (an evenly strided subset beyond it).
MAX_FIT_SAMPLES = 400_000


@dataclass(frozen=True)
class SweepTiming:
    """The TOP sweep's time model of one segment: ``dt(col) = intercept_s + slope_s * col``.

    Attributes:
        intercept_s: seconds, offset of column 0 from the frame's vehicle-pose time.
        slope_s: seconds per column (negative when the sweep runs towards column 0).
        num_samples: per-return samples offered to the fit (moving frames, |dt| plausible).
        num_inliers: samples kept by the last trimming round (of at most
            :data:`MAX_FIT_SAMPLES` evenly strided ones).
        residual_rms_s: RMS residual of the inliers, seconds.
        fitted: False when there was nothing to fit (then every offset is 0).
    """
    intercept_s: float = 0.0
    slope_s: float = 0.0
    num_samples: int = 0
    num_inliers: int = 0
    residual_rms_s: float = float("nan")
    fitted: bool = False

    def offsets(self, col: np.ndarray) -> np.ndarray:
        """float32 [...] seconds for range-image columns ``col`` (int [...])."""
        col = np.asarray(col, dtype=np.float64)
        return (self.intercept_s + self.slope_s * col).astype(np.float32)


def ego_velocity_world(world_from_vehicle: np.ndarray, timestamps_micros: np.ndarray) -> np.ndarray:
    """float64 [T, 3] ego velocity in the world frame (m/s), central differences of the frame
    poses (one-sided at the ends); zeros for a single frame."""
    position = np.asarray(world_from_vehicle, dtype=np.float64)[:, :3, 3]
    if position.shape[0] < 2:
        return np.zeros_like(position)
    return np.gradient(position, np.asarray(timestamps_micros, np.float64) * 1e-6, axis=0)


def pixel_time_offsets(pixel_position_world: np.ndarray, frame_position_world: np.ndarray,
                       velocity_world: np.ndarray, min_speed_mps: float = MIN_EGO_SPEED_MPS) -> np.ndarray:
    """float64 [N] capture-time offsets (s) of pixels from their pixel-pose positions.

    Args:
        pixel_position_world: float [N, 3], translation of ``lidar_pose`` at each pixel, metres.
        frame_position_world: float [N, 3] or [3], translation of the frame's vehicle pose.
        velocity_world: float [N, 3] or [3], ego velocity at the frame, m/s.
    Returns:
        ``dot(p_pixel - p_frame, v) / |v|^2``; NaN where ``|v| < min_speed_mps`` or the result
        exceeds :data:`MAX_ABS_OFFSET_S` in magnitude.
    """
    delta = np.asarray(pixel_position_world, np.float64) - np.asarray(frame_position_world, np.float64)
    v = np.broadcast_to(np.asarray(velocity_world, np.float64), delta.shape)
    speed2 = np.einsum("ni,ni->n", v, v)
    moving = speed2 >= min_speed_mps ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        dt = np.where(moving, np.einsum("ni,ni->n", delta, v) / np.where(moving, speed2, 1.0), np.nan)
    dt[~(np.abs(dt) <= MAX_ABS_OFFSET_S)] = np.nan
    return dt


def fit_sweep_timing(col: np.ndarray, dt: np.ndarray, rounds: int = 4) -> SweepTiming:
    """Robust line ``dt = a + b * col`` through per-return samples (NaN samples ignored).

    Least squares, then ``rounds`` re-fits on the samples whose residual lies within
    ``max(3 * 1.4826 * MAD, 0.5 ms)`` of the median residual of the previous round (outliers: bad
    poses, strong acceleration). Fewer than 2 distinct
    columns give an unfitted (all-zero) model.
    """
    col = np.asarray(col, np.float64).ravel()
    dt = np.asarray(dt, np.float64).ravel()
    if col.shape != dt.shape:
        raise ValueError(f"fit_sweep_timing: col has shape {col.shape}, dt {dt.shape}")
    ok = np.isfinite(dt)
    col, dt = col[ok], dt[ok]
    n = int(dt.size)
    if n > MAX_FIT_SAMPLES:
        pick = np.linspace(0, n - 1, MAX_FIT_SAMPLES).astype(np.int64)
        col, dt = col[pick], dt[pick]
    if dt.size < 2 or np.unique(col).size < 2:
        return SweepTiming(num_samples=n)
    keep = np.ones(dt.size, dtype=bool)
    a = b = 0.0
    for _ in range(rounds + 1):
        design = np.stack([np.ones(int(keep.sum())), col[keep]], axis=-1)
        (a, b), *_ = np.linalg.lstsq(design, dt[keep], rcond=None)
        residual = dt - (a + b * col)
        centre = float(np.median(residual[keep]))        # the inliers' level (LS is pulled by outliers)
        mad = float(np.median(np.abs(residual[keep] - centre)))
        new_keep = np.abs(residual - centre) <= max(3.0 * 1.4826 * mad, 5e-4)
        if new_keep.sum() < 2 or np.unique(col[new_keep]).size < 2 or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    residual = dt[keep] - (a + b * col[keep])
    return SweepTiming(intercept_s=float(a), slope_s=float(b), num_samples=n, num_inliers=int(keep.sum()),
                       residual_rms_s=float(np.sqrt(np.mean(residual ** 2))), fitted=True)


def capture_offsets(laser: np.ndarray, col: np.ndarray, timing: SweepTiming) -> np.ndarray:
    """float32 [M] per-return offsets (s, relative to the frame's pose time): the TOP model for
    TOP returns, 0 for the lasers without a per-pixel pose (see the module docstring)."""
    laser = np.asarray(laser)
    out = np.zeros(laser.shape, dtype=np.float32)
    if timing.fitted:
        top = laser == int(LaserName.TOP)
        out[top] = timing.offsets(np.asarray(col)[top])
    return out
