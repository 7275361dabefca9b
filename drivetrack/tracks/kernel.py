"""Fused numba kernel of the track stage's inner loop (global-shutter projection).

One pass over (point, frame) computes what :func:`drivetrack.tracks.core.run_object_job`'s numpy
path computes with [T, n] temporaries: the camera-frame point ``camera_from_box[tau] @ p +
shift_camera[tau]``, its Brown-Conrady projection (``CameraModel.pixels_from_camera``: valid iff
x > 1e-6 and the distortion factor lies in [0.8, 1.2]), the inside-image test, occlusion against
the clip's depth maps with the max-of-4 look-up (``drivetrack.depth.lookup_max4``; a surface
inside the object's own grown box hides no point with a reliable normal,
``drivetrack.visibility.own_surface``), the
vehicle-frame point ``vehicle_from_box[tau] @ p`` and the world-path speed. Math is float64; the
outputs are written directly in [N, T] order.

Two passes keep memory at what is kept: :func:`screen_points` decides for every candidate whether
it survives (visible at some frame, and the optional speed filter) and computes its speed; it stops
at a point's first visible frame. :func:`fill_tracks` then computes the kept points' tracks,
holding the nearest valid position where the projection is invalid (as
``core.fill_invalid_positions``), a chunk of points at a time. :func:`depth_margins` then gives
the kept point-frames' occlusion margins (the depth map's term where it is the smallest).

The writers stream the outputs without the depth maps (visibility is known by then):
:func:`fill_positions` gives exactly ``fill_tracks``' ``tracks`` and ``points3d`` of a chunk of
points (point-major), :func:`fill_points3d_frames` its ``points3d`` for a range of frames
(time-major), with the same float64 arithmetic in the same order (bit-identical results).

numba compiles on first use and caches the machine code on disk (``cache=True``), so a process
pays the compile once (or never, with a warm cache).
"""
from __future__ import annotations

import numpy as np

from drivetrack.camera.kernel import camera_parameters
from drivetrack.camera.kernel import pixel_from_camera_point as _pixel

__all__ = ["NUMBA_AVAILABLE", "camera_parameters", "screen_points", "fill_tracks", "depth_margins", "fill_positions",
           "fill_points3d_frames", "summarise_tracks", "path_speeds", "points_box_at"]

from drivetrack.numba_compat import NUMBA_AVAILABLE, njit

#: Status codes of :func:`screen_points`.
KEPT, DROPPED_INVISIBLE, DROPPED_SPEED = 0, 1, 2


@njit(cache=True, nogil=True, inline="always")
def _visible(depth_maps, tau, height, width, pix_x, pix_y, x, valid, occlusion_ratio, own, own_point, others,
             px, py, pz, grow_px):
    """Inside the image and not behind the max-of-4 surface of ``depth_maps[tau]`` (float32 [T, H, W]).

    ``own`` float64 [T, 13] (or [0, 13]: off): per frame the camera centre in the box frame, the
    half extents of the object's own box grown by ``TrackConfig.own_surface_margin_m``,
    ``own_surface_max_gap_m``, and the half extents and centre of the box itself a ray must pass
    through (the part its returns fill, less ``OWN_BOX_DEPTH_M``:
    :func:`drivetrack.visibility.own_box_parameters`); a surface whose point on the ray to the
    box-frame point (px, py, pz) lies in that grown box, at most the gap in front of the point or
    farther with the ray from it to the gap not passing through the box itself, does not hide it;
    where not ``own_point`` (the point's normal is unreliable, so the back-face test cannot
    decide) the gap is 0: only the ray test (:func:`drivetrack.visibility.own_surface`). ``others``
    float64 [T, K, 21] (K may be 0; used only with ``own``): per frame the other labelled objects'
    boxes as 9 rotation and 3 translation values taking this object's box frame to theirs, their
    half extents grown by the margin (negative: an unused slot), then the half extents and centre
    of the part their returns fill; a surface whose point lies in a
    grown one while the ray to the point misses the box itself is that object's outline spread by
    the map, and the z-buffer decides instead (:func:`drivetrack.visibility.other_surface`)."""
    if not valid:
        return False
    best = _max4(depth_maps, tau, height, width, pix_x, pix_y, grow_px)
    if best < 0:
        return False
    if not (best > 0 and best < occlusion_ratio * x):
        return True
    return _surface_is_theirs(tau, best / x, own, own_point, others, px, py, pz)


@njit(cache=True, nogil=True, inline="always")
def _max4(depth_maps, tau, height, width, pix_x, pix_y, grow_px=0):
    """The max-of-4 surface (float32, metres; 0: unknown) of ``depth_maps[tau]`` at pixel (pix_x,
    pix_y), ``drivetrack.depth.lookup_max4``; -1 outside the image. ``grow_px`` > 0: the maximum
    over those pixels and every pixel within ``grow_px`` of them (``lookup_max4(grow_px=...)``)."""
    if not (pix_x >= 0.0 and pix_x < width and pix_y >= 0.0 and pix_y < height):
        return np.float32(-1.0)
    # columns floor(x - 0.5) and ceil(x - 0.5), rows likewise; neighbours outside count as unknown
    cx = pix_x - 0.5
    cy = pix_y - 0.5
    c0 = int(np.floor(cx))
    r0 = int(np.floor(cy))
    c1 = c0 + 1 if cx > c0 else c0
    r1 = r0 + 1 if cy > r0 else r0
    best = np.float32(0.0)
    if grow_px > 0:
        for r in range(max(r0 - grow_px, 0), min(r1 + grow_px, height - 1) + 1):
            for c in range(max(c0 - grow_px, 0), min(c1 + grow_px, width - 1) + 1):
                best = max(best, depth_maps[tau, r, c])
        return best
    c0_ok = c0 >= 0
    c1_ok = c1 < width
    if r0 >= 0:
        if c0_ok:
            best = max(best, depth_maps[tau, r0, c0])
        if c1_ok:
            best = max(best, depth_maps[tau, r0, c1])
    if r1 < height:
        if c0_ok:
            best = max(best, depth_maps[tau, r1, c0])
        if c1_ok:
            best = max(best, depth_maps[tau, r1, c1])
    return best


@njit(cache=True, nogil=True, inline="always")
def _surface_is_theirs(tau, scale, own, own_point, others, px, py, pz):
    """The depth map's surface at ``scale`` (its depth over the point's) on the ray to the box-frame
    point (px, py, pz) is the object's own or another labelled object's spread, so it hides
    nothing (:func:`_visible`; False when ``own`` is [0, 13]: off)."""
    if own.shape[0] == 0:
        return False
    # the surface's point on the ray from the camera centre e through p: e + (best / x) (p - e)
    e = own[tau]
    qx = e[0] + scale * (px - e[0])
    qy = e[1] + scale * (py - e[1])
    qz = e[2] + scale * (pz - e[2])
    if abs(qx) <= e[3] and abs(qy) <= e[4] and abs(qz) <= e[5]:
        # ... unless it lies farther in front of the point than the gap limit (e[6]; 0 at a point
        # without a reliable normal) and the ray from it to that far in front of the point passes
        # through the box itself (a part of the object; through the margin only the map's spread)
        limit = e[6] if own_point else 0.0
        gap = np.sqrt((px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2)
        if gap <= limit:
            return True
        w = limit / gap
        if not _segment_in_box(qx - e[10], qy - e[11], qz - e[12], px + (qx - px) * w - e[10],
                               py + (qy - py) * w - e[11], pz + (qz - pz) * w - e[12], e[7], e[8], e[9]):
            return True
    for k in range(others.shape[1]):
        o = others[tau, k]
        if o[12] < 0:
            continue
        ox = o[0] * qx + o[1] * qy + o[2] * qz + o[9]
        oy = o[3] * qx + o[4] * qy + o[5] * qz + o[10]
        oz = o[6] * qx + o[7] * qy + o[8] * qz + o[11]
        if abs(ox) <= o[12] and abs(oy) <= o[13] and abs(oz) <= o[14] and not _segment_enters_box(o, e, px, py, pz):
            return True
    return False


@njit(cache=True, nogil=True, inline="always")
def _segment_in_box(sx, sy, sz, fx, fy, fz, hx, hy, hz):
    """The segment from (sx, sy, sz) to (fx, fy, fz) (a box's frame) passes through the box of
    half extents (hx, hy, hz) before its end (slab test, t in [0, 1); as
    ``drivetrack.visibility.facing._segment_enters_box``)."""
    enter, leave = 0.0, np.inf
    for s, f, h in ((sx, fx, hx), (sy, fy, hy), (sz, fz, hz)):
        d = f - s
        if abs(d) < 1e-12:
            if abs(s) > h:
                return False
            continue
        t1 = (-h - s) / d
        t2 = (h - s) / d
        enter = max(enter, min(t1, t2))
        leave = min(leave, max(t1, t2))
    return enter <= leave and enter < 1.0


@njit(cache=True, nogil=True, inline="always")
def _segment_enters_box(o, e, px, py, pz):
    """The segment from the camera centre ``e[:3]`` to the point (px, py, pz) (this object's box
    frame) passes through the solid part of the box of ``o`` (:func:`_visible`'s slot: rotation,
    translation, grown half extents, the solid part's half extents and centre) before the point
    (slab test, t in [0, 1))."""
    return _segment_in_box(o[0] * e[0] + o[1] * e[1] + o[2] * e[2] + o[9] - o[18],
                               o[3] * e[0] + o[4] * e[1] + o[5] * e[2] + o[10] - o[19],
                               o[6] * e[0] + o[7] * e[1] + o[8] * e[2] + o[11] - o[20],
                               o[0] * px + o[1] * py + o[2] * pz + o[9] - o[18],
                               o[3] * px + o[4] * py + o[5] * pz + o[10] - o[19],
                               o[6] * px + o[7] * py + o[8] * pz + o[11] - o[20], o[15], o[16], o[17])


@njit(cache=True, nogil=True, inline="always")
def _path_length(world_step, px, py, pz):
    """Length (metres) of a box point's world path: the sum over tau of ``|world_step[tau] @ p|``."""
    path = 0.0
    for tau in range(world_step.shape[0]):
        m = world_step[tau]
        sx = m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + m[0, 3]
        sy = m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + m[1, 3]
        sz = m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3]
        path += np.sqrt(sx * sx + sy * sy + sz * sz)
    return path


@njit(cache=True, nogil=True)
def path_speeds(points_box, world_step, duration_s, speeds):
    """``speeds[i]`` (float64 [N], m/s): the world path length of box point ``points_box[i]``
    (float64 [N, 3]) under ``world_step`` (float64 [T-1, 4, 4], ``world_from_box[tau+1] -
    world_from_box[tau]``) over ``duration_s``; the speed :func:`screen_points` computes."""
    for i in range(points_box.shape[0]):
        speeds[i] = _path_length(world_step, points_box[i, 0], points_box[i, 1], points_box[i, 2]) / duration_s


@njit(cache=True, nogil=True)
def screen_points(points_box, camera_from_box, shift_camera, world_step, camera, depth_maps,
                  occlusion_ratio, own, own_points, others, duration_s, box_speed_mps, max_speed_deviation_mps,
                  status, speeds, grow_px=0):
    """Which candidates survive, and their speeds; returns the number kept.

    Args:
        points_box: float64 [N, 3], metres, box frame.
        camera_from_box: float64 [T, 4, 4] (camera at the image pose of each clip frame).
        shift_camera: float64 [T, 3], metres, object motion between frame and image time.
        world_step: float64 [T-1, 4, 4], ``world_from_box[tau+1] - world_from_box[tau]``.
        camera: float64 [11], :func:`camera_parameters`.
        depth_maps: float32 [T, H, W], z-depth, metres, 0 = unknown.
        occlusion_ratio: occluded iff ``0 < surface < occlusion_ratio * z``.
        own: float64 [T, 13] or [0, 13]: the object's own box for the depth test (:func:`_visible`),
            ``drivetrack.visibility.own_box_parameters``; own_points: bool [N] (any length when
            ``own`` is [0, 7]), the points it applies to (reliable normals).
        others: float64 [T, K, 21], the other labelled objects' boxes (:func:`_visible`).
        duration_s: clip duration; the speed is NaN when T < 2 or this is <= 0.
        box_speed_mps, max_speed_deviation_mps: the speed filter drops a visible point whose
            ``|speed - box_speed_mps|`` is not <= the deviation; a NaN of either disables it.
        status: int8 [N] output, ``KEPT``, ``DROPPED_INVISIBLE`` or ``DROPPED_SPEED``.
        speeds: float64 [N] output, m/s, mean world-frame speed over the clip.
        grow_px: the depth look-up's growth (pixels; 0: the max-of-4, :func:`_max4`).
    """
    n = points_box.shape[0]
    t_count = camera_from_box.shape[0]
    f_u, f_v, c_u, c_v, k1, k2, k3, p1, p2 = (camera[0], camera[1], camera[2], camera[3], camera[4],
                                              camera[5], camera[6], camera[7], camera[8])
    height, width = depth_maps.shape[1], depth_maps.shape[2]
    use_speed_filter = not (np.isnan(box_speed_mps) or np.isnan(max_speed_deviation_mps))
    kept = 0
    for i in range(n):
        px, py, pz = points_box[i, 0], points_box[i, 1], points_box[i, 2]
        if t_count > 1 and duration_s > 0:
            speeds[i] = _path_length(world_step, px, py, pz) / duration_s
        else:
            speeds[i] = np.nan
        seen = False
        for tau in range(t_count):
            m = camera_from_box[tau]
            x = m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + m[0, 3] + shift_camera[tau, 0]
            y = m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + m[1, 3] + shift_camera[tau, 1]
            z = m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3] + shift_camera[tau, 2]
            pix_x, pix_y, valid = _pixel(x, y, z, f_u, f_v, c_u, c_v, k1, k2, k3, p1, p2)
            if _visible(depth_maps, tau, height, width, pix_x, pix_y, x, valid, occlusion_ratio, own,
                        own.shape[0] > 0 and own_points[i], others, px, py, pz, grow_px):
                seen = True
                break
        if not seen:
            status[i] = DROPPED_INVISIBLE
        elif use_speed_filter and not (abs(speeds[i] - box_speed_mps) <= max_speed_deviation_mps):
            status[i] = DROPPED_SPEED
        else:
            status[i] = KEPT
            kept += 1
    return kept


#: Points per block of :func:`fill_tracks`: frames are the middle loop so that one depth map is
#: read by a block's (nearby) points at a time; the block's outputs stay in cache.
_BLOCK = 256


@njit(cache=True, nogil=True)
def fill_tracks(points_box, order, camera_from_box, shift_camera, vehicle_from_box, camera, depth_maps,
                occlusion_ratio, own, own_points, others, tracks, visibles, points3d, with_points3d=True, grow_px=0):
    """Tracks of the points ``points_box`` float64 [K, 3] (box frame), written in [K, T] order.

    Outputs (filled in place): ``tracks`` float32 [K, T, 2] pixels (invalid projections hold the
    nearest frame's valid position, ties to the earlier; all NaN when no frame is valid),
    ``visibles`` bool [K, T], ``points3d`` float32 [K, T, 3] metres in the vehicle frame of each
    clip frame. ``order`` int64 [K] is the order in which points are processed (a permutation of
    ``range(K)``; output rows stay those of ``points_box``): points close in the image in turn
    read the depth maps' memory in turn. LiDAR order is already coherent (measured: sorting by
    image strips gained ~2% and cost more than that), so the track stage passes ``arange(K)``.
    Other arguments as :func:`screen_points` (``grow_px`` too). ``with_points3d=False`` leaves
    ``points3d`` untouched (the job needs only ``visibles``; the writers recompute ``points3d``).
    """
    n = points_box.shape[0]
    t_count = camera_from_box.shape[0]
    valid_at = np.zeros((_BLOCK, t_count), dtype=np.bool_)
    before = np.empty(t_count, dtype=np.int64)
    scratch = np.empty((_BLOCK, 3))                  # pixel x, pixel y, z-depth (NaN: invalid)
    f_u, f_v, c_u, c_v, k1, k2, k3, p1, p2 = (camera[0], camera[1], camera[2], camera[3], camera[4],
                                              camera[5], camera[6], camera[7], camera[8])
    height, width = depth_maps.shape[1], depth_maps.shape[2]
    for block in range(0, n, _BLOCK):
        stop = min(block + _BLOCK, n)
        for tau in range(t_count):
            c = camera_from_box[tau]
            s0, s1, s2 = shift_camera[tau, 0], shift_camera[tau, 1], shift_camera[tau, 2]
            c00, c01, c02, c03 = c[0, 0], c[0, 1], c[0, 2], c[0, 3] + s0
            c10, c11, c12, c13 = c[1, 0], c[1, 1], c[1, 2], c[1, 3] + s1
            c20, c21, c22, c23 = c[2, 0], c[2, 1], c[2, 2], c[2, 3] + s2
            for j in range(block, stop):
                i = order[j]
                px, py, pz = points_box[i, 0], points_box[i, 1], points_box[i, 2]
                x = c00 * px + c01 * py + c02 * pz + c03
                y = c10 * px + c11 * py + c12 * pz + c13
                z = c20 * px + c21 * py + c22 * pz + c23
                pix_x, pix_y, valid = _pixel(x, y, z, f_u, f_v, c_u, c_v, k1, k2, k3, p1, p2)
                fx, fy = np.float32(pix_x), np.float32(pix_y)
                tracks[i, tau, 0] = fx
                tracks[i, tau, 1] = fy
                # finite as stored (float32), like the numpy path's test on the float32 tracks
                valid_at[j - block, tau] = valid and np.isfinite(fx) and np.isfinite(fy)
                scratch[j - block, 0] = pix_x
                scratch[j - block, 1] = pix_y
                scratch[j - block, 2] = x if valid else np.nan
            # the depth look-ups in a loop of their own: little else to do, many loads in flight
            for j in range(block, stop):
                x = scratch[j - block, 2]
                i = order[j]
                visibles[i, tau] = _visible(depth_maps, tau, height, width, scratch[j - block, 0],
                                            scratch[j - block, 1], x, not np.isnan(x), occlusion_ratio, own,
                                            own.shape[0] > 0 and own_points[i], others,
                                            points_box[i, 0], points_box[i, 1], points_box[i, 2], grow_px)
        for j in range(block, stop):
            _hold_nearest_valid(tracks[order[j]], valid_at[j - block], before)
    # points3d in point order: streaming writes (scattered ones cost more than the arithmetic)
    for i in range(n if with_points3d else 0):
        px, py, pz = points_box[i, 0], points_box[i, 1], points_box[i, 2]
        for tau in range(t_count):
            m = vehicle_from_box[tau]
            points3d[i, tau, 0] = m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + m[0, 3]
            points3d[i, tau, 1] = m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + m[1, 3]
            points3d[i, tau, 2] = m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3]


@njit(cache=True, nogil=True)
def depth_margins(points_box, camera_from_box, shift_camera, camera, depth_maps, occlusion_ratio, own, own_points,
                  others, unit_m, margins, grow_px=0):
    """The occlusion margin of each point-frame: the depth-map test's, unless ``margins`` holds a
    smaller one.

    ``margins`` float32 [K, T] holds on entry the smallest margin of the other tests (+inf: none)
    and on return the smallest of that and the depth-map test's ``(surface - occlusion_ratio * z) /
    unit_m`` with the max-of-4 surface of :func:`_visible` (negative iff the map hides the point),
    which is +inf where the map knows no surface there or the surface is the object's own or
    another labelled object's spread (:func:`_surface_is_theirs`, asked only where the map's
    margin is the smaller: it cannot hide the point); NaN where the projection is invalid or
    outside the image. With ``unit_m`` 0 only the sign is left (+-inf, 0 stays 0). Other arguments
    as :func:`screen_points` (``points_box`` float64 [K, 3] and ``own_points`` bool [K] of these
    points; ``grow_px`` too). ``core._occlusion_margins`` computes the same in numpy.
    """
    n = points_box.shape[0]
    t_count = camera_from_box.shape[0]
    f_u, f_v, c_u, c_v, k1, k2, k3, p1, p2 = (camera[0], camera[1], camera[2], camera[3], camera[4],
                                              camera[5], camera[6], camera[7], camera[8])
    height, width = depth_maps.shape[1], depth_maps.shape[2]
    unit = np.float32(unit_m)
    for i in range(n):
        px, py, pz = points_box[i, 0], points_box[i, 1], points_box[i, 2]
        own_point = own.shape[0] > 0 and own_points[i]
        for tau in range(t_count):
            m = camera_from_box[tau]
            x = m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + m[0, 3] + shift_camera[tau, 0]
            y = m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + m[1, 3] + shift_camera[tau, 1]
            z = m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3] + shift_camera[tau, 2]
            pix_x, pix_y, valid = _pixel(x, y, z, f_u, f_v, c_u, c_v, k1, k2, k3, p1, p2)
            best = _max4(depth_maps, tau, height, width, pix_x, pix_y, grow_px) if valid else np.float32(-1.0)
            if best < 0:
                margins[i, tau] = np.nan
                continue
            if not best > 0:
                continue
            margin = np.float32(best - occlusion_ratio * x)
            if unit > 0:
                margin = margin / unit
            elif margin != 0:
                margin = np.float32(np.inf) if margin > 0 else np.float32(-np.inf)
            if margin < margins[i, tau] and not _surface_is_theirs(tau, best / x, own, own_point, others, px, py, pz):
                margins[i, tau] = margin


@njit(cache=True, nogil=True)
def fill_positions(points_box, camera_from_box, shift_camera, vehicle_from_box, camera, tracks, points3d,
                   with_tracks=True, with_points3d=True):
    """``tracks`` float32 [K, T, 2] and ``points3d`` float32 [K, T, 3] exactly as :func:`fill_tracks`.

    No depth maps and no visibility: what a writer needs once ``visibles`` are known. Arguments
    as :func:`fill_tracks` (points processed in their order); ``with_tracks`` /
    ``with_points3d`` False leave that output untouched (it may then be any float32 array of
    the right rank, e.g. empty).
    """
    n = points_box.shape[0]
    t_count = camera_from_box.shape[0]
    valid_at = np.zeros(t_count, dtype=np.bool_)
    before = np.empty(t_count, dtype=np.int64)
    f_u, f_v, c_u, c_v, k1, k2, k3, p1, p2 = (camera[0], camera[1], camera[2], camera[3], camera[4],
                                              camera[5], camera[6], camera[7], camera[8])
    for i in range(n):
        px, py, pz = points_box[i, 0], points_box[i, 1], points_box[i, 2]
        for tau in range(t_count if with_tracks else 0):
            c = camera_from_box[tau]
            # the same operations in the same order as fill_tracks (shift added to the translation)
            c03 = c[0, 3] + shift_camera[tau, 0]
            c13 = c[1, 3] + shift_camera[tau, 1]
            c23 = c[2, 3] + shift_camera[tau, 2]
            x = c[0, 0] * px + c[0, 1] * py + c[0, 2] * pz + c03
            y = c[1, 0] * px + c[1, 1] * py + c[1, 2] * pz + c13
            z = c[2, 0] * px + c[2, 1] * py + c[2, 2] * pz + c23
            pix_x, pix_y, valid = _pixel(x, y, z, f_u, f_v, c_u, c_v, k1, k2, k3, p1, p2)
            fx, fy = np.float32(pix_x), np.float32(pix_y)
            tracks[i, tau, 0] = fx
            tracks[i, tau, 1] = fy
            valid_at[tau] = valid and np.isfinite(fx) and np.isfinite(fy)
        if with_tracks:
            _hold_nearest_valid(tracks[i], valid_at, before)
        for tau in range(t_count if with_points3d else 0):
            m = vehicle_from_box[tau]
            points3d[i, tau, 0] = m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + m[0, 3]
            points3d[i, tau, 1] = m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + m[1, 3]
            points3d[i, tau, 2] = m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3]


@njit(cache=True, nogil=True)
def fill_points3d_frames(points_box, vehicle_from_box, points3d):
    """Time-major ``points3d`` float32 [F, K, 3] of the frames of ``vehicle_from_box`` [F, 4, 4].

    ``points3d[f, i]`` equals :func:`fill_tracks`' ``points3d[i, f]`` for the same transforms
    (pass a slice of the clip's transforms for a range of frames).
    """
    n = points_box.shape[0]
    for f in range(vehicle_from_box.shape[0]):
        m = vehicle_from_box[f]
        for i in range(n):
            px, py, pz = points_box[i, 0], points_box[i, 1], points_box[i, 2]
            points3d[f, i, 0] = m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + m[0, 3]
            points3d[f, i, 1] = m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + m[1, 3]
            points3d[f, i, 2] = m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3]


@njit(cache=True, nogil=True)
def summarise_tracks(tracks, visibles, source_frames, width, height, query_pixels):
    """Query pixels and sanity counts of a chunk of tracks (as ``core._summarise_tracks``).

    ``query_pixels`` float32 [K, 2] (output) takes ``tracks[i, f]`` at the TAPVid-3D query
    frame ``f``: ``source_frames[i]`` when visible there, else the first visible frame (0 when
    none). Returns int64 [2]: visible point-frames whose position is not finite, and those
    finite but outside ``[0, width) x [0, height)``.
    """
    counts = np.zeros(2, dtype=np.int64)
    for i in range(tracks.shape[0]):
        source = source_frames[i]
        frame = source if visibles[i, source] else -1
        for tau in range(tracks.shape[1]):
            if visibles[i, tau]:
                if frame < 0:
                    frame = tau
                x, y = tracks[i, tau, 0], tracks[i, tau, 1]
                if not (np.isfinite(x) and np.isfinite(y)):
                    counts[0] += 1
                elif not (x >= 0 and x < width and y >= 0 and y < height):
                    counts[1] += 1
        frame = max(frame, 0)
        query_pixels[i, 0] = tracks[i, frame, 0]
        query_pixels[i, 1] = tracks[i, frame, 1]
    return counts


@njit(cache=True, nogil=True)
def _hold_nearest_valid(track, valid_at, before):
    """Invalid frames of ``track`` float32 [T, 2] take the nearest valid frame (ties: earlier).

    As ``core.fill_invalid_positions``; all NaN when no frame is valid. ``before`` is scratch.
    """
    t_count = track.shape[0]
    last = -1
    for tau in range(t_count):
        if valid_at[tau]:
            last = tau
        before[tau] = last
    if last == t_count - 1 and before[0] == 0:
        all_valid = True
        for tau in range(t_count):
            all_valid &= valid_at[tau]
        if all_valid:
            return
    following = t_count
    for tau in range(t_count - 1, -1, -1):
        if valid_at[tau]:
            following = tau
            continue
        previous = before[tau]
        if previous < 0 or (following < t_count and following - tau < tau - previous):
            source = following
        else:
            source = previous
        if 0 <= source < t_count:
            track[tau, 0] = track[source, 0]
            track[tau, 1] = track[source, 1]
        else:
            track[tau, 0] = np.nan
            track[tau, 1] = np.nan


@njit(cache=True, nogil=True)
def points_box_at(rows, tau, points_world, centre, velocity, acceleration, cos_roll, sin_roll, cos_pitch, sin_pitch,
                  cos_yaw, sin_yaw, out):
    """``drivetrack.tracks.trajectory.points_box_at`` after its angles: world points
    ``points_world`` float64 [N, 3] into the box frame of box row ``rows`` (int64 [N])'s object
    ``tau`` (float64 [N], s) after its sample, its centre ``centre + tau v + tau^2 a / 2``
    (``centre``, ``velocity``, ``acceleration`` float64 [K, 3], the trajectory's) and its rotation
    ``Rz(yaw) Ry(pitch) Rx(roll)`` from the cosines and sines float64 [N] of its angles then:
    ``out`` float64 [N, 3] = R^T (p - centre). The float64 arithmetic of ``BoxTrajectory.motion``,
    ``geometry.rotation_from_rpy`` and the einsum, in their order (bit-identical results) without
    their [N, 4, 4] temporaries."""
    for i in range(rows.shape[0]):
        k = rows[i]
        t = tau[i]
        cr, sr, cp, sp, cy, sy = cos_roll[i], sin_roll[i], cos_pitch[i], sin_pitch[i], cos_yaw[i], sin_yaw[i]
        rel0 = points_world[i, 0] - (centre[k, 0] + t * velocity[k, 0] + 0.5 * t * t * acceleration[k, 0])
        rel1 = points_world[i, 1] - (centre[k, 1] + t * velocity[k, 1] + 0.5 * t * t * acceleration[k, 1])
        rel2 = points_world[i, 2] - (centre[k, 2] + t * velocity[k, 2] + 0.5 * t * t * acceleration[k, 2])
        r00, r01, r02 = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
        r10, r11, r12 = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
        r20, r21, r22 = -sp, cp * sr, cp * cr
        out[i, 0] = r00 * rel0 + r10 * rel1 + r20 * rel2
        out[i, 1] = r01 * rel0 + r11 * rel1 + r21 * rel2
        out[i, 2] = r02 * rel0 + r12 * rel1 + r22 * rel2
