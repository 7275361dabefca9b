"""Rigid transforms, rotations and boxes, vectorised in numpy (camera model: drivetrack.camera).

Every rotation helper of the project lives here (box poses from centre, heading, pitch and roll
and back; rotations of vectors into and out of a box frame).

Conventions, stated once for the whole project:

- A 4x4 rigid transform is named ``<dst>_from_<src>`` and maps homogeneous points of frame ``src``
  to frame ``dst``; compose so inner frames cancel:
  ``camera_from_world = camera_from_vehicle @ vehicle_from_world``.
- Frames: vehicle and Waymo camera are x forward, y left, z up, metres.
- Pixels: ``(x, y)`` = (column, row) in pixels; pixel ``i`` covers ``[i, i + 1)``, so the centre
  of the top-left pixel is ``(0.5, 0.5)``. Waymo's intrinsic ``c_u, c_v`` use this convention.
- Functions take ``[..., N, 3]`` points and ``[..., 4, 4]`` transforms and broadcast over the
  leading dimensions; empty inputs give empty outputs.
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "transform_points", "invert_rigid", "matrix_from_flat", "rotation_z", "rotation_from_rpy",
    "rigid_from_rotation_translation", "box_from_center_heading", "points_in_box_mask", "wrap_angle",
    "vectors_to_box", "vectors_from_box", "poses_from_center_heading", "center_heading_from_poses",
    "tilt_from_poses", "rigid_velocity_world",
]


def matrix_from_flat(flat: np.ndarray) -> np.ndarray:
    """``float64 [..., 4, 4]`` from Waymo's row-major ``[..., 16]`` transform columns."""
    flat = np.asarray(flat, dtype=np.float64)
    if flat.shape[-1:] != (16,):
        raise ValueError(f"a flat transform has 16 values, got shape {flat.shape}")
    return flat.reshape(flat.shape[:-1] + (4, 4))


def transform_points(dst_from_src: np.ndarray, points_src: np.ndarray) -> np.ndarray:
    """Apply rigid transforms to points.

    Args:
        dst_from_src: float [..., 4, 4].
        points_src: float [..., N, 3], metres, in frame ``src``.
    Returns:
        float64 [..., N, 3] in frame ``dst`` (leading dimensions broadcast).
    """
    dst_from_src = np.asarray(dst_from_src, dtype=np.float64)
    points_src = np.asarray(points_src, dtype=np.float64)
    if dst_from_src.shape[-2:] != (4, 4):
        raise ValueError(f"transform must be [..., 4, 4], got {dst_from_src.shape}")
    if points_src.shape[-1:] != (3,):
        raise ValueError(f"points must be [..., N, 3], got {points_src.shape}")
    rotation = dst_from_src[..., :3, :3]
    translation = dst_from_src[..., None, :3, 3]
    return np.einsum("...ij,...nj->...ni", rotation, points_src) + translation


def invert_rigid(dst_from_src: np.ndarray) -> np.ndarray:
    """``src_from_dst`` for rigid ``dst_from_src`` float [..., 4, 4] (exact, no general inverse)."""
    dst_from_src = np.asarray(dst_from_src, dtype=np.float64)
    rotation_t = np.swapaxes(dst_from_src[..., :3, :3], -1, -2)
    out = np.zeros_like(dst_from_src)
    out[..., :3, :3] = rotation_t
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rotation_t, dst_from_src[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def rotation_z(yaw: np.ndarray) -> np.ndarray:
    """float64 [..., 3, 3] rotation by ``yaw`` radians about +z (counter-clockwise seen from above)."""
    yaw = np.asarray(yaw, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    zeros, ones = np.zeros_like(yaw), np.ones_like(yaw)
    return np.stack([np.stack([c, -s, zeros], -1), np.stack([s, c, zeros], -1),
                     np.stack([zeros, zeros, ones], -1)], -2)


def rotation_from_rpy(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """float64 [..., 3, 3] = Rz(yaw) @ Ry(pitch) @ Rx(roll), angles in radians (Waymo's order)."""
    roll, pitch, yaw = (np.asarray(a, dtype=np.float64) for a in (roll, pitch, yaw))
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    return np.stack([
        np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
        np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
        np.stack([-sp, cp * sr, cp * cr], -1),
    ], -2)


def rigid_from_rotation_translation(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """float64 [..., 4, 4] from rotation [..., 3, 3] and translation [..., 3]."""
    rotation = np.asarray(rotation, dtype=np.float64)
    translation = np.asarray(translation, dtype=np.float64)
    shape = np.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    out = np.zeros(shape + (4, 4))
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def box_from_center_heading(center: np.ndarray, heading: np.ndarray, pitch: np.ndarray | None = None,
                            roll: np.ndarray | None = None) -> np.ndarray:
    """``parent_from_box`` float64 [..., 4, 4] of a Waymo box, optionally tilted.

    Args:
        center: float [..., 3], box centre in the parent frame (for ``lidar_box``: the vehicle
            frame of the box's own frame), metres.
        heading: float [...], yaw about +z, radians. The box frame has x along the heading
            (length, ``size.x``), y to its left (width, ``size.y``), z up (height, ``size.z``).
        pitch, roll: optional float [...], radians (None: 0, a ``lidar_box`` label, exactly
            ``Rz(heading)``). Rotation ``R = Rz(heading) @ Ry(pitch) @ Rx(roll)`` (intrinsic z-y'-x'',
            the order of :func:`rotation_from_rpy`): roll about the box's own x (length) axis, then
            pitch about its y (width) axis, then heading about the parent z. Positive pitch tips the
            box's front (+x) down (``R[2, 0] = -sin(pitch)``); positive roll lifts its left (+y)
            side (``R[2, 1] = cos(pitch) sin(roll)``). ``heading`` stays the yaw of the box x axis
            projected on the parent xy plane (``atan2(R[1, 0], R[0, 0])``).
    """
    if pitch is None and roll is None:
        return rigid_from_rotation_translation(rotation_z(heading), center)
    heading = np.asarray(heading, dtype=np.float64)
    pitch = np.zeros_like(heading) if pitch is None else pitch
    roll = np.zeros_like(heading) if roll is None else roll
    return rigid_from_rotation_translation(rotation_from_rpy(roll, pitch, heading), center)


def points_in_box_mask(points_box: np.ndarray, size: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """bool [..., N]: points (box frame, float [..., N, 3]) inside a box of ``size`` [..., 3].

    ``margin`` (metres) grows the box on every side when positive and shrinks it when negative.
    """
    half = np.asarray(size, dtype=np.float64)[..., None, :] / 2.0 + margin
    return np.all(np.abs(points_box) <= half, axis=-1)


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """float64 [...]: angles (radians) wrapped to (-pi, pi]."""
    return -((-np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi)


def vectors_to_box(vectors: np.ndarray, heading: np.ndarray, pitch: np.ndarray | None = None,
                   roll: np.ndarray | None = None, rows: np.ndarray | None = None) -> np.ndarray:
    """float64 [N, 3] ``R^T v`` of vectors float [N, 3] (e.g. ``x - center``: body points), per row
    ``R = Rz(heading) Ry(pitch) Rx(roll)`` (:func:`box_from_center_heading`'s rotation), angles
    float [N] radians. ``pitch`` and ``roll`` None: yaw only (exactly ``Rz(heading)^T v``); one
    of them None: 0. Elementwise (no matrices), so cheap on many rows. With ``rows`` (int [N]) the
    angles are per pose (float [R]) and vector n uses pose ``rows[n]``: the sines and cosines are
    taken once per pose, the same values as for the angles repeated per vector."""
    def trig(angle):
        c, s = np.cos(angle), np.sin(angle)
        return (c, s) if rows is None else (c[rows], s[rows])

    c, s = trig(heading)
    u = np.stack([c * vectors[:, 0] + s * vectors[:, 1], -s * vectors[:, 0] + c * vectors[:, 1], vectors[:, 2]],
                 axis=-1)
    if pitch is None and roll is None:
        return u
    count = np.shape(heading)[0] if rows is not None else u.shape[0]
    pitch = np.zeros(count) if pitch is None else pitch
    roll = np.zeros(count) if roll is None else roll
    (ct, st), (cr, sr) = trig(pitch), trig(roll)
    vx, vz = ct * u[:, 0] - st * u[:, 2], st * u[:, 0] + ct * u[:, 2]                 # Ry^T u
    return np.stack([vx, cr * u[:, 1] + sr * vz, -sr * u[:, 1] + cr * vz], axis=-1)   # Rx^T v


def vectors_from_box(vectors: np.ndarray, heading: np.ndarray, pitch: np.ndarray | None = None,
                     roll: np.ndarray | None = None) -> np.ndarray:
    """float64 [N, 3] ``R v``: the inverse of :func:`vectors_to_box` (same arguments)."""
    if pitch is not None or roll is not None:
        pitch = np.zeros(vectors.shape[0]) if pitch is None else pitch
        roll = np.zeros(vectors.shape[0]) if roll is None else roll
        ct, st, cr, sr = np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
        vy, vz = cr * vectors[:, 1] - sr * vectors[:, 2], sr * vectors[:, 1] + cr * vectors[:, 2]     # Rx v
        vectors = np.stack([ct * vectors[:, 0] + st * vz, vy, -st * vectors[:, 0] + ct * vz], axis=-1)  # Ry
    c, s = np.cos(heading), np.sin(heading)
    return np.stack([c * vectors[:, 0] - s * vectors[:, 1], s * vectors[:, 0] + c * vectors[:, 1], vectors[:, 2]],
                    axis=-1)


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


def tilt_from_poses(vehicle_from_box: np.ndarray) -> np.ndarray:
    """float64 [T, 2] (pitch, roll) radians of box poses [T, 4, 4] with rotation
    ``Rz(heading) Ry(pitch) Rx(roll)``; exactly 0 for yaw-only poses."""
    r = np.asarray(vehicle_from_box, dtype=np.float64)[..., :3, :3]
    return np.stack([-np.arcsin(np.clip(r[..., 2, 0], -1.0, 1.0)), np.arctan2(r[..., 2, 1], r[..., 2, 2])], axis=-1)


def rigid_velocity_world(points_world: np.ndarray, centre_world: np.ndarray, velocity_world: np.ndarray,
                         yaw_rate: float | np.ndarray) -> np.ndarray:
    """float64 [n, 3] m/s: the world velocity of points float [n, 3] (world frame, metres) of objects
    moving rigidly, ``v + w z x (p - c)``: centre ``centre_world`` [3] or [n, 3] (metres), centre
    velocity ``velocity_world`` [3] or [n, 3] (m/s), yaw rate ``yaw_rate`` scalar or [n] (rad/s)
    about the world z."""
    points_world = np.asarray(points_world, np.float64)
    velocity = np.broadcast_to(np.asarray(velocity_world, np.float64), points_world.shape)
    yaw_rate = np.asarray(yaw_rate, np.float64)
    if not np.any(yaw_rate):
        return velocity
    lever = points_world - centre_world
    spin = np.stack([-lever[:, 1], lever[:, 0], np.zeros(lever.shape[0])], axis=-1)
    return velocity + (yaw_rate[:, None] if yaw_rate.ndim else yaw_rate) * spin
