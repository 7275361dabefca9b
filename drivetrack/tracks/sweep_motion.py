"""Object motion during the LiDAR sweep: put each return where its surface was at the frame time.

The reader removes the *ego's* motion during the sweep, so ``scene.lidar.points_vehicle`` is
where a surface was at the return's capture time, in the vehicle frame of the frame's pose. A box
(``lidar_box``) describes its object at the frame (pose) time. A return captured ``dt`` seconds
off that time (``LidarReturns.capture_offset_s``) on an object moving at ``v`` is displaced by
``v dt`` (up to ~0.75 m at 15 m/s for a 0.1 s sweep), so selecting points in boxes and computing
box-frame points from the frame's box smears moving objects.

Model: over the sweep each box moves with constant velocity and constant yaw rate. A return of
object k at frame t, captured at ``t + dt``, is expressed in the box *at its capture time*::

    center(dt)  = center_t + v_vehicle dt          heading(dt) = heading_t + yaw_rate dt
    p_box       = box_from_vehicle(center(dt), heading(dt)) @ X

which is the body point; ``X_frame = vehicle_from_box_t @ p_box`` is where that surface was at
the frame time. A tilted box (``Boxes.pitch`` / ``roll``, from pose refinement) keeps its pitch
and roll over the sweep (0.1 s): only centre and heading move. Velocity and yaw rate come from the object's own box track by central finite
differences over its labelled frames (one-sided at its ends), in the world frame, then rotated
into the vehicle frame of each box's frame. Why not the ``speed`` column: it is the label's
velocity, whose frame convention differs between producers and which has no yaw rate; the track
is defined wherever the object has two boxes and uses the same boxes the points are selected
with. An object with a single box falls back to ``speed`` (read as the world velocity expressed
in the vehicle frame, as Waymo and the synthetic generator write it) when finite, else to 0.
"""
from __future__ import annotations

import numpy as np

from drivetrack.geometry import vectors_to_box

__all__ = ["box_motion_world", "scene_box_motion", "points_box_at_capture"]


def _yaw_of(rotation: np.ndarray) -> np.ndarray:
    return np.arctan2(rotation[..., 1, 0], rotation[..., 0, 0])


def box_motion_world(world_from_box: np.ndarray, time_s: np.ndarray,
                     group: np.ndarray | None = None, half: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Finite-difference velocity and yaw rate of box tracks, in the world frame.

    Args:
        world_from_box: float64 [K, 4, 4], box poses.
        time_s: float64 [K], seconds (any origin) of each box.
        group: optional [K] object ids (any comparable dtype); rows of one id form one track.
            None: all rows are one track.
    Returns:
        ``(velocity_world float64 [K, 3] m/s, yaw_rate float64 [K] rad/s, has_neighbour bool [K])``
        by central differences between a row's previous and next box of the same object in time
        (one-sided at the ends; 0 and ``has_neighbour`` False for a single box). With ``half`` > 1:
        the least-squares slope over the row's box and up to ``half`` boxes of the object on each
        side (centred on the row: unbiased by a constant acceleration away from the track's ends).
    """
    world_from_box = np.asarray(world_from_box, dtype=np.float64)
    time_s = np.asarray(time_s, dtype=np.float64)
    k = time_s.shape[0]
    velocity = np.zeros((k, 3))
    yaw_rate = np.zeros(k)
    if k == 0:
        return velocity, yaw_rate, np.zeros(0, dtype=bool)
    keys = np.zeros(k, dtype=np.int64) if group is None else np.unique(np.asarray(group), return_inverse=True)[1]
    order = np.lexsort((time_s, keys))
    same_prev = np.zeros(k, dtype=bool)
    same_prev[1:] = keys[order][1:] == keys[order][:-1]
    same_next = np.zeros(k, dtype=bool)
    same_next[:-1] = same_prev[1:]
    position = np.arange(k)
    prev = order[np.where(same_prev, position - 1, position)]
    nxt = order[np.where(same_next, position + 1, position)]
    span = time_s[nxt] - time_s[prev]
    ok = span > 0
    centre = world_from_box[:, :3, 3]
    yaw = _yaw_of(world_from_box[:, :3, :3])
    moved = centre[nxt] - centre[prev]
    turned = np.angle(np.exp(1j * (yaw[nxt] - yaw[prev])))
    velocity[order[ok]] = moved[ok] / span[ok, None]
    yaw_rate[order[ok]] = turned[ok] / span[ok]
    has_neighbour = np.zeros(k, dtype=bool)
    has_neighbour[order] = ok
    if half > 1:
        # least-squares slope over the row and its object's boxes up to ``half`` either side in
        # time (trajectory's window): sum (t_j - t_mean)(x_j - x_row) / sum (t_j - t_mean)^2
        from drivetrack.tracks.trajectory import _window

        window = _window(keys, time_s, half)                                  # [K, 2 half]
        valid = window >= 0
        j = np.where(valid, window, np.arange(k)[:, None])
        dt = np.where(valid, time_s[j] - time_s[:, None], 0.0)                # the row itself: 0
        dt = dt - (dt.sum(axis=1) / (valid.sum(axis=1) + 1))[:, None]
        dt[~valid] = 0.0
        mean_shift = dt.sum(axis=1, keepdims=True)      # = the mean time: the row itself, centred
        var = (dt * dt).sum(axis=1) + mean_shift[:, 0] ** 2
        dx = np.where(valid[..., None], centre[j] - centre[:, None], 0.0)
        dw = np.where(valid, np.angle(np.exp(1j * (yaw[j] - yaw[:, None]))), 0.0)
        fit = has_neighbour & (var > 1e-12)
        safe = np.where(fit, var, 1.0)
        velocity[fit] = (np.einsum("kw,kwi->ki", dt, dx) / safe[:, None])[fit]
        yaw_rate[fit] = ((dt * dw).sum(axis=1) / safe)[fit]
    return velocity, yaw_rate, has_neighbour


def scene_box_motion(scene, half: int = 1,
                     label_offset_s: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(velocity_vehicle float64 [K, 3] m/s, yaw_rate float64 [K] rad/s)`` of every box row.

    Velocity of each box in the vehicle frame of its own frame (the world velocity rotated by
    ``vehicle_from_world``), from :func:`box_motion_world` over each object's track, each box
    taken at its frame time plus ``label_offset_s`` (float [K], s; None: 0), the time its pose
    describes; a single-box object uses its finite ``speed`` (else 0).
    """
    boxes = scene.boxes
    if len(boxes) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    world_from_vehicle = np.asarray(scene.world_from_vehicle, dtype=np.float64)[boxes.frame]
    world_from_box = world_from_vehicle @ boxes.vehicle_from_box()
    time_s = np.asarray(scene.timestamps_micros, dtype=np.float64)[boxes.frame] * 1e-6
    if label_offset_s is not None:
        time_s = time_s + np.asarray(label_offset_s, dtype=np.float64).reshape(len(boxes))
    velocity_world, yaw_rate, has_neighbour = box_motion_world(world_from_box, time_s,
                                                               boxes.object_id.astype(str), half=half)
    velocity = np.einsum("kji,kj->ki", world_from_vehicle[:, :3, :3], velocity_world)   # R^T v
    speed = np.asarray(boxes.speed, dtype=np.float64)
    fallback = ~has_neighbour & np.isfinite(speed).all(axis=1)
    velocity[fallback] = speed[fallback]
    return velocity, yaw_rate


def points_box_at_capture(points_vehicle: np.ndarray, offset_s: np.ndarray | None, center: np.ndarray,
                          heading: np.ndarray, velocity_vehicle: np.ndarray | None = None,
                          yaw_rate: np.ndarray | None = None, pitch: np.ndarray | None = None,
                          roll: np.ndarray | None = None) -> np.ndarray:
    """float64 [N, 3] box-frame (body) points of returns, with the box moved to each capture time.

    Args:
        points_vehicle: float [N, 3], metres, vehicle frame of the box's frame.
        offset_s: float [N] capture time minus frame time, seconds (None: 0).
        center: float [N, 3] or [3], box centre at the frame time, same vehicle frame.
        heading: float [N] or scalar, box yaw at the frame time, radians.
        velocity_vehicle: float [N, 3] or [3], box velocity in that vehicle frame, m/s (None: 0).
        yaw_rate: float [N] or scalar, rad/s (None: 0).
        pitch, roll: float [N] or scalar, radians, the box's tilt (``Boxes.pitch`` / ``roll``;
            None: 0, then the computation is exactly the yaw-only one), held over the sweep.
    With zero offsets or zero motion this is ``box_from_vehicle_t @ X`` exactly.
    """
    points = np.asarray(points_vehicle, dtype=np.float64).reshape(-1, 3)
    n = points.shape[0]
    dt = np.zeros(n) if offset_s is None else np.asarray(offset_s, dtype=np.float64).reshape(n)
    centre = np.broadcast_to(np.asarray(center, dtype=np.float64), (n, 3))
    yaw = np.broadcast_to(np.asarray(heading, dtype=np.float64), (n,))
    if velocity_vehicle is not None:
        centre = centre + np.broadcast_to(np.asarray(velocity_vehicle, np.float64), (n, 3)) * dt[:, None]
    if yaw_rate is not None:
        yaw = yaw + np.broadcast_to(np.asarray(yaw_rate, np.float64), (n,)) * dt
    if pitch is not None or roll is not None:     # R^T = Rx(roll)^T Ry(pitch)^T Rz(heading)^T
        pitch, roll = (np.broadcast_to(np.asarray(0.0 if a is None else a, dtype=np.float64), (n,))
                       for a in (pitch, roll))
    return vectors_to_box(points - centre, yaw, pitch, roll)
