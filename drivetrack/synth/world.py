"""The procedural world: ego trajectory and objects with closed-form motion.

Everything is a closed-form function of time (seconds since frame 0), so any sensor can ask for
the exact pose at its own capture time (lidar columns, camera rows) and velocities are exact
derivatives. The world frame has z up and the ground is the plane z = 0; traffic drives along
world +x (lanes at ``y = LANES``), oncoming traffic along -x.

Motion model shared by the ego and every object ("weave"): in a local frame rotated by the
initial heading ``h0`` about z and placed at ``p0``, ``local x = s t`` and
``local y = a (1 - cos(w t))``; the heading is ``h0 + atan2(a w sin(w t), s)``. Parked objects have
``s = a = 0``. The ego adds a small pitch and roll oscillation (about its origin on the ground).

Turning objects ("arc", ``turn`` != 0, ``a = 0``): a circle at speed ``s`` and constant yaw rate
``turn`` (rad/s): ``local x = s sin(turn t) / turn``, ``local y = s (1 - cos(turn t)) / turn``,
heading ``h0 + turn t``.

Speed changes ("surge", ``SynthConfig.speed_changes_mps2``; off by default): a weaving mover may
also brake and speed up along its path, with the acceleration ``g cos(W t + phi)`` (m/s^2) added
to its local x: ``local x = s t - g / W^2 (cos(W t + phi) - cos(phi)) - g / W sin(phi) t``, so its
speed is ``s + g / W (sin(W t + phi) - sin(phi))`` and its jerk up to ``g W``; the heading follows
the velocity. Real traffic brakes and accelerates; a world of constant speeds flatters any motion
model that assumes them.
"""
from __future__ import annotations

import dataclasses
import string
from dataclasses import dataclass

import numpy as np

from drivetrack.geometry import rigid_from_rotation_translation, rotation_from_rpy
from drivetrack.waymo.schema import BoxType

__all__ = ["Motion", "SynthObject", "World", "make_world", "with_car_shape", "with_pedestrian_shape", "world_overlaps", "LANE_WIDTH", "WORLDS",
           "CAR_SHAPES", "EGO_BOX", "CLEARANCE_M"]

#: ``SynthConfig.world`` values: the default scene, and the one adding the cases of issues 15/16.
WORLDS = ("default", "hard")

#: ``SynthConfig.car_shape`` values: "box" (every object is its label box), "cabin" (a vehicle is
#: a lower body and a narrower, shorter cabin on it; the label box is their tight bounding box) or
#: "rounded" (the cabin car with the body's four corners rounded in plan view, :func:`rounded_parts`:
#: its side's returns end where the corner turns away, which depends on where it is seen from).
CAR_SHAPES = ("box", "cabin", "rounded")

#: "rounded" corners: plan-view radius as a fraction of the width, and the boxes (steps) per corner
_CORNER_RADIUS, _CORNER_STEPS = 0.2, 5

#: The cabin shape as fractions of the label box (length L, width W, height H): the body is the
#: whole length and width and the lower ``_BODY_HEIGHT`` of H; the cabin, the rest of the height,
#: is ``_CABIN_LENGTH`` of L long, centred ``_CABIN_SHIFT`` of L behind the box centre, and
#: ``_CABIN_WIDTH`` of W wide (a saloon's glasshouse; bonnet ahead of it, boot behind).
_BODY_HEIGHT, _CABIN_LENGTH, _CABIN_SHIFT, _CABIN_WIDTH = 0.55, 0.5, 0.06, 0.86

#: ``SynthConfig.pedestrian_shape`` values: "box" (every pedestrian is its label box) or "body" (two
#: legs mid-stride, a torso, two arms swinging the other way and a head; the label box is their
#: tight bounding box: :func:`body_parts`).
PEDESTRIAN_SHAPES = ("box", "body")

LANE_WIDTH = 3.5
#: lane centres (world y, metres): ego direction at negative y, oncoming at positive y.
EGO_LANES = (-1.75, -5.25, -8.75)
ONCOMING_LANES = (1.75, 5.25)
CURB_Y = -13.0          # right edge of the road (a 2.5 m parking strip beyond the lanes); sidewalk beyond
FAR_CURB_Y = 7.0        # left edge of the road (oncoming side)
PARKED_Y = CURB_Y + 1.1  # centre line of the cars parked along the right curb

#: The ego's body as ``(centre x, length, width, height)`` metres in the vehicle frame (origin on
#: the ground below the rear axle): it spans the short-range lidars, REAR at x = -1.15 to FRONT at
#: 4.07, SIDE_LEFT / SIDE_RIGHT at y = +-1.02.
EGO_BOX = (1.45, 5.3, 2.1, 1.8)
#: Metres kept between any two bodies (the ego's and every label box) over the whole clip; objects
#: that would come closer are moved (:func:`make_world`).
CLEARANCE_M = 0.1
#: Seconds between the instants at which bodies are checked for overlap: the fastest object
#: (13.5 m/s) moves 0.27 m between checks, less than the thinnest body with its clearance (a
#: 0.3 m pole), and two movers closing at 25 m/s 0.5 m, less than the thinnest mover (a 0.6 m
#: pedestrian), so nothing passes through anything between two checks.
_CHECK_STEP_S = 0.02
#: The displacements (metres) tried, in this order, to move a new object clear of the bodies
#: already placed: along its direction of travel (a mover) or along the road (a static object).
_SHIFTS_M = tuple(float(d) for k in range(1, 61) for d in (k, -k))


@dataclass(frozen=True)
class Motion:
    """Closed-form planar motion (see module docstring). Units: metres, radians, seconds."""
    p0: tuple[float, float]
    h0: float
    s: float = 0.0
    a: float = 0.0
    w: float = 0.0
    turn: float = 0.0
    surge: float = 0.0
    surge_w: float = 0.0
    surge_phase: float = 0.0

    def __post_init__(self):
        if self.turn != 0.0 and self.a != 0.0:
            raise ValueError(f"Motion: a turning motion (turn={self.turn}) cannot also weave (a={self.a})")
        if self.surge != 0.0 and (self.turn != 0.0 or not self.s > 0.0 or not self.surge_w > 0.0):
            raise ValueError(f"Motion: a speed change (surge={self.surge}) needs a weaving mover with s > 0 and "
                             f"surge_w > 0, got s={self.s}, turn={self.turn}, surge_w={self.surge_w}")

    def _local(self, t):
        """(x, y, vx, vy, ax, ay) in the local frame, float64 [...] each."""
        if self.turn != 0.0:
            wt = self.turn * t
            r = self.s / self.turn
            return (r * np.sin(wt), r * (1.0 - np.cos(wt)), self.s * np.cos(wt), self.s * np.sin(wt),
                    -self.s * self.turn * np.sin(wt), self.s * self.turn * np.cos(wt))
        x, vx, ax = self.s * t, np.full_like(t, self.s), np.zeros_like(t)
        if self.surge != 0.0:
            g, ww, phi = self.surge, self.surge_w, self.surge_phase
            x = x - g / ww**2 * (np.cos(ww * t + phi) - np.cos(phi)) - g / ww * np.sin(phi) * t
            vx = vx + g / ww * (np.sin(ww * t + phi) - np.sin(phi))
            ax = g * np.cos(ww * t + phi)
        return (x, self.a * (1.0 - np.cos(self.w * t)), vx,
                self.a * self.w * np.sin(self.w * t), ax,
                self.a * self.w * self.w * np.cos(self.w * t))

    def _world(self, lx, ly):
        c, s = np.cos(self.h0), np.sin(self.h0)
        return np.stack([c * lx - s * ly, s * lx + c * ly], axis=-1)

    def position_xy(self, t: np.ndarray) -> np.ndarray:
        """float64 [..., 2] world (x, y) at times ``t`` float [...], seconds."""
        t = np.asarray(t, dtype=np.float64)
        lx, ly = self._local(t)[:2]
        c, s = np.cos(self.h0), np.sin(self.h0)
        return np.stack([self.p0[0] + c * lx - s * ly, self.p0[1] + s * lx + c * ly], axis=-1)

    def velocity_xy(self, t: np.ndarray) -> np.ndarray:
        """float64 [..., 2] world-frame velocity (m/s)."""
        return self._world(*self._local(np.asarray(t, dtype=np.float64))[2:4])

    def acceleration_xy(self, t: np.ndarray) -> np.ndarray:
        """float64 [..., 2] world-frame acceleration (m/s^2)."""
        return self._world(*self._local(np.asarray(t, dtype=np.float64))[4:])

    def heading(self, t: np.ndarray) -> np.ndarray:
        """float64 [...] yaw about world z (radians)."""
        t = np.asarray(t, dtype=np.float64)
        if self.turn != 0.0:
            return self.h0 + self.turn * t
        if self.s == 0.0 and self.a == 0.0:
            return np.full_like(t, self.h0)
        _, _, vx, vy, _, _ = self._local(t)
        return self.h0 + np.arctan2(vy, vx)

    def yaw_rate(self, t: np.ndarray) -> np.ndarray:
        """float64 [...] d heading / dt (rad/s)."""
        t = np.asarray(t, dtype=np.float64)
        if self.turn != 0.0:
            return np.full_like(t, self.turn)
        if self.s == 0.0:
            return np.zeros_like(t)
        _, _, vx, vy, ax, ay = self._local(t)
        return (vx * ay - vy * ax) / (vx * vx + vy * vy)

    def yaw_acceleration(self, t: np.ndarray) -> np.ndarray:
        """float64 [...] d^2 heading / dt^2 (rad/s^2): a central difference of :meth:`yaw_rate`
        over 1e-4 s (the weave's is smooth: error ~1e-9 rad/s^2); 0 on an arc."""
        t = np.asarray(t, dtype=np.float64)
        if self.turn != 0.0 or self.s == 0.0:
            return np.zeros_like(t)
        h = 1e-4
        return (self.yaw_rate(t + h) - self.yaw_rate(t - h)) / (2.0 * h)


@dataclass(frozen=True)
class SynthObject:
    """One labelled object: an oriented box moving with ``motion``.

    ``size`` (length along heading, width, height) in metres; the box sits on the ground unless
    ``z_center`` says otherwise. ``color`` float RGB in [0, 1], ``pattern`` 0 = checker,
    1 = stripes, ``texture_scale`` metres per texture cell, ``seed`` for its noise. ``parts``: the
    solid as axis-aligned boxes in the box frame, ``((offset xyz, half size xyz), ...)`` metres,
    all inside the label box; empty: the label box itself (:attr:`solids`).

    ``axle_offset_m``: 0 (default) the box centre follows ``motion``'s path and the heading is its
    tangent, so the centre never slips sideways. > 0: the point that far behind the centre on the
    box's long axis (a rear axle) follows the path, shifted by a constant vector so that the centre
    is where the path puts it while the heading is that of ``motion.h0``: the centre is
    ``path + axle_offset_m (f(heading) - f(h0))`` (``f`` the unit forward vector) and the axle
    point moves along its heading, as a car's rear axle does, while the centre gains the lateral
    velocity ``yaw_rate x axle_offset_m`` on a turn (real cars; a model that assumes no slip at the
    centre is wrong by that much).
    """
    object_id: str
    type: int
    size: tuple[float, float, float]
    z_center: float
    motion: Motion
    color: tuple[float, float, float]
    pattern: int
    texture_scale: float
    seed: int
    role: str
    parts: tuple = ()
    axle_offset_m: float = 0.0

    @property
    def solids(self) -> tuple:
        """``((offset float64 [3], half size float64 [3]), ...)``: the boxes (in the box frame) whose
        union is the object's surface."""
        if self.parts:
            return tuple((np.asarray(o, np.float64), np.asarray(h, np.float64)) for o, h in self.parts)
        return ((np.zeros(3), np.asarray(self.size, np.float64) / 2.0),)

    def _axle_terms(self, t: np.ndarray):
        """(forward [..., 2], left [..., 2], yaw rate [...]) of the heading at ``t``."""
        heading = self.motion.heading(t)
        forward = np.stack([np.cos(heading), np.sin(heading)], axis=-1)
        left = np.stack([-np.sin(heading), np.cos(heading)], axis=-1)
        return forward, left, self.motion.yaw_rate(t)

    def center(self, t: np.ndarray) -> np.ndarray:
        """float64 [..., 3] box centre in the world at times ``t``."""
        xy = self.motion.position_xy(t)
        if self.axle_offset_m:          # (the heading alone: the lidar cast asks this per column)
            heading = self.motion.heading(np.asarray(t, dtype=np.float64))
            forward = np.stack([np.cos(heading), np.sin(heading)], axis=-1)
            xy = xy + self.axle_offset_m * (forward - np.array([np.cos(self.motion.h0), np.sin(self.motion.h0)]))
        return np.concatenate([xy, np.full(xy.shape[:-1] + (1,), self.z_center)], axis=-1)

    def heading(self, t: np.ndarray) -> np.ndarray:
        return self.motion.heading(t)

    def velocity(self, t: np.ndarray) -> np.ndarray:
        """float64 [..., 3] world-frame velocity of the box centre, m/s."""
        v = self.motion.velocity_xy(t)
        if self.axle_offset_m:
            _, left, rate = self._axle_terms(np.asarray(t, dtype=np.float64))
            v = v + self.axle_offset_m * rate[..., None] * left
        return np.concatenate([v, np.zeros(v.shape[:-1] + (1,))], axis=-1)

    def acceleration(self, t: np.ndarray) -> np.ndarray:
        a = self.motion.acceleration_xy(t)
        if self.axle_offset_m:
            t = np.asarray(t, dtype=np.float64)
            forward, left, rate = self._axle_terms(t)
            a = a + self.axle_offset_m * (self.motion.yaw_acceleration(t)[..., None] * left
                                          - (rate * rate)[..., None] * forward)
        return np.concatenate([a, np.zeros(a.shape[:-1] + (1,))], axis=-1)

    def world_from_box(self, t: np.ndarray) -> np.ndarray:
        """float64 [..., 4, 4]."""
        from drivetrack.geometry import rotation_z
        return rigid_from_rotation_translation(rotation_z(self.heading(t)), self.center(t))


@dataclass(frozen=True)
class World:
    """Ego motion (with pitch/roll oscillation) and the objects of one segment."""
    ego: Motion
    pitch_amplitude: float
    roll_amplitude: float
    objects: tuple[SynthObject, ...]
    ground_seed: int

    def _rp(self, t):
        t = np.asarray(t, dtype=np.float64)
        pitch = self.pitch_amplitude * np.sin(2 * np.pi * t / 3.1)
        roll = self.roll_amplitude * np.sin(2 * np.pi * t / 2.3 + 1.0)
        dpitch = self.pitch_amplitude * 2 * np.pi / 3.1 * np.cos(2 * np.pi * t / 3.1)
        droll = self.roll_amplitude * 2 * np.pi / 2.3 * np.cos(2 * np.pi * t / 2.3 + 1.0)
        return pitch, roll, dpitch, droll

    def ego_rpy_xyz(self, t: np.ndarray) -> np.ndarray:
        """float64 [..., 6] ego pose [roll, pitch, yaw, x, y, z] (Waymo ``lidar_pose`` layout)."""
        t = np.asarray(t, dtype=np.float64)
        pitch, roll, _, _ = self._rp(t)
        xy = self.ego.position_xy(t)
        return np.stack([roll, pitch, self.ego.heading(t), xy[..., 0], xy[..., 1],
                         np.zeros_like(t)], axis=-1)

    def world_from_vehicle(self, t: np.ndarray) -> np.ndarray:
        """float64 [..., 4, 4] ego pose at times ``t`` (seconds since frame 0)."""
        p = self.ego_rpy_xyz(t)
        return rigid_from_rotation_translation(rotation_from_rpy(p[..., 0], p[..., 1], p[..., 2]),
                                               p[..., 3:])

    def ego_velocity(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(linear [..., 3] m/s, angular [..., 3] rad/s), both in the world frame.

        Angular velocity is the exact world-frame rate of ``Rz(yaw) Ry(pitch) Rx(roll)``:
        ``w = yaw' z + pitch' Rz(yaw) y + roll' Rz(yaw) Ry(pitch) x``.
        """
        t = np.asarray(t, dtype=np.float64)
        v = self.ego.velocity_xy(t)
        linear = np.concatenate([v, np.zeros(v.shape[:-1] + (1,))], axis=-1)
        pitch, roll, dpitch, droll = self._rp(t)
        yaw, dyaw = self.ego.heading(t), self.ego.yaw_rate(t)
        cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
        y_axis = np.stack([-sy, cy, np.zeros_like(t)], -1)
        x_axis = np.stack([cy * cp, sy * cp, -sp], -1)
        angular = (dyaw[..., None] * np.array([0.0, 0.0, 1.0]) + dpitch[..., None] * y_axis
                   + droll[..., None] * x_axis)
        return linear, angular


def _object_id(rng: np.random.Generator) -> str:
    alphabet = np.array(list(string.ascii_letters + string.digits + "-_"))
    return "".join(rng.choice(alphabet, size=22))


def cabin_parts(size) -> tuple:
    """``parts`` (:class:`SynthObject`) of a vehicle of label ``size`` (L, W, H) shaped as a body and
    a cabin (:data:`CAR_SHAPES`); the label box is their tight bounding box."""
    length, width, height = (float(s) for s in size)
    body, cabin = _BODY_HEIGHT * height, (1.0 - _BODY_HEIGHT) * height
    return (((0.0, 0.0, -height / 2 + body / 2), (length / 2, width / 2, body / 2)),
            ((-_CABIN_SHIFT * length, 0.0, height / 2 - cabin / 2),
             (_CABIN_LENGTH * length / 2, _CABIN_WIDTH * width / 2, cabin / 2)))


def rounded_parts(size) -> tuple:
    """``parts`` of a vehicle of label ``size`` shaped as :func:`cabin_parts` with the body's four
    corners rounded in plan view (radius ``_CORNER_RADIUS`` x W, 0.38 m on a 1.9 m wide car, a
    bumper's), as ``_CORNER_STEPS`` full-height boxes whose corners lie on the rounding circle;
    the label box is still their tight bounding box."""
    length, width, height = (float(s) for s in size)
    (body_centre, body_half), cabin = cabin_parts(size)
    radius = _CORNER_RADIUS * width
    angle = np.linspace(0.0, np.pi / 2, _CORNER_STEPS)
    steps = tuple((body_centre, (length / 2 - radius + radius * float(np.sin(a)),
                                 width / 2 - radius + radius * float(np.cos(a)), body_half[2])) for a in angle)
    return steps + (cabin,)


def body_parts(size) -> tuple:
    """``parts`` (:class:`SynthObject`) of a pedestrian of label ``size`` (L along its heading, W
    across, H) shaped as a walking body (:data:`PEDESTRIAN_SHAPES`), as (centre, half size) boxes
    in its box frame from (low, high) corners given as fractions of (L, W, H) from the box's
    centre: the right leg forward, the left back (the lower 46% of H), a torso, the left arm
    forward and the right back (a gap of 4% of W beside the torso), a head; the label box is their
    tight bounding box. Unlike a box it hides parts of itself from cameras its faces turn to: the
    near leg the far one, the torso an arm."""
    length, width, height = (float(s) for s in size)
    extents = (((0.05, -0.28, -0.5), (0.5, -0.02, -0.04)),         # right leg, forward
               ((-0.5, 0.02, -0.5), (-0.05, 0.28, -0.04)),         # left leg, back
               ((-0.15, -0.3, -0.04), (0.15, 0.3, 0.33)),          # torso
               ((0.0, 0.34, 0.0), (0.35, 0.5, 0.32)),              # left arm, forward
               ((-0.35, -0.5, 0.0), (0.0, -0.34, 0.32)),           # right arm, back
               ((-0.12, -0.13, 0.36), (0.12, 0.13, 0.5)))          # head
    scale = np.array([length, width, height])
    return tuple(((tuple((np.add(lo, hi) / 2 * scale).tolist())), tuple((np.subtract(hi, lo) / 2 * scale).tolist()))
                 for lo, hi in extents)


def with_pedestrian_shape(world: World, pedestrian_shape: str) -> World:
    """``world`` with every pedestrian given ``pedestrian_shape`` (:data:`PEDESTRIAN_SHAPES`);
    nothing else changes (the labels are the same), as :func:`with_car_shape` for vehicles."""
    return _with_shape(world, pedestrian_shape, PEDESTRIAN_SHAPES, BoxType.PEDESTRIAN, body_parts, "pedestrian")


def with_car_shape(world: World, car_shape: str) -> World:
    """``world`` with every vehicle given ``car_shape`` (:data:`CAR_SHAPES`); nothing else changes
    (the same objects, motions, colours and labels), so a segment differs from the box world's only
    where a vehicle's shape does."""
    return _with_shape(world, car_shape, CAR_SHAPES, BoxType.VEHICLE,
                       rounded_parts if car_shape == "rounded" else cabin_parts, "car")


def _with_shape(world: World, shape: str, shapes: tuple, box_type, parts, what: str) -> World:
    """``world`` with every object of ``box_type`` made of ``parts(size)`` unless ``shape`` is
    "box" (one of ``shapes``)."""
    if shape not in shapes:
        raise ValueError(f"unknown {what} shape {shape!r}; choose from {', '.join(shapes)}")
    if shape == "box":
        return world
    objects = tuple(dataclasses.replace(o, parts=parts(o.size)) if o.type == int(box_type) else o
                    for o in world.objects)
    return dataclasses.replace(world, objects=objects)


def _footprints(xy: np.ndarray, heading: np.ndarray, length: float, width: float) -> np.ndarray:
    """float64 [T, 4, 2]: the corners (world x, y) of a ``length`` x ``width`` rectangle centred at
    ``xy`` float64 [T, 2] and turned by ``heading`` float64 [T] radians."""
    dx = np.array([1.0, 1.0, -1.0, -1.0]) * length / 2
    dy = np.array([1.0, -1.0, -1.0, 1.0]) * width / 2
    c, s = np.cos(heading)[:, None], np.sin(heading)[:, None]
    return np.stack([xy[:, None, 0] + c * dx - s * dy, xy[:, None, 1] + s * dx + c * dy], axis=-1)


def _overlapping(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """bool [T]: whether the convex quadrilaterals ``a`` and ``b`` float64 [T, 4, 2] overlap at each
    instant (no edge normal of either separates them)."""
    separated = np.zeros(a.shape[0], dtype=bool)
    for poly in (a, b):
        edge = np.roll(poly, -1, axis=1) - poly
        normal = np.stack([-edge[..., 1], edge[..., 0]], axis=-1)            # [T, 4, 2]
        pa, pb = np.einsum("tkd,tnd->tkn", normal, a), np.einsum("tkd,tnd->tkn", normal, b)
        separated |= np.any((pa.max(-1) < pb.min(-1)) | (pb.max(-1) < pa.min(-1)), axis=-1)
    return ~separated


@dataclass(frozen=True)
class _Body:
    """One body's footprints (inflated by half :data:`CLEARANCE_M` each side) at the check times,
    and its height interval (metres)."""
    role: str
    corners: np.ndarray          # float64 [T, 4, 2]
    z: tuple[float, float]

    def clash(self, other: "_Body") -> np.ndarray:
        """bool [T]: the instants at which the two bodies come closer than the clearance."""
        if self.z[0] >= other.z[1] or other.z[0] >= self.z[1]:
            return np.zeros(self.corners.shape[0], dtype=bool)
        return _overlapping(self.corners, other.corners)


def _ego_body(ego: Motion, times: np.ndarray) -> _Body:
    x, length, width, height = EGO_BOX
    heading = ego.heading(times)
    xy = ego.position_xy(times) + x * np.stack([np.cos(heading), np.sin(heading)], axis=-1)
    return _Body("ego", _footprints(xy, heading, length + CLEARANCE_M, width + CLEARANCE_M), (0.0, height))


def _object_body(o: SynthObject, times: np.ndarray) -> _Body:
    length, width, height = o.size
    return _Body(o.role, _footprints(o.center(times)[..., :2], o.motion.heading(times), length + CLEARANCE_M,
                                     width + CLEARANCE_M), (o.z_center - height / 2, o.z_center + height / 2))


def _check_times(duration: float) -> np.ndarray:
    """float64 [T] seconds: the clip (frame 0 to ``duration``) and half a sweep either side."""
    from drivetrack.synth.config import SWEEP_S
    return np.arange(-SWEEP_S / 2, duration + SWEEP_S / 2 + _CHECK_STEP_S, _CHECK_STEP_S)


def _shifted(o: SynthObject, d: float) -> SynthObject:
    """``o`` moved ``d`` metres along its direction of travel (a mover: it passes every place
    ``d / s`` seconds earlier) or along the road (world x, a static object)."""
    m = o.motion
    if m.s != 0.0:
        p0 = (m.p0[0] + d * np.cos(m.h0), m.p0[1] + d * np.sin(m.h0))
    else:
        p0 = (m.p0[0] + d, m.p0[1])
    return dataclasses.replace(o, motion=dataclasses.replace(m, p0=(float(p0[0]), float(p0[1]))))


def _place(o: SynthObject, bodies: list[_Body], times: np.ndarray) -> SynthObject | None:
    """``o``, or the first of its :data:`_SHIFTS_M` displacements that keeps it clear of ``bodies``
    (the ego's and those of the objects placed before it) at every check time; None when none
    does (the world is then generated without it)."""
    for d in (0.0,) + _SHIFTS_M:
        candidate = o if d == 0.0 else _shifted(o, d)
        body = _object_body(candidate, times)
        if not any(body.clash(b).any() for b in bodies):
            return candidate
    return None


def world_overlaps(world: World, duration: float) -> list[tuple[str, str, float]]:
    """``(role, role, first time s)`` of every pair of bodies (``"ego"`` or an object's role) that come
    closer than :data:`CLEARANCE_M` (label boxes, ignoring their height where they do not share
    one) between frame 0 and ``duration`` seconds; :func:`make_world` returns worlds where this is
    empty."""
    times = _check_times(duration)
    bodies = [_ego_body(world.ego, times)] + [_object_body(o, times) for o in world.objects]
    found = []
    for i, a in enumerate(bodies):
        for b in bodies[i + 1:]:
            hit = a.clash(b)
            if hit.any():
                found.append((a.role, b.role, float(times[np.argmax(hit)])))
    return found


def make_world(rng: np.random.Generator, duration: float, kind: str = "default", speed_changes_mps2: float = 0.0,
               speed_rng: np.random.Generator | None = None, rear_axle_fraction: float = 0.0) -> World:
    """Sample one segment's world from ``rng``; ``duration`` (s) shapes where objects start.

    ``speed_changes_mps2`` > 0: every moving vehicle and cyclist that does not turn also brakes
    and speeds up (module docstring, "surge"): acceleration amplitude ``g`` uniform in [0.5, 1]
    of it (at most a quarter of its speed times ``W``, so its speed stays above half its mean),
    period ``2 pi / W`` uniform in 4-8 s, phase uniform; drawn from ``speed_rng`` (default: seed 0)
    so that everything else is the world of ``speed_changes_mps2 = 0`` (before placement, which
    then keeps the surging objects clear like any other).

    ``rear_axle_fraction`` > 0: every moving vehicle and cyclist slips at its centre as a car
    does on a turn: the point this fraction of its length behind the centre follows the path
    (:attr:`SynthObject.axle_offset_m`; nothing else is drawn differently).

    ``kind`` "hard" adds :func:`_hard_objects` after the default ones (drawn from ``rng`` after
    everything the default world draws, so the default objects, ego and ground are the same),
    except the ``overtaking`` car: its lane beside the ego is the hard world's ``overtaken_right``
    car's, which it would have to drive through.

    Roles: ``lead`` (ahead in the ego lane), ``overtaking`` (passing on the right, in the next
    lane, clear ahead before the ego's weave takes the ego into that lane), ``slow`` (ahead, in
    the outer lane: overtaken, occluded by the lead car), ``oncoming`` (x2, one starting beyond
    the 75 m label range so it enters late), ``crossing`` (drives across the road in front,
    passing in front of other cars), ``parked`` (x3 in the parking strip along the right curb,
    some beyond 20 m), ``pedestrian`` (x3, type 2; one crosses), ``sign`` (type 3).

    Nothing drives through anything: each object is placed in turn so that its label box keeps
    :data:`CLEARANCE_M` from the ego's body (:data:`EGO_BOX`) and from every box placed before it
    at every instant of the clip (every 20 ms, half a sweep either side); one that would not is
    moved along its path (it comes later or earlier) or, static, along the road, by the first of
    1, -1, 2, -2, ... 60 m that clears, and left out if none does (only in clips much longer than
    the 4 s default; :func:`world_overlaps` checks a world).
    """
    u = rng.uniform
    v_ego = u(7.0, 9.5)
    ego = Motion(p0=(0.0, EGO_LANES[0]), h0=0.0, s=v_ego, a=-u(1.4, 1.75), w=2 * np.pi / u(5.0, 7.0))
    objects: list[SynthObject] = []
    times = _check_times(duration)
    bodies, ghosts = [_ego_body(ego, times)], []
    if not (np.isfinite(speed_changes_mps2) and speed_changes_mps2 >= 0):
        raise ValueError(f"make_world: speed_changes_mps2 must be a number >= 0, got {speed_changes_mps2!r}")
    if not (np.isfinite(rear_axle_fraction) and 0 <= rear_axle_fraction < 0.5):
        raise ValueError(f"make_world: rear_axle_fraction must be a number in [0, 0.5), got {rear_axle_fraction!r}")
    if speed_changes_mps2 > 0 and speed_rng is None:
        speed_rng = np.random.default_rng(0)

    def surging(type_, motion: Motion) -> Motion:
        """``motion`` with a speed change, for a moving vehicle or cyclist that does not turn."""
        if not (speed_changes_mps2 > 0 and type_ in (BoxType.VEHICLE, BoxType.CYCLIST)
                and motion.turn == 0.0 and motion.s > 0.0):
            return motion
        g, period, phase = speed_rng.uniform(0.5, 1.0), speed_rng.uniform(4.0, 8.0), speed_rng.uniform(0.0, 2 * np.pi)
        w = 2 * np.pi / period
        return dataclasses.replace(motion, surge=float(min(g * speed_changes_mps2, 0.25 * motion.s * w)),
                                   surge_w=float(w), surge_phase=float(phase))

    def add(role, type_, size, motion, z=None, pattern=None, keep=True) -> Motion:
        """Place a new object (moved clear of those before it, or left out when it cannot be or
        ``keep`` is False; everything is drawn from ``rng`` either way); returns its motion as
        placed."""
        color = tuple(float(c) for c in rng.uniform(0.15, 0.95, size=3))
        wheeled_mover = type_ in (BoxType.VEHICLE, BoxType.CYCLIST) and (motion.s > 0.0 or motion.turn != 0.0)
        o = SynthObject(
            object_id=_object_id(rng), type=int(type_), size=tuple(float(s) for s in size),
            z_center=float(size[2] / 2 if z is None else z), motion=surging(type_, motion), color=color,
            pattern=int(rng.integers(0, 2) if pattern is None else pattern),
            texture_scale=float(u(0.15, 0.4)), seed=int(rng.integers(0, 2**31 - 1)), role=role,
            axle_offset_m=float(rear_axle_fraction * size[0]) if wheeled_mover else 0.0)
        o = _place(o, bodies, times)
        if o is None:
            return motion
        if not keep:                # the default objects after it are placed as if it were there
            ghosts.append(_object_body(o, times))
            bodies.append(ghosts[-1])
            return o.motion
        objects.append(o)
        bodies.append(_object_body(o, times))
        return o.motion

    def car_size():
        return (u(4.2, 5.0), u(1.8, 2.05), u(1.45, 1.8))

    vehicle, pedestrian, sign = BoxType.VEHICLE, BoxType.PEDESTRIAN, BoxType.SIGN
    add("lead", vehicle, car_size(), Motion((u(13.0, 17.0), EGO_LANES[0]), 0.0, s=v_ego + u(-0.5, 0.5)))
    # the overtaking car passes on the right and is clear ahead (its rear 2.5 m beyond the ego's
    # front, which the weave's yaw swings out) when the weave brings the ego's right side within
    # CLEARANCE_M of its lane
    size, dv = car_size(), u(4.0, 6.0)
    into_lane = EGO_LANES[0] - EGO_BOX[2] / 2 - CLEARANCE_M - (EGO_LANES[1] + size[1] / 2)
    t_in = np.arccos(1.0 - into_lane / abs(ego.a)) / ego.w
    front = EGO_BOX[0] + EGO_BOX[1] / 2
    add("overtaking", vehicle, size,
        Motion((float(front + 2.5 + size[0] / 2 - dv * t_in), EGO_LANES[1]), 0.0, s=v_ego + dv), keep=kind != "hard")
    add("slow", vehicle, car_size(), Motion((u(24.0, 32.0), EGO_LANES[2]), 0.0, s=u(2.0, 3.5)))
    add("oncoming", vehicle, car_size(), Motion((u(45.0, 60.0), ONCOMING_LANES[0]), np.pi, s=u(8.0, 11.0)))
    add("oncoming", vehicle, car_size(),
        Motion((85.0 + v_ego * duration * 0.3, ONCOMING_LANES[1]), np.pi, s=u(9.0, 12.0)))
    cross_x = u(30.0, 38.0) + v_ego * duration * 0.25
    add("crossing", vehicle, car_size(), Motion((cross_x, CURB_Y - 6.0), np.pi / 2, s=u(5.0, 7.0)))
    for x in (u(10.0, 16.0), u(22.0, 28.0), u(40.0, 55.0)):
        add("parked", vehicle, car_size(), Motion((x, PARKED_Y), u(-0.05, 0.05)))
    add("pedestrian", pedestrian, (u(0.6, 0.9), u(0.6, 0.9), u(1.6, 1.9)),
        Motion((u(12.0, 20.0), CURB_Y - 1.5), 0.0, s=u(1.0, 1.5)))
    add("pedestrian", pedestrian, (u(0.6, 0.9), u(0.6, 0.9), u(1.6, 1.9)),
        Motion((u(25.0, 35.0), CURB_Y - 2.5), np.pi, s=u(1.0, 1.5), a=0.4, w=2 * np.pi / 4.0))
    add("pedestrian", pedestrian, (u(0.6, 0.9), u(0.6, 0.9), u(1.6, 1.9)),
        Motion((u(18.0, 26.0) + v_ego * duration * 0.5, FAR_CURB_Y + 1.0), -np.pi / 2, s=u(1.2, 1.6)))
    add("sign", sign, (0.12, 0.9, 0.9), Motion((u(20.0, 30.0), CURB_Y - 0.8), np.pi / 2),
        z=2.4, pattern=1)
    if kind not in WORLDS:
        raise ValueError(f"unknown world {kind!r}; choose from {', '.join(WORLDS)}")
    pitch, roll = float(u(0.003, 0.008)), float(u(0.002, 0.006))
    ground_seed = int(rng.integers(0, 2**31 - 1))
    if kind == "hard":
        bodies[:] = [b for b in bodies if not any(b is g for g in ghosts)]
        _hard_objects(rng, duration, ego, objects, add, car_size)
    return World(ego=ego, pitch_amplitude=pitch, roll_amplitude=roll, objects=tuple(objects),
                 ground_seed=ground_seed)


def _hard_objects(rng, duration, ego: Motion, objects, add, car_size) -> None:
    """The cases of issues 15 and 16 that break a depth-ratio occlusion test or frame-time
    projection (all closed-form in time; roles name them in the truth's ``objects.npz``):

    - ``oblique`` (x3, one pulling out at 2 m/s): cars 20-70 m ahead (at mid-clip) beside the
      road, turned 30-60 degrees from the line of sight, so their far faces hide behind their near
      ones and the ego's motion shows the lidar different faces over the clip;
    - ``occluder`` (a parked 8 m van beyond the far curb) and ``hidden`` (a car behind it, driving
      so that it slides progressively into the van's shadow as seen from the ego);
    - ``pole`` (x3, 0.3 x 0.3 x 5 m, type SIGN) on the curbs in the mid-clip line of sight to the
      oblique cars and the van; ``low_sign`` (a plate 0.8 m square centred 1.3 m up, car height);
    - ``pedestrian_near_car`` (x2): one walking along the road side of the first parked car
      (between it and the outer lane), one standing on the sidewalk behind the second;
    - ``close_pass``: a car overtaking on the left 1.5-1.8 m beside the ego (it follows the ego's
      weave, so the gap stays constant), passing it at mid-clip (SIDE_LEFT, FRONT_LEFT);
    - ``overtaken_right``: a slower car 1.5-2 m right of the ego (it follows the ego's weave, which
      takes it from the next lane to the outer one), overtaken at mid-clip (FRONT_RIGHT,
      SIDE_RIGHT);
    - ``turning``: an oncoming car turning right (towards +y) off the road just ahead of the ego
      (FRONT_LEFT, SIDE_LEFT);
    - ``crossing_cyclist`` (type CYCLIST): crosses the road ahead of the ego's end position (and
      of where the lead car ends).
    """
    u = rng.uniform
    v = ego.s
    t_mid = 0.5 * duration
    x_mid = v * t_mid
    y_ego = EGO_LANES[0] + ego.a          # mean lateral position of the weaving ego
    vehicle, pedestrian, sign = BoxType.VEHICLE, BoxType.PEDESTRIAN, BoxType.SIGN

    def toward(x, y):
        return float(np.arctan2(y - y_ego, x - x_mid))

    def on_sight_line(x, y, y_line):
        """x where the mid-clip line of sight from the ego to (x, y) crosses y = y_line."""
        return float(x_mid + (x - x_mid) * (y_line - y_ego) / (y - y_ego))

    oblique = [(x_mid + u(20.0, 30.0), FAR_CURB_Y + u(3.5, 5.0)),
               (x_mid + u(35.0, 45.0), CURB_Y - u(3.5, 5.0)),
               (x_mid + u(50.0, 65.0), FAR_CURB_Y + u(3.0, 4.0))]
    for i, (x, y) in enumerate(oblique):
        angle = np.deg2rad(u(30.0, 60.0)) * (1 if rng.integers(0, 2) else -1)
        heading = toward(x, y) + angle + (np.pi if rng.integers(0, 2) else 0.0)
        oblique[i] = add("oblique", vehicle, car_size(), Motion((x, y), float(heading), s=2.0 if i == 2 else 0.0)).p0
    # the van and the car sliding into its shadow (seen from the ego's mean lateral position)
    van = (8.0, 2.4, 3.0)
    xo, yo, yh = x_mid + u(22.0, 30.0), FAR_CURB_Y + 2.0, FAR_CURB_Y + 9.0      # hidden: beyond the obliques
    xo = add("occluder", vehicle, van, Motion((xo, yo), 0.0)).p0[0]
    scale = (yh - y_ego) / (yo - y_ego)

    def shadow_x(t):    # x of the van's centre seen at y = yh from the ego at time t
        return v * t + (xo - v * t) * scale
    # just clear of the shadow at t = 0: beyond the ray from the ego (at x = 0, EGO_LANES[0]) past
    # the van's near far corner, by 1 m
    size = car_size()
    start = (xo + van[0] / 2) * (yh - EGO_LANES[0]) / (yo - van[1] / 2 - EGO_LANES[0]) + size[0] / 2 + 1.0
    end = shadow_x(duration)                                  # behind the van's centre at the end
    add("hidden", vehicle, size, Motion((start, yh), 0.0, s=(end - start) / duration))
    for x, y in (oblique[0], oblique[2], (xo, yo)):
        add("pole", sign, (0.3, 0.3, 5.0), Motion((on_sight_line(x, y, FAR_CURB_Y + 0.4), FAR_CURB_Y + 0.4), 0.0),
            z=2.5, pattern=1)
    x, y = oblique[1]
    add("low_sign", sign, (0.1, 0.8, 0.8),
        Motion((on_sight_line(x, y, CURB_Y - 0.4), CURB_Y - 0.4), np.pi / 2), z=1.3, pattern=1)
    parked = [o for o in objects if o.role == "parked"]
    p0, p1 = parked[0].motion.p0, parked[1].motion.p0
    # between the first parked car and the right side of the widest car (car_size: 2.05 m, half
    # rounded up) in the outer lane
    y_walk = 0.5 * (p0[1] + parked[0].size[1] / 2 + EGO_LANES[2] - 1.03)
    add("pedestrian_near_car", pedestrian, (u(0.6, 0.9), u(0.6, 0.9), u(1.6, 1.9)),
        Motion((p0[0] - 4.0, y_walk), 0.0, s=u(1.0, 1.4)))
    add("pedestrian_near_car", pedestrian, (u(0.6, 0.9), u(0.6, 0.9), u(1.6, 1.9)),
        Motion((p1[0] + u(-1.0, 1.0), CURB_Y - 0.6), 0.0))
    # movers beside the ego: same weave as the ego, so the lateral gap is constant
    gap = u(1.5, 1.8)
    size = car_size()
    dv = u(3.0, 4.5)
    add("close_pass", vehicle, size, Motion((-dv * t_mid, EGO_LANES[0] + 1.0 + gap + size[1] / 2), 0.0,
                                            s=v + dv, a=ego.a, w=ego.w))
    size = car_size()
    dv = u(2.5, 3.5)
    add("overtaken_right", vehicle, size, Motion((dv * t_mid, EGO_LANES[0] - EGO_BOX[2] / 2 - u(1.5, 2.0) - size[1] / 2),
                                                 0.0, s=v - dv, a=ego.a, w=ego.w))
    s_turn = u(5.0, 6.5)
    add("turning", vehicle, car_size(), Motion((x_mid + 6.0 + s_turn * t_mid, ONCOMING_LANES[0]), np.pi,
                                               s=s_turn, turn=-u(0.45, 0.6)))
    s_bike = u(3.5, 4.5)
    lead = next(o for o in objects if o.role == "lead")        # crosses beyond where it ends
    x_bike = max(v * duration + u(8.0, 12.0), float(lead.center(np.array(duration))[0]) + lead.size[0] / 2 + 2.0)
    if abs(x_bike - xo) < van[0] / 2 + 1.5:     # it comes from the far sidewalk: not out of the van
        x_bike = xo + van[0] / 2 + 1.5
    add("crossing_cyclist", BoxType.CYCLIST, (1.8, 0.6, 1.7),
        Motion((x_bike, y_ego + s_bike * duration * 0.6), -np.pi / 2, s=s_bike))
