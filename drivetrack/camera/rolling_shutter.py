"""Rolling-shutter-aware projection with the Waymo camera model, vectorised in numpy.

Semantics follow the official model (``waymo-open-dataset``,
``src/waymo_open_dataset/wdl_limited/camera/camera_model.cc``); the code is our own.

A Waymo camera reads its sensor line by line. ``rolling_shutter_direction`` (calibration) says in
which image direction: 1 TOP_TO_BOTTOM, 2 LEFT_TO_RIGHT, 3 BOTTOM_TO_TOP, 4 RIGHT_TO_LEFT,
5 GLOBAL_SHUTTER (0 UNKNOWN). Per image (``camera_image``):

- ``readout = camera_readout_done_time - camera_trigger_time - shutter`` (s) is the time the
  readout takes to sweep the image; a pixel at ``x`` (columns) or ``y`` (rows) is captured at the
  middle of its exposure, ``trigger + shutter / 2 + readout * y / H`` (top-to-bottom; the other
  directions use ``H - y``, ``x`` and ``W - x``).
- ``pose`` is ``world_from_vehicle`` at ``pose_timestamp``; ``velocity`` holds the vehicle's linear
  velocity in the world frame and its angular velocity in the vehicle frame (this is what the
  official code does; ``dataset.proto`` calls both "global"). Over the few tens of milliseconds of
  a readout the camera moves at constant velocity: its position is ``p0 + dt v_cam`` (with the
  lever arm ``v_cam = v + w_world x (R t_vehicle_camera)``) and its rotation, to first order,
  ``camera_from_world(dt) = (I - dt [w_cam]x) camera_from_world(0)``.
- Projecting a world point is a 1-D root finding over ``dt = t_capture - pose_timestamp``: the
  line the point lands on must be the line read at ``t_capture``. Like the official code, the
  line position is measured in undistorted normalised coordinates, solved by Newton's method
  (at most 4 iterations, stop below 1e-5 s, reject when the residual stays above 0.1 s).

Points may move: ``velocity_world`` [N, 3] (m/s) moves each point linearly, ``p + dt v``, where
``points_world`` are positions at ``pose_timestamp``.

When a frame has no usable rolling-shutter data (direction 0 or 5, readout <= 0, or any needed
value missing/NaN) projection falls back to a global shutter at ``pose_timestamp``.

Pixels follow :mod:`drivetrack.geometry`: (x, y) = (column, row), pixel i covers [i, i + 1).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivetrack.camera.model import CameraModel
from drivetrack.geometry import invert_rigid
from drivetrack.scene import CameraFrames

__all__ = [
    "TOP_TO_BOTTOM", "LEFT_TO_RIGHT", "BOTTOM_TO_TOP", "RIGHT_TO_LEFT", "GLOBAL_SHUTTER",
    "ShutterState", "Projection", "shutter_state", "project_world", "pixels_from_world", "capture_offsets",
    "world_from_pixels", "pixel_times",
]

TOP_TO_BOTTOM, LEFT_TO_RIGHT, BOTTOM_TO_TOP, RIGHT_TO_LEFT, GLOBAL_SHUTTER = 1, 2, 3, 4, 5

#: Newton's method on the capture time: stop when |residual| is below this (s) ...
_TOLERANCE_S = 1e-5
#: ... or after this many iterations; reject points whose last residual exceeds the limit (s).
_MAX_ITERATIONS = 4
_MAX_RESIDUAL_S = 0.1


def _skew(v: np.ndarray) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


@dataclass(frozen=True)
class ShutterState:
    """Everything the projection of one image needs (built by :func:`shutter_state`).

    Attributes:
        model: the camera.
        world_from_camera: float64 [4, 4] at ``pose_timestamp``.
        pose_timestamp: float, seconds.
        rolling: False for the global-shutter fallback; the fields below are then unused.
        horizontal: readout sweeps columns (LEFT_TO_RIGHT / RIGHT_TO_LEFT) instead of rows.
        time_per_normalised: signed readout seconds per unit of undistorted normalised
            coordinate (u = -y/x for columns, v = -z/x for rows).
        time_per_pixel: signed readout seconds per pixel.
        pose_offset: ``pose_timestamp`` minus the capture time of the principal point (s).
        camera_velocity_world: float64 [3], m/s, camera centre velocity (lever arm included).
        camera_omega_camera: float64 [3], rad/s, angular velocity in the camera frame.
    """
    model: CameraModel
    world_from_camera: np.ndarray
    pose_timestamp: float
    rolling: bool
    horizontal: bool = False
    time_per_normalised: float = 0.0
    time_per_pixel: float = 0.0
    pose_offset: float = 0.0
    camera_velocity_world: np.ndarray | None = None
    camera_omega_camera: np.ndarray | None = None

    @property
    def camera_from_world(self) -> np.ndarray:
        return invert_rigid(self.world_from_camera)

    def pose_at(self, dt: np.ndarray):
        """Camera pose ``dt`` seconds (float [N]) after ``pose_timestamp``, to first order.

        Returns ``(camera_rot_world float64 [N, 3, 3], camera_centre_world float64 [N, 3])``:
        ``p_camera = camera_rot_world @ (p_world - camera_centre_world)``. The rotation is the
        first-order ``(I - dt [w]x) R0`` the official model uses (not re-orthonormalised).
        """
        dt = np.asarray(dt, np.float64)
        r0 = self.world_from_camera[:3, :3].T
        rot = r0[None] - dt[:, None, None] * (_skew(self.camera_omega_camera) @ r0)[None]
        centre = self.world_from_camera[:3, 3][None] + dt[:, None] * self.camera_velocity_world[None]
        return rot, centre

    def rotate_at(self, dt: np.ndarray, vectors_world: np.ndarray) -> np.ndarray:
        """float64 [N, 3]: world vectors float [N, 3] rotated by :meth:`pose_at`'s rotation at
        ``dt`` (float [N], s), without forming the N matrices: ``R0 q - dt [w]x R0 q``."""
        dt = np.asarray(dt, np.float64)
        r0 = self.world_from_camera[:3, :3].T
        return vectors_world @ r0.T - dt[:, None] * (vectors_world @ (_skew(self.camera_omega_camera) @ r0).T)

    def camera_points_at(self, dt: np.ndarray, points_world: np.ndarray) -> np.ndarray:
        """float64 [N, 3]: world points float [N, 3] in the camera frame of :meth:`pose_at` ``dt``
        (float [N], s): ``p_camera = camera_rot_world @ (p_world - camera_centre_world)``."""
        dt = np.asarray(dt, np.float64)
        return self.rotate_at(dt, points_world - self.world_from_camera[:3, 3][None]
                              - dt[:, None] * self.camera_velocity_world[None])


def _normalised_from_pixels(model: CameraModel, pixels: np.ndarray) -> np.ndarray:
    """float64 [..., 2] undistorted normalised (u, v) = (-y/x, -z/x) of pixels [..., 2]."""
    rays = model.rays_from_pixels(pixels)
    return np.stack([-rays[..., 1] / rays[..., 0], -rays[..., 2] / rays[..., 0]], axis=-1)


def _readout_offset(direction: int, width: int, height: int, readout: float,
                    x: float, y: float) -> float:
    """Seconds from the first line's capture to the capture of pixel (x, y)."""
    if direction == TOP_TO_BOTTOM:
        return readout / height * y
    if direction == BOTTOM_TO_TOP:
        return readout / height * (height - y)
    if direction == LEFT_TO_RIGHT:
        return readout / width * x
    return readout / width * (width - x)  # RIGHT_TO_LEFT


def shutter_state(frames: CameraFrames, t: int) -> ShutterState:
    """Projection state of image ``t`` of a camera (rolling, or the global-shutter fallback)."""
    model = frames.model
    world_from_vehicle = np.asarray(frames.world_from_vehicle[t], np.float64)
    if np.isnan(world_from_vehicle).any():
        raise ValueError(f"camera frame {t} has no pose (camera_image.pose is null)")
    world_from_camera = world_from_vehicle @ np.asarray(model.vehicle_from_camera, np.float64)
    pose_ts = float(frames.pose_timestamp[t])
    trigger, done, shutter = (float(frames.trigger_time[t]), float(frames.readout_done_time[t]),
                              float(frames.shutter[t]))
    velocity = np.asarray(frames.velocity[t], np.float64)
    direction = int(model.rolling_shutter_direction)
    readout = done - trigger - shutter
    usable = (direction in (TOP_TO_BOTTOM, LEFT_TO_RIGHT, BOTTOM_TO_TOP, RIGHT_TO_LEFT)
              and np.isfinite([pose_ts, trigger, done, shutter]).all()
              and np.isfinite(velocity).all() and readout > 0)
    if not usable:
        if not np.isfinite(pose_ts):
            pose_ts = trigger + 0.5 * shutter if np.isfinite(trigger + shutter) else np.nan
        return ShutterState(model, world_from_camera, pose_ts, rolling=False)

    horizontal = direction in (LEFT_TO_RIGHT, RIGHT_TO_LEFT)
    t_principal = trigger + 0.5 * shutter + _readout_offset(
        direction, model.width, model.height, readout, model.c_u, model.c_v)
    if horizontal:
        ends = np.array([[0.0, 0.5 * model.height], [model.width, 0.5 * model.height]])
        span = np.diff(_normalised_from_pixels(model, ends)[:, 0])[0]
        pixels_span = model.width
    else:
        ends = np.array([[0.5 * model.width, 0.0], [0.5 * model.width, model.height]])
        span = np.diff(_normalised_from_pixels(model, ends)[:, 1])[0]
        pixels_span = model.height
    sign = -1.0 if direction in (BOTTOM_TO_TOP, RIGHT_TO_LEFT) else 1.0

    rot_wv = world_from_vehicle[:3, :3]
    omega_vehicle = velocity[3:]
    lever_world = rot_wv @ np.asarray(model.vehicle_from_camera, np.float64)[:3, 3]
    camera_velocity = velocity[:3] + np.cross(rot_wv @ omega_vehicle, lever_world)
    omega_camera = np.asarray(model.vehicle_from_camera, np.float64)[:3, :3].T @ omega_vehicle
    return ShutterState(model, world_from_camera, pose_ts, rolling=True, horizontal=horizontal,
                        time_per_normalised=sign * readout / span,
                        time_per_pixel=sign * readout / pixels_span,
                        pose_offset=pose_ts - t_principal, camera_velocity_world=camera_velocity,
                        camera_omega_camera=omega_camera)


@dataclass(frozen=True)
class Projection:
    """Result of :func:`project_world` for N points.

    Attributes:
        pixels: float64 [N, 2], distorted pixel (x, y); NaN where not ``valid``.
        valid: bool [N], in front of the camera, trusted distortion, capture time solved.
            Inside-the-image is not required (use ``model.inside_image``).
        capture_time: float64 [N], seconds (clock of ``pose_timestamp``), when the camera saw
            the point; NaN where not valid.
        points_camera: float64 [N, 3], metres, the point in the camera frame at its capture time
            (``points_camera[:, 0]`` is the z-depth); NaN where not valid.
    """
    pixels: np.ndarray
    valid: np.ndarray
    capture_time: np.ndarray
    points_camera: np.ndarray


def _check_points(points: np.ndarray, name: str) -> np.ndarray:
    points = np.asarray(points, np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} must be float [N, 3], got shape {points.shape}")
    return points


def _distorted(model: CameraModel, points_camera: np.ndarray):
    """(pixels [N, 2], trusted [N]) like ``CameraModel.pixels_from_camera`` for x > 0 points."""
    return model.pixels_from_camera(points_camera)


def project_world(frames: CameraFrames, t: int, points_world: np.ndarray,
                  velocity_world: np.ndarray | None = None) -> Projection:
    """Project world points into image ``t`` of a camera, rolling shutter included.

    Args:
        frames: the camera (calibration + per-image pose, velocity and shutter timing).
        t: frame index.
        points_world: float [N, 3], metres, world frame, positions at ``pose_timestamp[t]``.
        velocity_world: optional float [N, 3], m/s, world frame; each point moves linearly
            during the readout.
    """
    points_world = _check_points(points_world, "points_world")
    n = points_world.shape[0]
    if velocity_world is None:
        velocity_world = np.zeros_like(points_world)
    else:
        velocity_world = _check_points(velocity_world, "velocity_world")
        if velocity_world.shape != points_world.shape:
            raise ValueError(f"velocity_world shape {velocity_world.shape} differs from "
                             f"points_world shape {points_world.shape}")
    state = shutter_state(frames, t)
    model = state.model
    if not state.rolling or n == 0:
        camera_from_world = state.camera_from_world
        points_camera = points_world @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
        pixels, valid = _distorted(model, points_camera)
        capture = np.where(valid, state.pose_timestamp, np.nan)
        points_camera[~valid] = np.nan
        return Projection(pixels, valid, capture, points_camera)

    omega_skew = _skew(state.camera_omega_camera)
    dt = np.zeros(n)
    active = np.ones(n, bool)
    in_front = np.ones(n, bool)
    residual = np.full(n, 2 * _TOLERANCE_S)
    axis = 0 if state.horizontal else 1
    for _ in range(_MAX_ITERATIONS):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        p_cam = state.camera_points_at(dt[idx], points_world[idx] + dt[idx, None] * velocity_world[idx])
        x = p_cam[:, 0]
        front = x > 0
        in_front[idx[~front]] = False
        safe_x = np.where(front, x, 1.0)
        normalised = -p_cam[:, 1 + axis] / safe_x
        res = dt[idx] - normalised * state.time_per_normalised + state.pose_offset
        # d(normalised)/d(dt) through the point's and the camera's motion (chain rule on -y/x).
        rate = state.rotate_at(dt[idx], velocity_world[idx] - state.camera_velocity_world) - p_cam @ omega_skew.T
        d_norm = (normalised * rate[:, 0] - rate[:, 1 + axis]) / safe_x
        jac = 1.0 - state.time_per_normalised * d_norm
        step = np.where(front, -res / jac, 0.0)
        dt[idx] += step
        residual[idx] = res
        active[idx] = front & (np.abs(res) > _TOLERANCE_S)
    converged = in_front & (np.abs(residual) <= _MAX_RESIDUAL_S)

    points_camera = state.camera_points_at(dt, points_world + dt[:, None] * velocity_world)
    pixels, trusted = _distorted(model, points_camera)
    valid = converged & trusted
    pixels[~valid] = np.nan
    points_camera[~valid] = np.nan
    capture = np.where(valid, state.pose_timestamp + dt, np.nan)
    return Projection(pixels, valid, capture, points_camera)


def capture_offsets(frames: CameraFrames, t: int, points_vehicle: np.ndarray, velocity_vehicle: np.ndarray,
                    world_from_vehicle: np.ndarray, frame_time_s: float) -> np.ndarray:
    """float64 [N], seconds: when image ``t`` captured each of N moving points, minus
    ``frame_time_s`` (the clock of ``pose_timestamp``); NaN where the projection is not valid
    (:class:`Projection`).

    ``points_vehicle`` float [N, 3] (metres) are positions at ``frame_time_s`` in the vehicle frame
    ``world_from_vehicle`` float [4, 4] of that time, moving at ``velocity_vehicle`` float [N, 3]
    (m/s, world velocity expressed in that frame): how ``label.proto`` solves a
    ``camera_synced_box``'s t_capture for its box centre and speed.
    """
    rotation, origin = world_from_vehicle[:3, :3], world_from_vehicle[:3, 3]
    velocity = np.asarray(velocity_vehicle, np.float64) @ rotation.T
    lead = frames.pose_timestamp[t] - frame_time_s            # the points at the pose time
    points = np.asarray(points_vehicle, np.float64) @ rotation.T + origin + lead * velocity
    projection = project_world(frames, t, points, velocity)
    return np.where(projection.valid, projection.capture_time - frame_time_s, np.nan)


def pixels_from_world(frames: CameraFrames, t: int, points_world: np.ndarray,
                      velocity_world: np.ndarray | None = None):
    """``(pixels float64 [N, 2], valid bool [N], capture_time float64 [N])``.

    See :func:`project_world` (which also returns the camera-frame points).
    """
    p = project_world(frames, t, points_world, velocity_world)
    return p.pixels, p.valid, p.capture_time


def pixel_times(frames: CameraFrames, t: int, pixels: np.ndarray) -> np.ndarray:
    """float64 [N] capture time (s) of pixels (x, y) float [N, 2] of image ``t``.

    ``pose_timestamp + time_per_pixel * (pixel - principal point) - pose_offset`` along the
    readout axis; ``pose_timestamp`` everywhere for the global-shutter fallback.
    """
    pixels = np.asarray(pixels, np.float64)
    state = shutter_state(frames, t)
    if not state.rolling:
        return np.full(pixels.shape[:-1], state.pose_timestamp)
    spacing = (pixels[..., 0] - state.model.c_u if state.horizontal
               else pixels[..., 1] - state.model.c_v)
    return state.pose_timestamp + state.time_per_pixel * spacing - state.pose_offset


def world_from_pixels(frames: CameraFrames, t: int, pixels: np.ndarray,
                      depth: np.ndarray) -> np.ndarray:
    """Inverse projection: world points float64 [N, 3] of pixels [N, 2] at z-depth [N] (metres).

    The camera pose is taken at each pixel's capture time (:func:`pixel_times`); the result is
    where a static point would have to be to appear at that pixel.
    """
    pixels = np.asarray(pixels, np.float64)
    if pixels.ndim != 2 or pixels.shape[1] != 2:
        raise ValueError(f"pixels must be float [N, 2], got shape {pixels.shape}")
    depth = np.broadcast_to(np.asarray(depth, np.float64), pixels.shape[:1])
    state = shutter_state(frames, t)
    normalised = _normalised_from_pixels(state.model, pixels)
    points_camera = np.stack([depth, -normalised[:, 0] * depth, -normalised[:, 1] * depth], -1)
    if not state.rolling:
        w = state.world_from_camera
        return points_camera @ w[:3, :3].T + w[:3, 3]
    dt = pixel_times(frames, t, pixels) - state.pose_timestamp
    rot, centre = state.pose_at(dt)
    return np.einsum("nji,nj->ni", rot, points_camera) + centre

