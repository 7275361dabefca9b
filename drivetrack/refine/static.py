"""Static objects: one world pose for all their labels.

A parked car, a pole or a sign does not move, so the frame-to-frame differences between its
labels are label noise, and every one of them moves the object's tracks (a constant error cancels
from a track; a changing one does not). Per-frame registration cannot remove that noise where the
returns observe a direction weakly (height above all), so an object the labels show standing still
gets one world pose, the robust mean of its labels' (:func:`static_object_centres`).

An object is static when its labelled speed (``lidar_box`` ``speed``, when given) stays under
``static_speed_mps`` in every frame and its labels' world centres show no motion either: the
least-squares line through them over time moves slower than ``static_fit_speed_mps`` (and by
less than ``static_max_drift_m`` over the object's labels). A static object is not registered
frame by frame (:func:`drivetrack.refine.scene.refine_scene_boxes`, reason ``static``): with one
pose there is no frame-to-frame error left to find, and a registration could only add jitter (a
thin pole with 11 returns a frame was moved 4-13 cm off exact labels by its normals' error).
"""
from __future__ import annotations

import numpy as np

__all__ = ["static_object_centres"]

#: Labels within this of the one pose (metres, radians) already hold it and are kept as they are.
SAME_POSE_M, SAME_POSE_RAD = 1e-3, 1e-4


def static_object_centres(scene, rows: np.ndarray, speed_mps: float, fit_speed_mps: float,
                          max_drift_m: float = 0.2) -> tuple[np.ndarray, np.ndarray, bool] | None:
    """``(centre float64 [R, 3] m, heading float64 [R] rad, replaced bool)``: one object's labels
    (box rows ``rows``, int [R]) as one world pose, in the vehicle frame of each row's frame; None
    when the object is not static (module docstring; also when the line through its labels' world
    centres drifts by more than ``max_drift_m`` over its labels, a slow mover over a long
    segment) or its boxes carry their own tilt. ``replaced`` is False, and the labels are returned
    as they are (bit for bit), when they already hold one pose (within :data:`SAME_POSE_M` and
    :data:`SAME_POSE_RAD`).

    The world pose: the per-axis median of the labels' world centres and the circular mean of
    their world yaws (the heading axis projected on the world's horizontal plane).
    """
    rows = np.asarray(rows, np.int64)
    boxes = scene.boxes
    if rows.size < 2 or boxes.tilt(rows)[0] is not None:
        return None
    speed = np.asarray(boxes.speed, np.float64)[rows] if boxes.speed is not None else np.full((rows.size, 3), np.nan)
    horizontal = np.linalg.norm(speed[:, :2], axis=-1)
    known = np.isfinite(horizontal)
    if known.any() and not np.all(horizontal[known] <= speed_mps):    # e.g. a car starting off at the end
        return None
    world_from_vehicle = np.asarray(scene.world_from_vehicle, np.float64)[boxes.frame[rows]]      # [R, 4, 4]
    centre_w = np.einsum("rij,rj->ri", world_from_vehicle[:, :3, :3], boxes.center[rows]) + world_from_vehicle[:, :3, 3]
    t = (np.asarray(scene.timestamps_micros, np.int64)[boxes.frame[rows]] - int(scene.timestamps_micros[0])) * 1e-6
    dt = t - t.mean()
    span = float(np.sum(dt * dt))
    if span <= 0:
        return None
    velocity = (dt[:, None] * (centre_w[:, :2] - centre_w[:, :2].mean(0))).sum(0) / span
    speed_fit = float(np.linalg.norm(velocity))
    if not (speed_fit <= (speed_mps if not known.any() else fit_speed_mps)
            and speed_fit * float(np.ptp(t)) <= max_drift_m):
        return None
    heading = boxes.heading[rows]
    forward = np.einsum("rij,rj->ri", world_from_vehicle[:, :3, :3],
                        np.stack([np.cos(heading), np.sin(heading), np.zeros(rows.size)], -1))
    yaw = np.arctan2(forward[:, 1], forward[:, 0])
    mean_yaw = float(np.arctan2(np.sin(yaw).mean(), np.cos(yaw).mean()))
    centre = np.median(centre_w, axis=0)
    vehicle_from_world = np.linalg.inv(world_from_vehicle)
    centre_v = np.einsum("rij,j->ri", vehicle_from_world[:, :3, :3], centre) + vehicle_from_world[:, :3, 3]
    forward_v = np.einsum("rij,j->ri", vehicle_from_world[:, :3, :3], np.array([np.cos(mean_yaw), np.sin(mean_yaw), 0.0]))
    heading_v = np.arctan2(forward_v[:, 1], forward_v[:, 0])
    moved = np.abs(centre_v - boxes.center[rows]).max()
    turned = np.abs(np.angle(np.exp(1j * (heading_v - heading)))).max()
    if moved <= SAME_POSE_M and turned <= SAME_POSE_RAD:      # the labels already hold one pose
        return boxes.center[rows].copy(), heading.copy(), False
    return centre_v, heading_v, True
