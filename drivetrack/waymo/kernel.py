"""numba kernels of the reader's range-image steps (returns into points, TOP returns into their
frame's vehicle frame).

- :func:`vehicle_from_pixel_pose` does what :func:`drivetrack.waymo.lidar.apply_pixel_pose` did in
  numpy (rotation matrices for every return, two einsums) in one pass over the returns, without
  the [M, 3, 3] temporaries. The sines and cosines are numpy's (the caller passes them), and the
  products and sums follow :func:`drivetrack.geometry.rotation_from_rpy` and
  :func:`drivetrack.geometry.transform_points` operation for operation (tests/test_waymo_reader.py).
- :func:`returns_from_range_image`: the valid pixels of one range image as points, rows, columns
  and intensities (reference: :func:`drivetrack.waymo.lidar.points_from_directions`, same values).
- :func:`pack_return_keys`: the return keys of equal-length columns in one pass, with the first
  value outside its field (reference: :func:`drivetrack.waymo.lidar.return_keys`).
- :func:`posed_returns`: one TOP image's returns moved with their pixel's pose, the pose checked
  finite where a return uses it, and each return's capture-time sample (reference:
  ``apply_pixel_pose`` and :func:`drivetrack.waymo.capture_time.pixel_time_offsets`).

Compiled on first use and cached on disk.
"""
from __future__ import annotations

import numpy as np

from drivetrack.numba_compat import njit

__all__ = ["vehicle_from_pixel_pose", "returns_from_range_image", "posed_returns", "pack_return_keys"]


@njit(cache=True, nogil=True)
def vehicle_from_pixel_pose(points, cos_rpy, sin_rpy, translation, frame_from_world, out):
    """``out[m] = frame_from_world @ pixel_pose[m] @ points[m]`` for M returns.

    Args:
        points: float64 [M, 3], each return in the vehicle frame of its own pixel's capture time.
        cos_rpy, sin_rpy: float64 [M, 3], cos / sin of the pixel pose's roll, pitch, yaw.
        translation: float64 [M, 3], the pixel pose's position in the world, metres.
        frame_from_world: float64 [4, 4], the frame's ``inv(world_from_vehicle)``.
        out: float64 [M, 3], written (may be ``points``).
    """
    a = frame_from_world
    for m in range(points.shape[0]):
        _posed(points, m, cos_rpy[m, 0], cos_rpy[m, 1], cos_rpy[m, 2], sin_rpy[m, 0], sin_rpy[m, 1], sin_rpy[m, 2],
               translation[m, 0], translation[m, 1], translation[m, 2], a, out)


@njit(cache=True, nogil=True, inline="always")
def _posed(points, m, cr, cp, cy, sr, sp, sy, tx, ty, tz, a, out):
    """``out[m] = a @ (Rz(yaw) Ry(pitch) Rx(roll) points[m] + t)`` (``rotation_from_rpy``'s products)."""
    r00 = cy * cp
    r01 = cy * sp * sr - sy * cr
    r02 = cy * sp * cr + sy * sr
    r10 = sy * cp
    r11 = sy * sp * sr + cy * cr
    r12 = sy * sp * cr - cy * sr
    r20 = -sp
    r21 = cp * sr
    r22 = cp * cr
    x, y, z = points[m, 0], points[m, 1], points[m, 2]
    wx = r00 * x + r01 * y + r02 * z + tx
    wy = r10 * x + r11 * y + r12 * z + ty
    wz = r20 * x + r21 * y + r22 * z + tz
    out[m, 0] = a[0, 0] * wx + a[0, 1] * wy + a[0, 2] * wz + a[0, 3]
    out[m, 1] = a[1, 0] * wx + a[1, 1] * wy + a[1, 2] * wz + a[1, 3]
    out[m, 2] = a[2, 0] * wx + a[2, 1] * wy + a[2, 2] * wz + a[2, 3]


@njit(cache=True, nogil=True)
def _count_returns(image):
    n, nonfinite = 0, 0
    for r in range(image.shape[0]):
        for c in range(image.shape[1]):
            v = image[r, c, 0]
            if v > 0 and v < np.inf:
                n += 1
            elif not np.isfinite(v):
                nonfinite += 1
    return n, nonfinite


@njit(cache=True, nogil=True)
def _fill_returns(image, directions, origin, points, rows, cols, intensity):
    m = 0
    has_intensity = image.shape[2] > 1
    for r in range(image.shape[0]):
        for c in range(image.shape[1]):
            v = image[r, c, 0]
            if v > 0 and v < np.inf:                  # finite and positive: a return
                rng = np.float64(v)
                points[m, 0] = rng * directions[r, c, 0] + origin[0]
                points[m, 1] = rng * directions[r, c, 1] + origin[1]
                points[m, 2] = rng * directions[r, c, 2] + origin[2]
                rows[m], cols[m] = r, c
                intensity[m] = np.float32(image[r, c, 1]) if has_intensity else np.float32(np.nan)
                m += 1


def returns_from_range_image(image: np.ndarray, directions: np.ndarray, origin: np.ndarray):
    """``(points float64 [M, 3], rows int32 [M], cols int32 [M], intensity float32 [M], nonfinite)``
    of the pixels of ``image`` (float [H, W, C]) whose range is finite and > 0, in row-major order:
    ``range * directions[row, col] + origin`` (directions float64 [H, W, 3], origin float64 [3],
    vehicle frame); intensity is channel 1 (NaN without one); ``nonfinite`` counts the NaN / inf
    ranges (no return)."""
    n, nonfinite = _count_returns(image)
    points = np.empty((n, 3))
    rows, cols = np.empty(n, np.int32), np.empty(n, np.int32)
    intensity = np.empty(n, np.float32)
    _fill_returns(image, np.ascontiguousarray(directions, dtype=np.float64),
                  np.ascontiguousarray(origin, dtype=np.float64), points, rows, cols, intensity)
    return points, rows, cols, intensity, int(nonfinite)


@njit(cache=True, nogil=True)
def _posed_kernel(points, rows, cols, pose, frame_from_world, position, velocity, min_speed, max_abs, out, dt):
    speed2 = velocity[0] * velocity[0] + velocity[1] * velocity[1] + velocity[2] * velocity[2]
    moving = speed2 >= min_speed ** 2
    for m in range(points.shape[0]):
        r, c = rows[m], cols[m]
        for k in range(6):
            if not np.isfinite(pose[r, c, k]):
                return m
        roll, pitch, yaw = np.float64(pose[r, c, 0]), np.float64(pose[r, c, 1]), np.float64(pose[r, c, 2])
        tx, ty, tz = np.float64(pose[r, c, 3]), np.float64(pose[r, c, 4]), np.float64(pose[r, c, 5])
        _posed(points, m, np.cos(roll), np.cos(pitch), np.cos(yaw), np.sin(roll), np.sin(pitch), np.sin(yaw),
               tx, ty, tz, frame_from_world, out)
        value = np.nan
        if moving:
            value = ((tx - position[0]) * velocity[0] + (ty - position[1]) * velocity[1]
                     + (tz - position[2]) * velocity[2]) / speed2
            if not abs(value) <= max_abs:
                value = np.nan
        dt[m] = np.float32(value)
    return -1


def posed_returns(points: np.ndarray, rows: np.ndarray, cols: np.ndarray, pose: np.ndarray,
                  frame_from_world: np.ndarray, position: np.ndarray, velocity: np.ndarray,
                  min_speed: float, max_abs: float):
    """``(out float64 [M, 3], dt float32 [M], bad)`` for returns ``points`` float64 [M, 3] at pixels
    (``rows``, ``cols``) of a TOP image whose per-pixel pose is ``pose`` float [H, W, 6] (roll,
    pitch, yaw, x, y, z): ``frame_from_world @ pixel_pose @ p`` and the capture-time sample
    ``dot(p_pixel - position, velocity) / |velocity|^2`` (NaN below ``min_speed`` m/s or beyond
    ``max_abs`` s). ``bad`` is the first return whose pose has a NaN / inf value (-1: none; then
    ``out`` and ``dt`` are only partly written)."""
    n = points.shape[0]
    out, dt = np.empty((n, 3)), np.empty(n, np.float32)
    bad = _posed_kernel(np.ascontiguousarray(points, dtype=np.float64), rows, cols, pose,
                        np.ascontiguousarray(frame_from_world, dtype=np.float64),
                        np.ascontiguousarray(position, dtype=np.float64), np.ascontiguousarray(velocity, dtype=np.float64),
                        float(min_speed), float(max_abs), out, dt)
    return out, dt, int(bad)


@njit(cache=True, nogil=True)
def pack_return_keys(frame, laser, return_index, row, col, bits, out):
    """``out[i]`` (int64 [N]) = the return key of row i (frame, laser, return, row, col: int arrays
    [N]; ``bits`` int64 [5] field widths, most significant first). Returns (field, index) of the
    first value outside ``[0, 2**bits)`` of the first such field, (-1, -1) when all fit."""
    first = np.full(5, -1, np.int64)
    n = frame.shape[0]
    for i in range(n):
        values = (np.int64(frame[i]), np.int64(laser[i]), np.int64(return_index[i]), np.int64(row[i]),
                  np.int64(col[i]))
        key = np.int64(0)
        for k in range(5):
            v = values[k]
            if (v < 0 or v >= (np.int64(1) << bits[k])) and first[k] < 0:
                first[k] = i
            key = (key << bits[k]) | v
        out[i] = key
    for k in range(5):
        if first[k] >= 0:
            return k, first[k]
    return -1, -1
