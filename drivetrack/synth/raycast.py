"""Vectorised ray casting against the ground plane (z = 0) and yaw-oriented boxes.

An object is the union of its :attr:`drivetrack.synth.world.SynthObject.solids` (its label box,
or a vehicle's body and cabin): a ray hits the nearest of them.

Rays are given in the world frame (origins float64 [N, 3], unit directions float64 [N, 3]); a hit
distance ``t`` is metres along the ray. Boxes are passed per object as centre and heading, either
one pose for all its candidate rays or one per ray (a lidar column sees a moving object at that
column's capture time). Callers restrict each object to candidate rays (a screen rectangle or an
azimuth window); every candidate goes through an exact slab test, so the restriction only saves
time and never changes a result as long as it contains the object's silhouette.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from drivetrack.synth.texture import face_albedo, ground_albedo
from drivetrack.synth.world import World

__all__ = ["Hits", "intersect_box", "intersect_solids", "part_center", "cast", "surface_albedo_normal", "GROUND", "NO_HIT"]

GROUND = -1
NO_HIT = -2

#: (center float64 [n, 3], heading float64 [n]) of object k for the given ray indices [n].
PoseFn = Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass
class Hits:
    """First hit per ray. ``t`` float64 [N] metres (inf = none), ``obj`` int32 [N] object index
    or GROUND / NO_HIT, ``axis`` int8 [N] box-frame axis of the hit face, ``t_exit`` float64 [N]
    where the ray leaves the hit solid (inf for the ground), ``part`` int8 [N] which of the
    object's solids it hit."""
    t: np.ndarray
    obj: np.ndarray
    axis: np.ndarray
    t_exit: np.ndarray
    part: np.ndarray

    @classmethod
    def empty(cls, n: int) -> "Hits":
        return cls(np.full(n, np.inf), np.full(n, NO_HIT, np.int32), np.zeros(n, np.int8),
                   np.full(n, np.inf), np.zeros(n, np.int8))


def _to_box(origins, dirs, center, heading):
    c, s = np.cos(heading), np.sin(heading)
    rx, ry, rz = (origins[:, i] - center[..., i] for i in range(3))
    o = (c * rx + s * ry, -s * rx + c * ry, rz)
    d = (c * dirs[:, 0] + s * dirs[:, 1], -s * dirs[:, 0] + c * dirs[:, 1], dirs[:, 2])
    return o, d


def intersect_box(origins: np.ndarray, dirs: np.ndarray, center: np.ndarray, heading: np.ndarray,
                  half_size: np.ndarray, t_min: np.ndarray | float = 0.0):
    """Slab test of rays against one box.

    Args:
        origins, dirs: float64 [n, 3] world rays.
        center: float64 [3] or [n, 3]; heading: float or float64 [n] (yaw about world z).
        half_size: float64 [3], half length/width/height.
        t_min: hits at or before ``t_min`` (float or [n]) are ignored.
    Returns:
        ``(t_enter, t_exit, axis)``: float64 [n] (inf where missed), float64 [n], int8 [n].
    """
    o, d = _to_box(origins, dirs, np.asarray(center, np.float64), np.asarray(heading, np.float64))
    lo, hi = [], []
    with np.errstate(divide="ignore", invalid="ignore"):
        for i in range(3):
            di = np.where(d[i] == 0.0, 1e-300, d[i])
            t1 = (-half_size[i] - o[i]) / di
            t2 = (half_size[i] - o[i]) / di
            lo.append(np.minimum(t1, t2))
            hi.append(np.maximum(t1, t2))
    lo_all = np.stack(lo, axis=0)
    t_near = lo_all.max(axis=0)
    t_far = np.minimum(np.minimum(hi[0], hi[1]), hi[2])
    axis = lo_all.argmax(axis=0).astype(np.int8)
    hit = (t_near <= t_far) & (t_near > t_min)
    return np.where(hit, t_near, np.inf), np.where(hit, t_far, np.inf), axis


def part_center(center: np.ndarray, heading: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """float64 [..., 3]: the world centre of a solid at box-frame ``offset`` float64 [3] of a box at
    ``center`` float64 [..., 3] with yaw ``heading`` float64 [...]."""
    c, s = np.cos(heading), np.sin(heading)
    x = center[..., 0] + c * offset[0] - s * offset[1]
    y = center[..., 1] + s * offset[0] + c * offset[1]
    return np.stack([x, y, np.broadcast_to(center[..., 2] + offset[2], x.shape)], axis=-1)


def intersect_solids(origins: np.ndarray, dirs: np.ndarray, center: np.ndarray, heading: np.ndarray,
                     solids, t_min: np.ndarray | float = 0.0):
    """:func:`intersect_box` against the union of ``solids`` (``((offset [3], half size [3]), ...)``
    in the box frame; :attr:`drivetrack.synth.world.SynthObject.solids`): the nearest entry.
    Returns ``(t_enter, t_exit, axis, part int8 [n])``."""
    center = np.asarray(center, np.float64)
    heading = np.asarray(heading, np.float64)
    best = None
    for index, (offset, half) in enumerate(solids):
        found = intersect_box(origins, dirs, part_center(center, heading, offset) if offset.any() else center,
                              heading, half, t_min)
        if best is None:
            best = (*found, np.zeros(found[0].shape, np.int8))
            continue
        nearer = found[0] < best[0]
        best = (np.where(nearer, found[0], best[0]), np.where(nearer, found[1], best[1]),
                np.where(nearer, found[2], best[2]).astype(np.int8), np.where(nearer, np.int8(index), best[3]))
    return best


def cast(origins: np.ndarray, dirs: np.ndarray, world: World, pose_of: PoseFn,
         candidates: list[np.ndarray | None], t_min: np.ndarray | float = 0.0,
         t_max: float = np.inf, ground: bool = True) -> Hits:
    """First hit of each ray over the ground and the objects of ``world``.

    Args:
        origins, dirs: float64 [N, 3] world rays (dirs unit length).
        pose_of: pose of object k for ray indices (see :data:`PoseFn`).
        candidates: per object, int indices of rays to test (None = skip the object).
        t_min: float or float64 [N]; only hits beyond it count (second returns).
        t_max: hits beyond it are dropped (sensor range).
    """
    n = origins.shape[0]
    hits = Hits.empty(n)
    t_min_arr = np.broadcast_to(np.asarray(t_min, np.float64), (n,))
    if ground:
        with np.errstate(divide="ignore", invalid="ignore"):
            tg = -origins[:, 2] / dirs[:, 2]
        ok = (dirs[:, 2] < 0) & (tg > t_min_arr)
        hits.t = np.where(ok, tg, np.inf)
        hits.obj[ok] = GROUND
    for k, idx in enumerate(candidates):
        if idx is None or idx.size == 0:
            continue
        obj = world.objects[k]
        center, heading = pose_of(k, idx)
        t_in, t_out, axis, part = intersect_solids(origins[idx], dirs[idx], center, heading, obj.solids,
                                                   t_min_arr[idx])
        better = t_in < hits.t[idx]
        sel = idx[better]
        hits.t[sel] = t_in[better]
        hits.obj[sel] = k
        hits.axis[sel] = axis[better]
        hits.t_exit[sel] = t_out[better]
        hits.part[sel] = part[better]
    far = hits.t > t_max
    hits.t[far] = np.inf
    hits.obj[far] = NO_HIT
    return hits


def surface_albedo_normal(hits: Hits, origins: np.ndarray, dirs: np.ndarray, world: World,
                          pose_of: PoseFn) -> tuple[np.ndarray, np.ndarray]:
    """Albedo float32 [N, 3] and world normal float32 [N, 3] at each hit (zeros where none)."""
    n = hits.t.shape[0]
    albedo = np.zeros((n, 3), np.float32)
    normal = np.zeros((n, 3), np.float32)
    g = np.flatnonzero(hits.obj == GROUND)
    if g.size:
        tg = hits.t[g]
        gx = (origins[g, 0] + tg * dirs[:, 0][g]).astype(np.float32)
        gy = (origins[g, 1] + tg * dirs[:, 1][g]).astype(np.float32)
        albedo[g] = ground_albedo(gx, gy, world.ground_seed)
        normal[g, 2] = 1.0
    for k, obj in enumerate(world.objects):
        idx = np.flatnonzero(hits.obj == k)
        if idx.size == 0:
            continue
        center, heading = pose_of(k, idx)
        p = origins[idx] + hits.t[idx, None] * dirs[idx]
        o, _ = _to_box(p, dirs[idx], np.asarray(center), np.asarray(heading))
        pb = np.stack(o, axis=-1)
        axis = hits.axis[idx].astype(np.int64)
        other_a = np.where(axis == 0, pb[:, 1], pb[:, 0])
        other_b = np.where(axis == 2, pb[:, 1], pb[:, 2])
        albedo[idx] = face_albedo(other_a + 7.0 * axis, other_b, np.asarray(obj.color),
                                  obj.pattern, obj.texture_scale, obj.seed)
        # the face's side from the hit solid's own centre (the box centre for a plain box)
        offsets = np.stack([o for o, _ in obj.solids])[hits.part[idx].astype(np.int64)]      # [n, 3]
        sign = np.sign((pb - offsets)[np.arange(idx.size), axis])
        nb = np.zeros((idx.size, 3))
        nb[np.arange(idx.size), axis] = sign
        c, s = np.cos(heading), np.sin(heading)
        normal[idx, 0] = c * nb[:, 0] - s * nb[:, 1]
        normal[idx, 1] = s * nb[:, 0] + c * nb[:, 1]
        normal[idx, 2] = nb[:, 2]
    return albedo, normal
