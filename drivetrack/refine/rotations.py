"""Box pose helpers of the refinement: centre/heading/tilt of poses and rotations of vectors."""
from __future__ import annotations

import numpy as np

from drivetrack.geometry import box_from_center_heading

__all__ = ["poses_from_center_heading", "center_heading_from_poses", "tilt_from_poses"]


def poses_from_center_heading(center: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """float64 [T, 4, 4] ``vehicle_from_box`` of centres [T, 3] and headings [T] (radians)."""
    return box_from_center_heading(center, heading)


def center_heading_from_poses(vehicle_from_box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centre float64 [T, 3], heading float64 [T]) of yaw-dominant box poses [T, 4, 4].

    The heading is the yaw of the box x axis projected on the vehicle xy plane (the convention
    ``lidar_box`` labels use); roll and pitch, if any, are dropped.
    """
    vehicle_from_box = np.asarray(vehicle_from_box, dtype=np.float64)
    return vehicle_from_box[..., :3, 3].copy(), np.arctan2(vehicle_from_box[..., 1, 0], vehicle_from_box[..., 0, 0])


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles wrapped to (-pi, pi]."""
    return -((-np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi)


def _to_body(vec: np.ndarray, heading: np.ndarray, tilt: np.ndarray | None) -> np.ndarray:
    """float64 [M, 3] ``R^T vec`` for vectors vec [M, 3], R = Rz(heading) Ry(pitch) Rx(roll) per row
    (heading [M], tilt [M, 2] = (pitch, roll) or None: yaw only)."""
    c, s = np.cos(heading), np.sin(heading)
    u = np.stack([c * vec[:, 0] + s * vec[:, 1], -s * vec[:, 0] + c * vec[:, 1], vec[:, 2]], axis=-1)
    if tilt is None:
        return u
    ct, st, cr, sr = np.cos(tilt[:, 0]), np.sin(tilt[:, 0]), np.cos(tilt[:, 1]), np.sin(tilt[:, 1])
    vx, vz = ct * u[:, 0] - st * u[:, 2], st * u[:, 0] + ct * u[:, 2]                 # Ry^T u
    return np.stack([vx, cr * u[:, 1] + sr * vz, -sr * u[:, 1] + cr * vz], axis=-1)   # Rx^T v


def _from_body(vec: np.ndarray, heading: np.ndarray, tilt: np.ndarray | None) -> np.ndarray:
    """float64 [M, 3] ``R vec``: the inverse of :func:`_to_body`."""
    if tilt is not None:
        ct, st, cr, sr = np.cos(tilt[:, 0]), np.sin(tilt[:, 0]), np.cos(tilt[:, 1]), np.sin(tilt[:, 1])
        vy, vz = cr * vec[:, 1] - sr * vec[:, 2], sr * vec[:, 1] + cr * vec[:, 2]     # Rx q
        vec = np.stack([ct * vec[:, 0] + st * vz, vy, -st * vec[:, 0] + ct * vz], axis=-1)  # Ry v
    c, s = np.cos(heading), np.sin(heading)
    return np.stack([c * vec[:, 0] - s * vec[:, 1], s * vec[:, 0] + c * vec[:, 1], vec[:, 2]], axis=-1)


def tilt_from_poses(vehicle_from_box: np.ndarray) -> np.ndarray:
    """float64 [T, 2] (pitch, roll) radians of box poses [T, 4, 4] with rotation
    ``Rz(heading) Ry(pitch) Rx(roll)``; exactly 0 for yaw-only poses."""
    r = np.asarray(vehicle_from_box, dtype=np.float64)[..., :3, :3]
    return np.stack([-np.arcsin(np.clip(r[..., 2, 0], -1.0, 1.0)), np.arctan2(r[..., 2, 1], r[..., 2, 2])], axis=-1)
