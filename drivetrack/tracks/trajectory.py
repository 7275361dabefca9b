"""Per-object continuous-time trajectories: where each box was at any time (issue 16).

Every labelled box row k of a scene is a *sample* of its object's pose in the world frame at a
sample time ``time_s[k]`` (seconds since the scene's first frame):

- ``label_time="frame"``: ``lidar_box`` lives at its frame's timestamp (Waymo's ``label.proto``
  convention for ``camera_synced_box``);
- ``label_time="sweep"``: ``lidar_box`` sits where the object was when the TOP sweep passed its
  centre: frame time + :func:`sweep_label_offsets`, from the sweep's time law (offset linear in
  the azimuth about the lidar, whose position is fitted too) that the returns' own capture times
  (``LidarReturns.capture_offset_s``) give, :func:`fit_sweep_law`;
- ``label_time="auto"``: the convention whose boxes, moved to each return's capture time, leave
  fewer return-metres outside the boxes (:func:`label_time_residual`), one choice per segment.

Motion model: around each sample, constant acceleration in world position and constant yaw
acceleration, ``p(t) = p_k + v_k tau + a_k tau^2 / 2`` with ``tau = t - time_s[k]``; ``v_k`` and
``a_k`` by least squares over the object's samples up to :data:`WINDOW_HALF` before and after
(through the sample itself: the label is reproduced exactly; exact for constant acceleration).
A clip frame's image and a return of frame k are placed from sample k, never more than a sweep
away. Why not a spline through the samples: under ``sweep`` two consecutive samples of an object
behind the ego lie on both sides of the sweep's start and may be a millisecond apart; a fit over
a window is robust to that, a spline's tangents are not. Pitch and roll in the world frame are
held from the sample: a refined 6-DOF box's (``Boxes.pitch`` / ``roll``, issue 8) as they
are; for yaw-only labels, whose world tilt is the ego's frame-to-frame pitch and roll rather than
the object's, one tilt per object, their mean (``label_tilt="constant"``; ``"linear"``: a
straight line in time through them). A tilt that is constant over time cancels from every track
(an object's points are put into its box frame and taken out again with the same tilt), so only
tilt *changes* move the tracks, and the ego's pitch and roll changes (suspension, its own road)
say nothing about the object's. An object with one sample moves with its ``speed`` column (world
velocity in the vehicle frame) when finite, else stands still. Positions and yaw pass through
the labels exactly: smoothing would move the labels themselves, which the pose refinement
(issue 8) owns.

Times are float64 seconds relative to ``scene.timestamps_micros[0]``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivetrack.geometry import rotation_from_rpy
from drivetrack.waymo.schema import LaserName

__all__ = ["LABEL_TILTS", "LABEL_TIMES", "TIME_MODELS", "BoxTrajectory", "build_trajectory", "sweep_label_offsets",
           "label_time_residual", "segment_trajectory", "points_box_at", "points_box_at_numpy",
           "fit_sweep_law", "local_quadratic", "synced_samples"]

#: ``TrackConfig.label_time`` values.
LABEL_TIMES = ("frame", "sweep", "auto")
#: ``TrackConfig.label_tilt`` values: the world tilt of yaw-only labels, one per object (``constant``,
#: their mean) or a straight line in time through them (``linear``).
LABEL_TILTS = ("constant", "linear")
#: ``TrackConfig.time_model`` values: ``trajectory`` (this module) or ``velocity`` (the box moved
#: along its finite-difference velocity from the frame time to the image pose time, pre-issue 16).
TIME_MODELS = ("trajectory", "velocity")

#: Returns this far (metres) outside a box still count for :func:`label_time_residual`.
RESIDUAL_MARGIN_M = 0.6
#: At most this many boxes vote in ``auto`` (bounds its cost; the ones with the largest
#: difference between the conventions are not preferred: an even stride over the scene).
MAX_VOTERS = 48
#: Samples on each side of a row in its local quadratic fit.
WINDOW_HALF = 2
#: Only boxes whose two conventions differ by at least this (metres) vote in ``auto``.
MIN_VOTE_SHIFT_M = 0.02
#: A synced box captured less than this (seconds) from its label's frame time is no sample.
MIN_SYNCED_OFFSET_S = 1e-4
#: An object whose box centres all lie within this (metres) of each other in the world stands
#: still: its synced boxes are no samples.
STILL_M = 1e-6


def _wrap(a):
    return np.angle(np.exp(1j * np.asarray(a, np.float64)))


def _euler_zyx(rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(yaw, pitch, roll) float64 [...] of rotations [..., 3, 3] = Rz(yaw) Ry(pitch) Rx(roll)
    (the inverse of ``drivetrack.geometry.rotation_from_rpy``)."""
    yaw = np.arctan2(rotation[..., 1, 0], rotation[..., 0, 0])
    pitch = np.arcsin(np.clip(-rotation[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(rotation[..., 2, 1], rotation[..., 2, 2])
    return yaw, pitch, roll


@dataclass
class BoxTrajectory:
    """Continuous-time world poses of every box row's object (K rows of ``scene.boxes``).

    Attributes:
        label_time: the convention in use, ``frame`` or ``sweep``.
        frame_time_s: float64 [K], the row's frame time, s since the scene's first frame.
        time_s: float64 [K], the sample (label) time of the row.
        centre: float64 [K, 3], metres, world box centre at ``time_s``.
        yaw, pitch, roll: float64 [K], radians, world orientation (``Rz Ry Rx``) at ``time_s``.
        velocity, acceleration: float64 [K, 3], m/s and m/s^2, of the centre at ``time_s``.
        yaw_rate, yaw_acceleration: float64 [K], rad/s and rad/s^2.
    """
    label_time: str
    frame_time_s: np.ndarray
    time_s: np.ndarray
    centre: np.ndarray
    yaw: np.ndarray
    pitch: np.ndarray
    roll: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    yaw_rate: np.ndarray
    yaw_acceleration: np.ndarray

    def motion(self, rows: np.ndarray, time_s: np.ndarray):
        """State of the objects of box rows ``rows`` (int [N]) at ``time_s`` (float [N], s).

        Returns ``(centre [N, 3] m, yaw [N], pitch [N], roll [N] rad, velocity [N, 3] m/s,
        yaw_rate [N] rad/s)``, world frame, from the row's own sample (module docstring).
        """
        rows = np.asarray(rows, np.int64).reshape(-1)
        tau = np.broadcast_to(np.asarray(time_s, np.float64), rows.shape) - self.time_s[rows]
        t1 = tau[:, None]
        centre = self.centre[rows] + t1 * self.velocity[rows] + 0.5 * t1 * t1 * self.acceleration[rows]
        velocity = self.velocity[rows] + t1 * self.acceleration[rows]
        yaw = self.yaw[rows] + tau * self.yaw_rate[rows] + 0.5 * tau * tau * self.yaw_acceleration[rows]
        yaw_rate = self.yaw_rate[rows] + tau * self.yaw_acceleration[rows]
        return centre, yaw, self.pitch[rows].copy(), self.roll[rows].copy(), velocity, yaw_rate

    def world_from_box(self, rows: np.ndarray, time_s: np.ndarray) -> np.ndarray:
        """float64 [N, 4, 4]: the objects of box rows ``rows`` (int [N]) at ``time_s`` (float [N], s)."""
        centre, yaw, pitch, roll, _, _ = self.motion(rows, time_s)
        out = np.zeros(centre.shape[:1] + (4, 4))
        out[:, :3, :3] = rotation_from_rpy(roll, pitch, yaw)
        out[:, :3, 3] = centre
        out[:, 3, 3] = 1.0
        return out


def _window(keys: np.ndarray, time_s: np.ndarray, half: int) -> np.ndarray:
    """int64 [K, 2 half]: the rows of the same key up to ``half`` samples before and after each
    row in time (-1 where the object has fewer)."""
    k = time_s.shape[0]
    order = np.lexsort((time_s, keys))
    sorted_keys = keys[order]
    position = np.empty(k, np.int64)
    position[order] = np.arange(k)
    out = np.full((k, 2 * half), -1, np.int64)
    col = 0
    for step in [*range(-half, 0), *range(1, half + 1)]:
        other = position + step
        ok = (other >= 0) & (other < k)
        ok[ok] = sorted_keys[other[ok]] == keys[ok]
        out[ok, col] = order[other[ok]]
        col += 1
    return out


def local_quadratic(delta: np.ndarray, tau: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and second time derivatives (float64 [K, D] each) at each row: least squares
    ``v tau + a tau^2 / 2 = delta`` over its window (``delta`` float64 [K, W, D], the neighbours'
    values minus the row's; ``tau`` float64 [K, W], their times minus the row's; ``valid`` bool
    [K, W]); one neighbour: its slope and 0; none: 0."""
    k, _, d = delta.shape
    tau = np.where(valid, tau, 0.0)
    delta = np.where(valid[..., None], delta, 0.0)
    x1, x2 = tau, 0.5 * tau * tau
    s11, s12, s22 = (x1 * x1).sum(1), (x1 * x2).sum(1), (x2 * x2).sum(1)
    b1, b2 = (x1[..., None] * delta).sum(1), (x2[..., None] * delta).sum(1)
    det = s11 * s22 - s12 * s12
    count = valid.sum(1)
    quad = (count >= 2) & (det > 1e-9 * np.maximum(s11 * s22, 1e-300))
    velocity = np.zeros((k, d))
    acceleration = np.zeros((k, d))
    safe = np.where(quad, det, 1.0)[:, None]
    velocity[quad] = ((s22[:, None] * b1 - s12[:, None] * b2) / safe)[quad]
    acceleration[quad] = ((s11[:, None] * b2 - s12[:, None] * b1) / safe)[quad]
    line = ~quad & (count >= 1) & (s11 > 0)
    velocity[line] = (b1 / np.where(s11 > 0, s11, 1.0)[:, None])[line]
    return velocity, acceleration


def synced_samples(scene) -> tuple[np.ndarray, np.ndarray]:
    """``(offset_s float64 [K], shift_world float64 [K, 3])``: each box row's
    ``lidar_camera_synced_box`` as a time sample, NaN where it gives none.

    ``offset_s`` is ``t_capture - t_frame``, t_capture the time its most visible camera
    (``Boxes.synced_camera``) captured the box centre: the label centre moving at its labelled
    ``speed`` (0 where NaN), projected with that camera's rolling shutter and the ego motion
    (:func:`drivetrack.camera.rolling_shutter.project_world`), as Waymo's ``label.proto`` solves
    it. ``shift_world`` is ``Boxes.synced_shift`` in the world frame (metres). NaN where the scene
    has no synced box for the row, its camera is not loaded, the centre does not project (behind
    the camera), ``|offset_s|`` is below :data:`MIN_SYNCED_OFFSET_S` (the same time as the
    label: nothing to add), or all of the object's boxes sit at one world position (within
    :data:`STILL_M`: pose refinement's static objects stand still, whatever their labelled
    speed). Cached on the scene.
    """
    cache = scene.__dict__.get("_synced_samples")
    if cache is not None:
        return cache
    from drivetrack.camera.rolling_shutter import capture_offsets

    boxes = scene.boxes
    k = len(boxes)
    offset = np.full(k, np.nan)
    shift_world = np.full((k, 3), np.nan)
    shift = getattr(boxes, "synced_shift", None)
    if shift is not None and k:
        frame_s = np.asarray(scene.timestamps_micros, np.int64) * 1e-6
        world_from_vehicle = np.asarray(scene.world_from_vehicle, np.float64)
        camera = np.asarray(boxes.synced_camera, np.int64)
        usable = np.isfinite(shift).all(axis=1) & np.isin(camera, list(scene.cameras))
        for cam in np.unique(camera[usable]):
            frames = scene.cameras[int(cam)]
            rows_cam = np.flatnonzero(usable & (camera == cam))
            for t in np.unique(boxes.frame[rows_cam]):
                rows = rows_cam[boxes.frame[rows_cam] == t]
                if not np.isfinite(frames.pose_timestamp[t]):
                    continue
                speed = np.asarray(boxes.speed, np.float64)[rows]
                offset[rows] = capture_offsets(frames, int(t), np.asarray(boxes.center, np.float64)[rows],
                                               np.where(np.isfinite(speed), speed, 0.0), world_from_vehicle[t],
                                               frame_s[t])
                shift_world[rows] = shift[rows] @ world_from_vehicle[t, :3, :3].T
        # an object all of whose boxes sit at one world position (pose refinement's static
        # objects) stands still: a labelled speed does not move it
        keys = np.unique(boxes.object_id.astype(str), return_inverse=True)[1]
        centre = (np.einsum("kij,kj->ki", world_from_vehicle[boxes.frame, :3, :3], np.asarray(boxes.center, np.float64))
                  + world_from_vehicle[boxes.frame, :3, 3])
        order = np.argsort(keys, kind="stable")
        starts = np.r_[0, np.flatnonzero(np.diff(keys[order])) + 1]
        spread = (np.maximum.reduceat(centre[order], starts) - np.minimum.reduceat(centre[order], starts)).max(axis=1)
        small = ~(np.abs(offset) >= MIN_SYNCED_OFFSET_S) | (spread[keys] < STILL_M)
        offset[small] = np.nan
        shift_world[small] = np.nan
    scene.__dict__["_synced_samples"] = (offset, shift_world)
    return offset, shift_world


def build_trajectory(scene, label_offset_s: np.ndarray, label_time: str = "frame",
                     label_tilt: str = "constant", synced: bool = False) -> BoxTrajectory:
    """The :class:`BoxTrajectory` of every box row of ``scene``, sampled at frame time + ``label_offset_s``.

    Args:
        scene: a :class:`drivetrack.scene.Scene`.
        label_offset_s: float64 [K], seconds, each row's label time minus its frame time.
        label_time: the name of the convention (recorded only).
        label_tilt: the world tilt of objects whose boxes are all yaw-only, one of
            :data:`LABEL_TILTS` (module docstring).
        synced: also fit positions through the ``lidar_camera_synced_box`` samples
            (:func:`synced_samples`; module docstring).
    """
    if label_tilt not in LABEL_TILTS:
        raise ValueError(f"segment {scene.segment!r}: label_tilt must be one of {LABEL_TILTS}, got {label_tilt!r}")
    boxes = scene.boxes
    k = len(boxes)
    frame_time = ((np.asarray(scene.timestamps_micros, np.int64)[boxes.frame]
                   - int(scene.timestamps_micros[0])) * 1e-6) if k else np.zeros(0)
    time_s = frame_time + np.asarray(label_offset_s, np.float64).reshape(k)
    world_from_vehicle = np.asarray(scene.world_from_vehicle, np.float64)[boxes.frame]
    world_from_box = world_from_vehicle @ boxes.vehicle_from_box() if k else np.zeros((0, 4, 4))
    yaw, pitch, roll = _euler_zyx(world_from_box[:, :3, :3])
    keys = np.unique(boxes.object_id.astype(str), return_inverse=True)[1] if k else np.zeros(0, np.int64)
    if k:
        # Yaw-only labels in the frame of a pitching, rolling ego tilt the object in the world by
        # the ego's tilt, which changes frame to frame with the ego's suspension and road, not
        # with the object: one tilt per object (their mean), or a straight line in time, for
        # objects whose boxes are all yaw-only (a refined 6-DOF pose is kept as it is).
        box_pitch, box_roll = boxes.tilt()
        flat = (np.ones(k, bool) if box_pitch is None
                else (box_pitch == 0) & (box_roll == 0))
        level = np.bincount(keys, ~flat, minlength=keys.max() + 1)[keys] == 0
        if level.any():
            fit = _linear_in_time if label_tilt == "linear" else _mean_per_key
            fitted = [fit(a, time_s, keys) for a in (pitch, roll)]
            pitch = np.where(level, fitted[0], pitch)
            roll = np.where(level, fitted[1], roll)
    centre = world_from_box[:, :3, 3].copy()
    window = _window(keys, time_s, WINDOW_HALF)                                             # [K, W]
    valid = window >= 0
    w = np.where(valid, window, np.arange(k)[:, None])
    tau = time_s[w] - time_s[:, None]
    delta = centre[w] - centre[:, None]
    position_valid, position_tau = valid, tau
    if synced and k:
        # the synced boxes of the row and of its window: the label moved by speed x (t_capture -
        # t_frame), a position sample that long after the label's own time
        offset, shift = synced_samples(scene)
        own = np.concatenate([np.arange(k)[:, None], w], axis=1)                           # [K, W + 1]
        has = np.concatenate([np.ones((k, 1), bool), valid], axis=1) & np.isfinite(offset)[own]
        safe = np.where(has, own, 0)
        synced_tau = np.where(has, time_s[safe] + np.nan_to_num(offset[safe]) - time_s[:, None], 0.0)
        synced_delta = np.where(has[..., None], centre[safe] + np.nan_to_num(shift[safe]) - centre[:, None], 0.0)
        position_valid = np.concatenate([valid, has], axis=1)
        position_tau = np.concatenate([tau, synced_tau], axis=1)
        delta = np.concatenate([delta, synced_delta], axis=1)
    velocity, acceleration = local_quadratic(delta, position_tau, position_valid)
    turn = _wrap(yaw[w] - yaw[:, None])[..., None]                    # neighbours' yaw, unwrapped
    yaw_rate, yaw_acceleration = (a[:, 0] for a in local_quadratic(turn, tau, valid))
    alone = ~position_valid.any(axis=1)
    if alone.any():
        speed = np.asarray(boxes.speed, np.float64)[alone]
        ok = np.isfinite(speed).all(axis=1)
        velocity[alone] = np.einsum("nij,nj->ni", world_from_vehicle[alone, :3, :3], np.where(ok[:, None], speed, 0.0))
    return BoxTrajectory(label_time, frame_time, time_s, centre, yaw, pitch, roll, velocity, acceleration,
                         yaw_rate, yaw_acceleration)


def _mean_per_key(values: np.ndarray, time_s: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """float64 [K]: per key (int [K]), the mean of ``values`` at each row (``time_s`` unused:
    the signature of :func:`_linear_in_time`)."""
    count = np.bincount(keys).astype(np.float64)
    return (np.bincount(keys, values) / count)[keys]


def _linear_in_time(values: np.ndarray, time_s: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """float64 [K]: per key (int [K]), the least-squares line through ``values`` over ``time_s``
    evaluated at each row's time (the mean for a key with one time)."""
    count = np.bincount(keys).astype(np.float64)
    mean_t = np.bincount(keys, time_s) / count
    mean_v = np.bincount(keys, values) / count
    dt = time_s - mean_t[keys]
    var = np.bincount(keys, dt * dt)
    cov = np.bincount(keys, dt * (values - mean_v[keys]))
    slope = np.where(var > 0, cov / np.where(var > 0, var, 1.0), 0.0)
    return mean_v[keys] + slope[keys] * dt


def _ego_motion_vehicle(scene) -> tuple[np.ndarray, np.ndarray]:
    """``(velocity float64 [T, 3] m/s, yaw_rate float64 [T] rad/s)`` of the ego in the vehicle
    frame of each frame, by finite differences of the frame poses (0 for a one-frame scene)."""
    world_from_vehicle = np.asarray(scene.world_from_vehicle, np.float64)
    t = (np.asarray(scene.timestamps_micros, np.int64) - int(scene.timestamps_micros[0])) * 1e-6
    if t.size < 2:
        return np.zeros((t.size, 3)), np.zeros(t.size)
    velocity_world = np.gradient(world_from_vehicle[:, :3, 3], t, axis=0)
    yaw = np.unwrap(np.arctan2(world_from_vehicle[:, 1, 0], world_from_vehicle[:, 0, 0]))
    return np.einsum("tji,tj->ti", world_from_vehicle[:, :3, :3], velocity_world), np.gradient(yaw, t)


def fit_sweep_law(scene, max_samples: int = 100_000) -> tuple[float, float, np.ndarray] | None:
    """The TOP sweep's time law, ``offset = a + b * azimuth about the lidar``, from the returns.

    Each TOP return i of frame f (``capture_offset_s`` o_i, point p_i in the vehicle frame of the
    frame) was captured from the lidar at ``l + v_f o_i``, turned by ``w_f o_i`` (ego velocity and
    yaw rate in that frame, :func:`_ego_motion_vehicle`): ``o_i = a + b * (atan2(p_i - l - v_f o_i)
    - w_f o_i)``. ``(a s, b s/rad, l float64 [2] metres, the lidar's horizontal position in the
    vehicle frame)`` by Gauss-Newton over returns away from the sweep's seam at the rear;
    None when the scene has fewer than 100 usable returns.
    """
    lidar = scene.lidar
    offsets = getattr(lidar, "capture_offset_s", None)
    if offsets is None:
        return None
    top = np.flatnonzero((lidar.laser == int(LaserName.TOP)) & (offsets != 0))
    top = top[:: max(1, top.size // max_samples)]
    if top.size < 100:
        return None
    velocity, yaw_rate = _ego_motion_vehicle(scene)
    o = offsets[top].astype(np.float64)
    q0 = lidar.points_vehicle[top, :2] - velocity[lidar.frame[top], :2] * o[:, None]
    turn = yaw_rate[lidar.frame[top]] * o
    keep = np.abs(np.arctan2(q0[:, 1], q0[:, 0])) < 2.7
    o, q0, turn = o[keep], q0[keep], turn[keep]
    if o.size < 100:
        return None
    theta = np.zeros(4)                                              # a, b, lx, ly
    for _ in range(8):
        q = q0 - theta[2:]
        r2 = (q * q).sum(-1)
        phi = np.arctan2(q[:, 1], q[:, 0]) - turn
        residual = theta[0] + theta[1] * phi - o
        jac = np.stack([np.ones_like(o), phi, theta[1] * q[:, 1] / r2, -theta[1] * q[:, 0] / r2], -1)
        if theta[1] == 0.0:                                          # first step: the linear fit
            jac = jac[:, :2]
        step = np.linalg.lstsq(jac, -residual, rcond=None)[0]
        theta[:step.size] += step
    return float(theta[0]), float(theta[1]), theta[2:].copy()


def sweep_label_offsets(scene, box_point_offsets: np.ndarray | None = None,
                        box_point_index: np.ndarray | None = None) -> np.ndarray:
    """float64 [K], seconds: when the TOP sweep passed each box's centre, minus its frame time.

    The fixed point of ``o = a + b * (atan2(c - l - v o) - w o)`` for each box centre c (vehicle
    frame of its frame), with the sweep law of :func:`fit_sweep_law`: the box is taken where the
    object was when the sweep passed it, seen from where the lidar was then. A scene without
    capture times, or whose law cannot be fitted, gets 0 everywhere. (The box point arguments are
    accepted for callers that have them; the law uses every TOP return of the scene.)
    """
    boxes = scene.boxes
    k = len(boxes)
    out = np.zeros(k)
    law = fit_sweep_law(scene) if k else None
    if law is None:
        return out
    a, b, origin = law
    velocity, yaw_rate = _ego_motion_vehicle(scene)
    frame = boxes.frame
    centre = np.asarray(boxes.center, np.float64)[:, :2]
    for _ in range(6):
        q = centre - origin - velocity[frame, :2] * out[:, None]
        out = a + b * (_wrap(np.arctan2(q[:, 1], q[:, 0]) - yaw_rate[frame] * out))
    return out


def points_box_at(trajectory: BoxTrajectory, rows: np.ndarray, time_s: np.ndarray,
                  points_world: np.ndarray) -> np.ndarray:
    """float64 [N, 3]: world points float [N, 3] in the frame of box row ``rows`` (int [N])'s
    object at ``time_s`` (float [N], s): the body point of a return captured then.

    With numba, the pose and the product are one pass (``drivetrack.tracks.kernel.points_box_at``,
    the same float64 operations in the same order: bit-identical; about 6x faster on a segment's
    returns); :func:`points_box_at_numpy` is the numpy form, the reference."""
    from drivetrack.numba_compat import NUMBA_AVAILABLE

    if not NUMBA_AVAILABLE:
        return points_box_at_numpy(trajectory, rows, time_s, points_world)
    from drivetrack.tracks import kernel

    rows = np.asarray(rows, np.int64).reshape(-1)
    tau = np.broadcast_to(np.asarray(time_s, np.float64), rows.shape) - trajectory.time_s[rows]
    # the angles' cosines and sines by numpy, as BoxTrajectory.motion and rotation_from_rpy take them
    yaw = trajectory.yaw[rows] + tau * trajectory.yaw_rate[rows] + 0.5 * tau * tau * trajectory.yaw_acceleration[rows]
    roll, pitch = trajectory.roll[rows], trajectory.pitch[rows]
    out = np.empty((rows.size, 3))
    kernel.points_box_at(rows, np.ascontiguousarray(tau),
                         np.ascontiguousarray(np.broadcast_to(np.asarray(points_world, np.float64), (rows.size, 3))),
                         np.ascontiguousarray(trajectory.centre, dtype=np.float64),
                         np.ascontiguousarray(trajectory.velocity, dtype=np.float64),
                         np.ascontiguousarray(trajectory.acceleration, dtype=np.float64),
                         np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw), out)
    return out


def points_box_at_numpy(trajectory: BoxTrajectory, rows: np.ndarray, time_s: np.ndarray,
                        points_world: np.ndarray) -> np.ndarray:
    """:func:`points_box_at` in numpy, through ``BoxTrajectory.world_from_box`` (the reference)."""
    world_from_box = trajectory.world_from_box(rows, time_s)
    rel = np.asarray(points_world, np.float64) - world_from_box[:, :3, 3]
    return np.einsum("nji,nj->ni", world_from_box[:, :3, :3], rel)


def label_time_residual(scene, trajectory: BoxTrajectory, rows: np.ndarray, lidar_rows: np.ndarray) -> float:
    """Mean distance (metres) outside their box of returns ``lidar_rows`` (int [N]) of box rows
    ``rows`` (int [N]), with the box taken from ``trajectory`` at each return's capture time;
    NaN when there are none. Returns more than :data:`RESIDUAL_MARGIN_M` outside under the
    trajectory do not count (other surfaces)."""
    if rows.size == 0:
        return float("nan")
    lidar = scene.lidar
    frame = scene.boxes.frame[rows]
    offsets = lidar.capture_offset_s[lidar_rows].astype(np.float64)
    world = (np.einsum("nij,nj->ni", scene.world_from_vehicle[frame, :3, :3], lidar.points_vehicle[lidar_rows])
             + scene.world_from_vehicle[frame, :3, 3])
    local = points_box_at(trajectory, rows, trajectory.frame_time_s[rows] + offsets, world)
    half = scene.boxes.size[rows] / 2.0
    outside = np.linalg.norm(np.maximum(np.abs(local) - half, 0.0), axis=-1)
    outside = outside[outside <= RESIDUAL_MARGIN_M]
    return float(outside.mean()) if outside.size else float("nan")


def scene_label_times(scene, config) -> tuple[np.ndarray, dict]:
    """``(label_offset_s float64 [K], decision)``: each box row's label time minus its frame time
    under ``config.label_time`` (a :class:`drivetrack.tracks.TrackConfig`), and the decision.

    ``decision`` holds ``label_time`` (the convention used), ``requested``, ``residual_frame_m``
    and ``residual_sweep_m`` (:func:`label_time_residual` over the returns of boxes whose two
    conventions differ by >= :data:`MIN_VOTE_SHIFT_M`; NaN unless ``auto`` and some box votes)
    and ``votes`` (such boxes, at most :data:`MAX_VOTERS`). Cached on the scene (``scene.__dict__["_label_times"]``);
    :func:`carry_label_times` hands the decision on to a scene with refined boxes, so that the
    labels decide once and the refined boxes keep their convention.
    """
    label_time = config.label_time
    if label_time not in LABEL_TIMES:
        raise ValueError(f"segment {scene.segment!r}: TrackConfig.label_time must be one of {LABEL_TIMES}, "
                         f"got {label_time!r}")
    cache = scene.__dict__.setdefault("_label_times", {})
    key = (label_time, config.label_tilt, config.synced_boxes)
    if key in cache:
        return cache[key]
    k = len(scene.boxes)
    decision = {"requested": label_time, "residual_frame_m": float("nan"), "residual_sweep_m": float("nan"),
                "votes": 0, "label_time": "frame"}
    chosen = cache.get("chosen")           # carried from the labels by carry_label_times
    if label_time == "frame" or (chosen == "frame" and label_time == "auto"):
        offsets = np.zeros(k)
        if chosen is not None:
            decision.update(cache["decision"])
    elif chosen == "sweep" and label_time in ("auto", "sweep") and len(cache.get("offsets", ())) == k:
        # the refined boxes keep the label times their returns were registered at (the labels'):
        # recomputed from the refined centres they would move by the label noise's azimuth
        # (0.2-0.5 ms beside the vehicle, 3-6 mm along a car passing at 13 m/s)
        offsets = np.asarray(cache["offsets"], np.float64).copy()
        decision.update(cache["decision"])
    else:
        sweep = sweep_label_offsets(scene)
        offsets = sweep
        decision["label_time"] = "sweep"
        if label_time == "auto" and chosen is not None:
            decision.update(cache["decision"])
        elif label_time == "auto":
            by_sweep = build_trajectory(scene, sweep, "sweep", config.label_tilt, config.synced_boxes)
            by_frame = build_trajectory(scene, np.zeros(k), "frame", config.label_tilt, config.synced_boxes)
            shift = np.linalg.norm(by_frame.velocity, axis=-1) * np.abs(sweep)
            voters = np.flatnonzero(shift >= MIN_VOTE_SHIFT_M)
            if voters.size > MAX_VOTERS:       # evenly strided: the decision is per segment
                voters = voters[np.linspace(0, voters.size - 1, MAX_VOTERS).round().astype(np.int64)]
            # candidates from uncompensated boxes grown by the margin: a selection that assumed a
            # convention would favour it
            from drivetrack.boxes import returns_in_boxes

            box_offsets, index = returns_in_boxes(scene, voters, config.laser_values, config.returns,
                                                  RESIDUAL_MARGIN_M, config.ground_clearance_m, False)
            rows = np.repeat(np.arange(k), np.diff(box_offsets))
            if scene.lidar.capture_offset_s is not None and rows.size:
                from drivetrack.parallel import pool_map       # the two conventions at once, when a pool is installed

                decision["residual_frame_m"], decision["residual_sweep_m"] = pool_map(
                    lambda trajectory: label_time_residual(scene, trajectory, rows, index), [by_frame, by_sweep])
            decision["votes"] = int(voters.size)
            if not decision["residual_sweep_m"] < decision["residual_frame_m"]:
                offsets = np.zeros(k)
                decision["label_time"] = "frame"
    decision["requested"] = label_time
    cache[key] = (offsets, decision)
    return cache[key]


def carry_label_times(source, target, config) -> None:
    """Hand ``source``'s label-time decision (:func:`scene_label_times`) on to ``target``, the same
    segment with refined boxes (row for row): ``target`` then uses the same convention without
    re-deciding, and the same label times, those its refined boxes were registered at."""
    if config.time_model != "trajectory":
        return
    offsets, decision = scene_label_times(source, config)
    target.__dict__["_label_times"] = {"chosen": decision["label_time"], "decision": dict(decision),
                                       "offsets": offsets.copy()}


def segment_trajectory(plan, label_time: str | None = None) -> tuple[BoxTrajectory, dict]:
    """The segment's :class:`BoxTrajectory` under the plan's ``TrackConfig.label_time`` (or
    ``label_time`` when given) and the decision of :func:`scene_label_times`; cached on the plan."""
    import dataclasses

    config = plan.config if label_time is None else dataclasses.replace(plan.config, label_time=label_time)
    cache = plan.__dict__.setdefault("_trajectories", {})
    if config.label_time not in cache:
        offsets, decision = scene_label_times(plan.scene, config)
        cache[config.label_time] = (build_trajectory(plan.scene, offsets, decision["label_time"], config.label_tilt,
                                                     config.synced_boxes), decision)
    return cache[config.label_time]
