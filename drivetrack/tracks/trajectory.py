"""Per-object continuous-time trajectories: where each box was at any time (issue 16).

Every labelled box row k of a scene is a *sample* of its object's pose in the world frame at a
sample time ``time_s[k]`` (seconds since the scene's first frame):

- ``label_time="frame"``: ``lidar_box`` lives at its frame's timestamp (Waymo's ``label.proto``
  convention for ``camera_synced_box``);
- ``label_time="sweep"``: ``lidar_box`` sits where the object was when the TOP sweep passed its
  centre: frame time + :func:`sweep_label_offsets` (from the returns' own capture times,
  ``LidarReturns.capture_offset_s``);
- ``label_time="auto"``: the convention whose boxes, moved to each return's capture time, leave
  fewer return-metres outside the boxes (:func:`label_time_residual`), one choice per segment.

Motion model: between two consecutive samples of an object, a cubic Hermite curve in world
position and world yaw, with tangents from second-order finite differences over the object's
samples (three-point formulas for uneven spacing, one-sided at the ends); exact for constant
acceleration and constant yaw acceleration. Pitch and roll in the world frame (a yaw-only label in
a pitching ego frame, or a refined 6-DOF box) are interpolated linearly. Beyond an object's first
or last sample the end cubic is extrapolated (at most half a frame period in practice). An
object with one sample moves with its ``speed`` column (world velocity in the vehicle frame) when
finite, else stands still. Samples pass through the labels exactly: smoothing would move the
labels themselves, which the pose refinement (issue 8) owns.

Times are float64 seconds relative to ``scene.timestamps_micros[0]``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivetrack.waymo.schema import LaserName

__all__ = ["LABEL_TIMES", "TIME_MODELS", "BoxTrajectory", "build_trajectory", "sweep_label_offsets",
           "label_time_residual", "segment_trajectory", "points_box_at"]

#: ``TrackConfig.label_time`` values.
LABEL_TIMES = ("frame", "sweep", "auto")
#: ``TrackConfig.time_model`` values: ``trajectory`` (this module) or ``velocity`` (the box moved
#: along its finite-difference velocity from the frame time to the image pose time, pre-issue 16).
TIME_MODELS = ("trajectory", "velocity")

#: Returns this far (metres) outside a box still count for :func:`label_time_residual`.
RESIDUAL_MARGIN_M = 0.6
#: Only boxes whose two conventions differ by at least this (metres) vote in ``auto``.
MIN_VOTE_SHIFT_M = 0.02


def _wrap(a):
    return np.angle(np.exp(1j * np.asarray(a, np.float64)))


def _euler_zyx(rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(yaw, pitch, roll) float64 [...] of rotations [..., 3, 3] = Rz(yaw) Ry(pitch) Rx(roll)."""
    yaw = np.arctan2(rotation[..., 1, 0], rotation[..., 0, 0])
    pitch = np.arcsin(np.clip(-rotation[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(rotation[..., 2, 1], rotation[..., 2, 2])
    return yaw, pitch, roll


def _rotation_zyx(yaw, pitch, roll) -> np.ndarray:
    """float64 [..., 3, 3] = Rz(yaw) Ry(pitch) Rx(roll)."""
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    out = np.empty(np.shape(yaw) + (3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    out[..., 1, 0], out[..., 1, 1], out[..., 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    out[..., 2, 0], out[..., 2, 1], out[..., 2, 2] = -sp, cp * sr, cp * cr
    return out


@dataclass
class BoxTrajectory:
    """Continuous-time world poses of every box row's object (K rows of ``scene.boxes``).

    Attributes:
        label_time: the convention in use, ``frame`` or ``sweep``.
        frame_time_s: float64 [K], the row's frame time, s since the scene's first frame.
        time_s: float64 [K], the sample (label) time of the row.
        centre: float64 [K, 3], metres, world box centre at ``time_s``.
        yaw, pitch, roll: float64 [K], radians, world orientation (``Rz Ry Rx``) at ``time_s``.
        velocity: float64 [K, 3], m/s, world velocity of the centre at ``time_s``.
        yaw_rate: float64 [K], rad/s.
        prev, next: int64 [K], the object's previous / next sample row (itself when none).
    """
    label_time: str
    frame_time_s: np.ndarray
    time_s: np.ndarray
    centre: np.ndarray
    yaw: np.ndarray
    pitch: np.ndarray
    roll: np.ndarray
    velocity: np.ndarray
    yaw_rate: np.ndarray
    prev: np.ndarray
    next: np.ndarray

    def motion(self, rows: np.ndarray, time_s: np.ndarray):
        """State of the objects of box rows ``rows`` (int [N]) at ``time_s`` (float [N], s).

        Returns ``(centre [N, 3] m, yaw [N], pitch [N], roll [N] rad, velocity [N, 3] m/s,
        yaw_rate [N] rad/s)``, world frame, on the Hermite segment that holds ``time_s`` (the
        row's segment towards that time; the other one at an object's ends).
        """
        rows = np.asarray(rows, np.int64).reshape(-1)
        t = np.broadcast_to(np.asarray(time_s, np.float64), rows.shape)
        later = t >= self.time_s[rows]
        a = np.where(later, rows, self.prev[rows])
        b = np.where(later, self.next[rows], rows)
        single = a == b                                   # at an end: use the other side's segment
        a = np.where(single & later, self.prev[rows], a)
        b = np.where(single & ~later, self.next[rows], b)
        h = self.time_s[b] - self.time_s[a]
        alone = h <= 0                                    # one-sample object: constant velocity
        h = np.where(alone, 1.0, h)
        s = (t - self.time_s[a]) / h
        s2, s3 = s * s, s * s * s
        h00, h10, h01, h11 = 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2
        d00, d10, d01, d11 = 6 * s2 - 6 * s, 3 * s2 - 4 * s + 1, -6 * s2 + 6 * s, 3 * s2 - 2 * s
        pa, pb, va, vb = self.centre[a], self.centre[b], self.velocity[a], self.velocity[b]
        hh = h[:, None]
        centre = h00[:, None] * pa + (h10 * h)[:, None] * va + h01[:, None] * pb + (h11 * h)[:, None] * vb
        velocity = (d00[:, None] * pa + (d10 * h)[:, None] * va + d01[:, None] * pb + (d11 * h)[:, None] * vb) / hh
        ya = self.yaw[a]
        yb = ya + _wrap(self.yaw[b] - ya)
        wa, wb = self.yaw_rate[a], self.yaw_rate[b]
        yaw = h00 * ya + h10 * h * wa + h01 * yb + h11 * h * wb
        yaw_rate = (d00 * ya + d10 * h * wa + d01 * yb + d11 * h * wb) / h
        sc = np.clip(s, 0.0, 1.0)
        pitch = (1 - sc) * self.pitch[a] + sc * self.pitch[b]
        roll = (1 - sc) * self.roll[a] + sc * self.roll[b]
        if alone.any():
            dt = t[alone] - self.time_s[a[alone]]
            centre[alone] = self.centre[a[alone]] + dt[:, None] * self.velocity[a[alone]]
            velocity[alone] = self.velocity[a[alone]]
            yaw[alone] = self.yaw[a[alone]] + dt * self.yaw_rate[a[alone]]
            yaw_rate[alone] = self.yaw_rate[a[alone]]
            pitch[alone], roll[alone] = self.pitch[a[alone]], self.roll[a[alone]]
        return centre, yaw, pitch, roll, velocity, yaw_rate

    def world_from_box(self, rows: np.ndarray, time_s: np.ndarray) -> np.ndarray:
        """float64 [N, 4, 4]: the objects of box rows ``rows`` (int [N]) at ``time_s`` (float [N], s)."""
        centre, yaw, pitch, roll, _, _ = self.motion(rows, time_s)
        out = np.zeros(centre.shape[:1] + (4, 4))
        out[:, :3, :3] = _rotation_zyx(yaw, pitch, roll)
        out[:, :3, 3] = centre
        out[:, 3, 3] = 1.0
        return out


def _neighbours(keys: np.ndarray, time_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """prev / next rows of the same key in time (int64 [K]; the row itself when none)."""
    k = time_s.shape[0]
    order = np.lexsort((time_s, keys))
    same_prev = np.zeros(k, dtype=bool)
    same_prev[1:] = keys[order][1:] == keys[order][:-1]
    same_next = np.zeros(k, dtype=bool)
    same_next[:-1] = same_prev[1:]
    position = np.arange(k)
    prev = np.empty(k, np.int64)
    nxt = np.empty(k, np.int64)
    prev[order] = order[np.where(same_prev, position - 1, position)]
    nxt[order] = order[np.where(same_next, position + 1, position)]
    return prev, nxt


def _derivative(values: np.ndarray, time_s: np.ndarray, prev: np.ndarray, nxt: np.ndarray) -> np.ndarray:
    """Second-order finite-difference d values / dt (float64 [K, D]) along each object's samples.

    Three-point formulas for uneven spacing: central inside, one-sided at the ends (exact for
    quadratics); two samples give their slope, one sample 0. ``values`` are already unwrapped
    against their neighbours by the caller where angles are concerned (see :func:`build_trajectory`).
    """
    k = time_s.shape[0]
    out = np.zeros_like(values)
    has_prev, has_next = prev != np.arange(k), nxt != np.arange(k)
    inner = has_prev & has_next
    # interior: t_-1, t_0, t_1
    i = np.flatnonzero(inner)
    h1 = (time_s[i] - time_s[prev[i]])[:, None]
    h2 = (time_s[nxt[i]] - time_s[i])[:, None]
    out[i] = (-h2 / (h1 * (h1 + h2)) * values[prev[i]] + (h2 - h1) / (h1 * h2) * values[i]
              + h1 / (h2 * (h1 + h2)) * values[nxt[i]])
    # start: t_0, t_1, t_2 (t_2 = next of next, when it exists)
    for end, near in ((has_next & ~has_prev, nxt), (has_prev & ~has_next, prev)):
        j = np.flatnonzero(end)
        if j.size == 0:
            continue
        n1 = near[j]
        n2 = near[n1]
        three = n2 != n1
        h1 = (time_s[n1] - time_s[j])[:, None]
        slope = (values[n1] - values[j]) / h1
        out[j] = slope
        if three.any():
            jj, m1, m2 = j[three], n1[three], n2[three]
            a = (time_s[m1] - time_s[jj])[:, None]           # signed (negative towards the past)
            b = (time_s[m2] - time_s[jj])[:, None]
            # f'(0) from f(0), f(a), f(b): exact for quadratics
            out[jj] = (-(a + b) / (a * b) * values[jj] + b / (a * (b - a)) * values[m1]
                       - a / (b * (b - a)) * values[m2])
    return out


def build_trajectory(scene, label_offset_s: np.ndarray, label_time: str = "frame") -> BoxTrajectory:
    """The :class:`BoxTrajectory` of every box row of ``scene``, sampled at frame time + ``label_offset_s``.

    Args:
        scene: a :class:`drivetrack.scene.Scene`.
        label_offset_s: float64 [K], seconds, each row's label time minus its frame time.
        label_time: the name of the convention (recorded only).
    """
    boxes = scene.boxes
    k = len(boxes)
    frame_time = (np.asarray(scene.timestamps_micros, np.int64)[boxes.frame]
                  - int(scene.timestamps_micros[0])) * 1e-6 if k else np.zeros(0)
    time_s = frame_time + np.asarray(label_offset_s, np.float64).reshape(k)
    world_from_vehicle = np.asarray(scene.world_from_vehicle, np.float64)[boxes.frame]
    world_from_box = world_from_vehicle @ boxes.vehicle_from_box() if k else np.zeros((0, 4, 4))
    yaw, pitch, roll = _euler_zyx(world_from_box[:, :3, :3])
    keys = np.unique(boxes.object_id.astype(str), return_inverse=True)[1] if k else np.zeros(0, np.int64)
    prev, nxt = _neighbours(keys, time_s)
    centre = world_from_box[:, :3, 3].copy()
    # neighbours' yaw unwrapped near each row's own
    unwrapped_prev = yaw + _wrap(yaw[prev] - yaw)
    unwrapped_next = yaw + _wrap(yaw[nxt] - yaw)
    # derivative of yaw with neighbours' angles expressed near this row's
    yaw_rate = _angle_derivative(yaw, unwrapped_prev, unwrapped_next, time_s, prev, nxt)
    velocity = _derivative(centre, time_s, prev, nxt)
    alone = (prev == np.arange(k)) & (nxt == np.arange(k))
    if alone.any():
        speed = np.asarray(boxes.speed, np.float64)[alone]
        ok = np.isfinite(speed).all(axis=1)
        v_world = np.einsum("nij,nj->ni", world_from_vehicle[alone, :3, :3], np.where(ok[:, None], speed, 0.0))
        velocity[alone] = v_world
    return BoxTrajectory(label_time, frame_time, time_s, centre, yaw, pitch, roll, velocity, yaw_rate, prev, nxt)


def _angle_derivative(yaw, yaw_prev, yaw_next, time_s, prev, nxt) -> np.ndarray:
    """d yaw / dt [K] with :func:`_derivative`'s formulas on angles unwrapped locally."""
    k = yaw.shape[0]
    # Build a [K, 3] local table (prev, self, next) and reuse the scalar formulas.
    out = np.zeros(k)
    has_prev, has_next = prev != np.arange(k), nxt != np.arange(k)
    i = np.flatnonzero(has_prev & has_next)
    h1 = time_s[i] - time_s[prev[i]]
    h2 = time_s[nxt[i]] - time_s[i]
    out[i] = (-h2 / (h1 * (h1 + h2)) * yaw_prev[i] + (h2 - h1) / (h1 * h2) * yaw[i]
              + h1 / (h2 * (h1 + h2)) * yaw_next[i])
    for end, near, near_yaw in ((has_next & ~has_prev, nxt, yaw_next), (has_prev & ~has_next, prev, yaw_prev)):
        j = np.flatnonzero(end)
        if j.size == 0:
            continue
        n1 = near[j]
        n2 = near[n1]
        y1 = near_yaw[j]
        a = time_s[n1] - time_s[j]
        out[j] = (y1 - yaw[j]) / a
        three = n2 != n1
        if three.any():
            jj, m1, m2 = j[three], n1[three], n2[three]
            y1 = y1[three]
            y2 = y1 + _wrap(yaw[m2] - y1)
            a = time_s[m1] - time_s[jj]
            b = time_s[m2] - time_s[jj]
            out[jj] = -(a + b) / (a * b) * yaw[jj] + b / (a * (b - a)) * y1 - a / (b * (b - a)) * y2
    return out


def sweep_label_offsets(scene, box_point_offsets: np.ndarray, box_point_index: np.ndarray) -> np.ndarray:
    """float64 [K], seconds: when the TOP sweep passed each box's centre, minus its frame time.

    From the capture times of the box's own TOP returns (``box_point_*``: CSR over box rows, as
    :class:`drivetrack.tracks.plan.SegmentPlan` holds them): ``median(dt_i + b (az_c - az_i))``
    with ``az`` the azimuth about the vehicle origin and ``b`` the sweep's seconds per radian,
    fitted over all TOP returns of the scene. A box without TOP returns gets ``a + b az_c`` from
    that fit; a scene without capture times gets 0 everywhere.
    """
    boxes, lidar = scene.boxes, scene.lidar
    k = len(boxes)
    out = np.zeros(k)
    offsets = getattr(lidar, "capture_offset_s", None)
    if offsets is None or k == 0:
        return out
    top = np.flatnonzero((lidar.laser == int(LaserName.TOP)) & (offsets != 0))
    if top.size < 10:
        return out
    top = top[:: max(1, top.size // 200_000)]
    az = np.arctan2(lidar.points_vehicle[top, 1], lidar.points_vehicle[top, 0])
    fit = np.abs(az) < 2.8
    design = np.stack([np.ones(int(fit.sum())), az[fit]], -1)
    (a, b), *_ = np.linalg.lstsq(design, offsets[top][fit].astype(np.float64), rcond=None)
    az_c = np.arctan2(boxes.center[:, 1], boxes.center[:, 0])
    out[:] = a + b * az_c
    counts = np.diff(box_point_offsets)
    owner = np.repeat(np.arange(k), counts)
    index = np.asarray(box_point_index, np.int64)
    is_top = lidar.laser[index] == int(LaserName.TOP)
    owner, index = owner[is_top], index[is_top]
    if index.size:
        az_i = np.arctan2(lidar.points_vehicle[index, 1], lidar.points_vehicle[index, 0])
        estimate = offsets[index].astype(np.float64) + b * _wrap(az_c[owner] - az_i)
        order = np.lexsort((estimate, owner))
        estimate, owner = estimate[order], owner[order]
        first = np.searchsorted(owner, np.arange(k), side="left")
        last = np.searchsorted(owner, np.arange(k), side="right")
        has = last > first
        lo = estimate[np.clip((first + last - 1) // 2, 0, max(estimate.size - 1, 0))]
        hi = estimate[np.clip((first + last) // 2, 0, max(estimate.size - 1, 0))]
        out[has] = 0.5 * (lo[has] + hi[has])
    return out


def points_box_at(trajectory: BoxTrajectory, rows: np.ndarray, time_s: np.ndarray,
                  points_world: np.ndarray) -> np.ndarray:
    """float64 [N, 3]: world points float [N, 3] in the frame of box row ``rows`` (int [N])'s
    object at ``time_s`` (float [N], s): the body point of a return captured then."""
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


def segment_trajectory(plan, label_time: str) -> tuple[BoxTrajectory, dict]:
    """The segment's trajectory under ``label_time`` (``frame`` / ``sweep`` / ``auto``), cached on the plan.

    Returns ``(trajectory, decision)``; ``decision`` holds ``label_time`` (the convention used),
    ``requested``, ``residual_frame_m`` and ``residual_sweep_m`` (:func:`label_time_residual` over
    the returns of boxes whose conventions differ by >= :data:`MIN_VOTE_SHIFT_M`; NaN when not
    computed or no box votes) and ``votes`` (boxes that voted).
    """
    cache = plan.__dict__.setdefault("_trajectories", {})
    if label_time in cache:
        return cache[label_time]
    if label_time not in LABEL_TIMES:
        raise ValueError(f"segment {plan.scene.segment!r}: TrackConfig.label_time must be one of {LABEL_TIMES}, "
                         f"got {label_time!r}")
    scene = plan.scene
    k = len(scene.boxes)
    decision = {"requested": label_time, "residual_frame_m": float("nan"), "residual_sweep_m": float("nan"),
                "votes": 0}
    if label_time == "frame":
        trajectory = build_trajectory(scene, np.zeros(k), "frame")
    else:
        sweep = sweep_label_offsets(scene, plan.box_point_offsets, plan.box_point_index)
        by_sweep = build_trajectory(scene, sweep, "sweep")
        if label_time == "sweep":
            trajectory = by_sweep
        else:
            by_frame = build_trajectory(scene, np.zeros(k), "frame")
            shift = np.linalg.norm(by_frame.velocity, axis=-1) * np.abs(sweep)
            voters = np.flatnonzero(shift >= MIN_VOTE_SHIFT_M)
            # candidates from uncompensated boxes grown by the margin: the plan's own selection
            # already assumed a convention (frame) and would favour it
            from drivetrack.boxes import returns_in_boxes

            config = plan.config
            offsets, index = returns_in_boxes(scene, voters, config.laser_values, config.returns,
                                              RESIDUAL_MARGIN_M, config.ground_clearance_m, False)
            rows = np.repeat(np.arange(k), np.diff(offsets))
            lidar_rows = index
            if scene.lidar.capture_offset_s is not None and rows.size:
                decision["residual_frame_m"] = label_time_residual(scene, by_frame, rows, lidar_rows)
                decision["residual_sweep_m"] = label_time_residual(scene, by_sweep, rows, lidar_rows)
            decision["votes"] = int(voters.size)
            sweep_better = decision["residual_sweep_m"] < decision["residual_frame_m"]
            trajectory = by_sweep if sweep_better else by_frame
    decision["label_time"] = trajectory.label_time
    cache[label_time] = (trajectory, decision)
    return cache[label_time]
