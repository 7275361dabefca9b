"""numba kernel of the reader's per-pixel pose step (TOP returns into their frame's vehicle frame).

:func:`vehicle_from_pixel_pose` does what :func:`drivetrack.waymo.lidar.apply_pixel_pose` did in
numpy (rotation matrices for every return, two einsums) in one pass over the returns, without the
[M, 3, 3] temporaries. The sines and cosines are numpy's (the caller passes them), and the
products and sums follow :func:`drivetrack.geometry.rotation_from_rpy` and
:func:`drivetrack.geometry.transform_points` operation for operation, so both paths agree bit for
bit (tests/test_waymo_reader.py). Compiled on first use and cached on disk.
"""
from __future__ import annotations

import numpy as np

from drivetrack.numba_compat import njit

__all__ = ["vehicle_from_pixel_pose"]


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
        cr, cp, cy = cos_rpy[m, 0], cos_rpy[m, 1], cos_rpy[m, 2]
        sr, sp, sy = sin_rpy[m, 0], sin_rpy[m, 1], sin_rpy[m, 2]
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
        wx = r00 * x + r01 * y + r02 * z + translation[m, 0]
        wy = r10 * x + r11 * y + r12 * z + translation[m, 1]
        wz = r20 * x + r21 * y + r22 * z + translation[m, 2]
        out[m, 0] = a[0, 0] * wx + a[0, 1] * wy + a[0, 2] * wz + a[0, 3]
        out[m, 1] = a[1, 0] * wx + a[1, 1] * wy + a[1, 2] * wz + a[1, 3]
        out[m, 2] = a[2, 0] * wx + a[2, 1] * wy + a[2, 2] * wz + a[2, 3]
