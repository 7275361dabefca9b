"""Exact ground truth of the object returns: pixels and visibility in every camera and frame."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from drivetrack.camera.model import CameraModel
from drivetrack.geometry import invert_rigid
from drivetrack.synth import ground_truth as gt
from drivetrack.synth.boxes import _apply, _yaw_transform
from drivetrack.synth.raycast import intersect_solids

if TYPE_CHECKING:
    from drivetrack.synth.state import _Generator


def _empty_hits():
    return dict(frame=np.zeros(0, np.int32), laser=np.zeros(0, np.int8),
                return_index=np.zeros(0, np.int8), row=np.zeros(0, np.int32),
                col=np.zeros(0, np.int32), object_index=np.zeros(0, np.int32),
                capture_time=np.zeros(0), point_vehicle=np.zeros((0, 3)), point_box=np.zeros((0, 3)))



def face_normals_box(object_index: np.ndarray, point_box: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """float64 [N, 3] outward unit normal, in the box frame, of the face each body point lies on
    (the axis where the point is closest to the box surface, relative to the half size)."""
    rel = np.abs(point_box) / (sizes[object_index] / 2.0)
    axis = np.argmax(rel, axis=-1)
    normal = np.zeros_like(point_box)
    normal[np.arange(axis.size), axis] = np.sign(point_box[np.arange(axis.size), axis])
    return normal


def face_normals(object_index: np.ndarray, point_box: np.ndarray, solids: list) -> np.ndarray:
    """float64 [N, 3] outward unit normal, in the box frame, of the face each body point lies on,
    for objects made of several solids (``solids[k]``: object k's
    :attr:`drivetrack.synth.world.SynthObject.solids`): the solid whose surface the point lies on
    (its largest relative coordinate nearest 1), then :func:`face_normals_box` of that solid."""
    normal = np.zeros_like(point_box)
    for k in np.unique(object_index).tolist():
        on = np.flatnonzero(object_index == k)
        local = [point_box[on] - offset for offset, _ in solids[k]]
        gap = np.stack([np.abs(np.max(np.abs(q) / half, axis=-1) - 1.0) for q, (_, half) in zip(local, solids[k])])
        pick = np.argmin(gap, axis=0)
        for index, (_, half) in enumerate(solids[k]):
            sel = pick == index
            if sel.any():
                normal[on[sel]] = face_normals_box(np.zeros(int(sel.sum()), np.int64), local[index][sel],
                                                   (2.0 * half)[None])
    return normal


def _carry_and_check(g: _Generator, object_index: np.ndarray, point_box: np.ndarray, progress):
    """Pixels float32 [N, C, T, 2], visibility bool [N, C, T] and facing bool [N, C, T] of every
    body point. ``facing``: the point's face normal points towards the camera centre at the
    point's capture time (a back face when False); computed where the pixel is inside the image,
    False elsewhere."""
    N, C, T = object_index.size, len(g.cameras), g.T
    pixels = np.full((N, C, T, 2), np.nan, np.float32)
    visible = np.zeros((N, C, T), bool)
    facing = np.zeros((N, C, T), bool)
    if N == 0:
        return pixels, visible, facing
    solids = [obj.solids for obj in g.world.objects]
    normal_box = face_normals(object_index, point_box, solids)
    for tau in range(T):
        pw_frame = _yaw_transform(point_box, g.centers[object_index, tau], g.headings[object_index, tau])
        for ci, (cam, model) in enumerate(g.cameras.items()):
            law = g.time_law(cam, tau)
            if law is None:
                world_from_camera = g.world_from_vehicle[tau] @ model.vehicle_from_camera
                pw = pw_frame
                pc = _apply(invert_rigid(world_from_camera), pw)
                px, ok = model.pixels_from_camera(pc)
                point_time = None
            else:
                point_time, pw, pc, solved = _solve_capture_times(g, model, law, tau, object_index, point_box)
                px, ok = model.pixels_from_camera(pc)
                ok &= solved
                px[~ok] = np.nan
            pixels[:, ci, tau] = px
            inside = ok & model.inside_image(px)
            cand = np.flatnonzero(inside)
            if cand.size == 0:
                continue
            if point_time is None:
                origin = np.broadcast_to(world_from_camera[:3, 3], (cand.size, 3))
            else:
                origin = g.camera_centres_rays_at(model, point_time[cand], np.zeros((cand.size, 3)))[0]
            if point_time is None:
                heading = g.headings[object_index[cand], tau]
            else:
                heading = g.object_poses_at(object_index[cand], point_time[cand])[1]
            normal_world = _yaw_transform(normal_box[cand], np.zeros((cand.size, 3)), heading)
            facing[cand, ci, tau] = np.sum(normal_world * (origin - pw[cand]), axis=-1) > 0.0
            vec = pw[cand] - origin
            dist = np.linalg.norm(vec, axis=-1)
            dirs = vec / dist[:, None]
            best = np.full(cand.size, np.inf)
            best_obj = np.full(cand.size, -1)
            with np.errstate(divide="ignore", invalid="ignore"):
                tg = -origin[:, 2] / dirs[:, 2]
            ground_first = (dirs[:, 2] < 0) & (tg > 0)
            best = np.where(ground_first, tg, best)
            pxc = px[cand]
            own = object_index[cand]
            by_x = np.argsort(pxc[:, 0], kind="stable")
            xs_sorted = pxc[by_x, 0]
            by_own = np.argsort(own, kind="stable")
            own_bounds = np.searchsorted(own[by_own], np.arange(g.K + 1))
            origins = origin
            for k in range(g.K):
                rect = g.rects[(ci, tau, k)]
                own_k = by_own[own_bounds[k]:own_bounds[k + 1]]
                if rect is None:
                    sel = own_k
                else:
                    x0, x1, y0, y1 = rect
                    lo, hi = np.searchsorted(xs_sorted, [x0, x1], side="left")
                    in_x = by_x[lo:hi]
                    in_rect = in_x[(pxc[in_x, 1] >= y0) & (pxc[in_x, 1] < y1)]
                    sel = np.union1d(in_rect, own_k)
                if sel.size == 0:
                    continue
                if point_time is None:
                    center_k, heading_k = g.centers[k, tau], g.headings[k, tau]
                else:
                    obj = g.world.objects[k]
                    center_k, heading_k = obj.center(point_time[cand[sel]]), obj.heading(point_time[cand[sel]])
                t_in = intersect_solids(origins[sel], dirs[sel], center_k, heading_k, solids[k], 0.0)[0]
                better = t_in < best[sel]
                best[sel[better]] = t_in[better]
                best_obj[sel[better]] = k
            vis = (best_obj == own) & (np.abs(best - dist) <= gt.VISIBILITY_TOLERANCE_M)
            visible[cand, ci, tau] = vis
        if progress:
            progress("truth", tau + 1, T)
    return pixels, visible, facing


#: fixed-point iteration on a body point's capture time: stop below this change (s) ...
_TIME_TOLERANCE_S = 1e-12
#: ... or after this many iterations; points still moving by more than 1e-9 s are unsolved.
_TIME_ITERATIONS = 60


def _solve_capture_times(g: _Generator, model: CameraModel, law, tau: int, object_index: np.ndarray,
                         point_box: np.ndarray):
    """When the rolling-shutter camera sees each body point in image ``tau``.

    Solves ``t = times[tau] + offset + rate * n(t)``, with ``n(t)`` the undistorted normalised
    coordinate (along the readout axis) of the point at ``t`` (object pose at ``t``) in the camera
    at ``t`` (ego pose at ``t``), by fixed-point iteration on the still-moving points; the map
    contracts with factor ``rate * dn/dt`` (readout seconds per unit n times the angular rate of
    the point in the camera, below 0.5 even for a car passing 2 m from the lens). Times are
    clipped to 1 s around the frame (points far outside the view; never trusted pixels).

    Returns ``(time float64 [N] s since frame 0, points_world float64 [N, 3] at that time,
    points_camera float64 [N, 3] at that time, solved bool [N])``; ``solved`` is False for
    points behind the camera or whose time still changed by more than 1e-9 s at the end.
    """
    axis, rate, offset = law
    n = object_index.size
    base = g.times[tau]
    dt = np.full(n, offset)
    change = np.full(n, np.inf)
    front = np.ones(n, bool)
    active = np.arange(n)
    for _ in range(_TIME_ITERATIONS):
        if active.size == 0:
            break
        tt = base + dt[active]
        center, heading = g.object_poses_at(object_index[active], tt)
        pw = _yaw_transform(point_box[active], center, heading)
        pc = g.camera_from_world_at(model, tt, pw)
        x = pc[:, 0]
        ok = x > 1e-6
        new = np.clip(offset + rate * (-pc[:, 1 + axis] / np.where(ok, x, 1.0)), -1.0, 1.0)
        new = np.where(ok, new, dt[active])
        change[active] = np.abs(new - dt[active])
        front[active] = ok
        dt[active] = new
        active = active[ok & (change[active] > _TIME_TOLERANCE_S)]
    time = base + dt
    center, heading = g.object_poses_at(object_index, time)
    pw = _yaw_transform(point_box, center, heading)
    pc = g.camera_from_world_at(model, time, pw)
    solved = front & (change <= 1e-9) & (pc[:, 0] > 0)
    return time, pw, pc, solved
