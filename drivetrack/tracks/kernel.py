"""Fused numba kernel of the track stage's inner loop (global-shutter projection).

One pass over (point, frame) computes what :func:`drivetrack.tracks.core.run_object_job`'s numpy
path computes with [T, n] temporaries: the camera-frame point ``camera_from_box[tau] @ p +
shift_camera[tau]``, its Brown-Conrady projection (``CameraModel.pixels_from_camera``: valid iff
x > 1e-6 and the distortion factor lies in [0.8, 1.2]), the inside-image test, occlusion against
the clip's depth maps with the max-of-4 look-up (``drivetrack.depth.lookup_max4``), the
vehicle-frame point ``vehicle_from_box[tau] @ p`` and the world-path speed. Math is float64; the
outputs are written directly in [N, T] order.

Two passes keep memory at what is kept: :func:`screen_points` decides for every candidate whether
it survives (visible at some frame, and the optional speed filter) and computes its speed; it stops
at a point's first visible frame. :func:`fill_tracks` then materialises only the kept points,
holding the nearest valid position where the projection is invalid (as
``core.fill_invalid_positions``).

numba compiles on first use and caches the machine code on disk (``cache=True``), so a process
pays the compile once (or never, with a warm cache).
"""
from __future__ import annotations

import numpy as np

from drivetrack.geometry import MAX_TRUSTED_DISTORTION, MIN_TRUSTED_DISTORTION

__all__ = ["NUMBA_AVAILABLE", "camera_parameters", "screen_points", "fill_tracks"]

try:  # numba is a declared dependency; the numpy path remains when it cannot be imported
    from numba import njit
    NUMBA_AVAILABLE = True
except ImportError:  # pragma: no cover - exercised only in environments without numba
    NUMBA_AVAILABLE = False

    def njit(*args, **kwargs):
        def wrap(function):
            return function
        return wrap

#: Status codes of :func:`screen_points`.
KEPT, DROPPED_INVISIBLE, DROPPED_SPEED = 0, 1, 2


def camera_parameters(model) -> np.ndarray:
    """float64 [11]: (f_u, f_v, c_u, c_v, k1, k2, k3, p1, p2, width, height) of a CameraModel."""
    return np.array([model.f_u, model.f_v, model.c_u, model.c_v, model.k1, model.k2, model.k3,
                     model.p1, model.p2, model.width, model.height], dtype=np.float64)


@njit(cache=True, nogil=True)
def _project(camera_from_box, shift_camera, tau, px, py, pz, camera):
    """(pixel x, pixel y, z-depth, valid) of box-frame point (px, py, pz) at clip frame tau."""
    m = camera_from_box[tau]
    x = m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + m[0, 3] + shift_camera[tau, 0]
    y = m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + m[1, 3] + shift_camera[tau, 1]
    z = m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3] + shift_camera[tau, 2]
    if not x > 1e-6:
        return np.nan, np.nan, x, False
    u = -y / x
    v = -z / x
    k1, k2, k3, p1, p2 = camera[4], camera[5], camera[6], camera[7], camera[8]
    r2 = u * u + v * v
    d = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    if not (d >= MIN_TRUSTED_DISTORTION and d <= MAX_TRUSTED_DISTORTION):
        return np.nan, np.nan, x, False
    u_d = u * d + 2.0 * p1 * u * v + p2 * (r2 + 2.0 * u * u)
    v_d = v * d + p1 * (r2 + 2.0 * v * v) + 2.0 * p2 * u * v
    return camera[0] * u_d + camera[2], camera[1] * v_d + camera[3], x, True


@njit(cache=True, nogil=True)
def _visible(depth_map, pix_x, pix_y, x, valid, occlusion_ratio):
    """Inside the image and not behind the max-of-4 surface of ``depth_map`` float32 [H, W]."""
    if not valid:
        return False
    height, width = depth_map.shape
    if not (pix_x >= 0.0 and pix_x < width and pix_y >= 0.0 and pix_y < height):
        return False
    cx = pix_x - 0.5
    cy = pix_y - 0.5
    c0, c1 = np.floor(cx), np.ceil(cx)
    r0, r1 = np.floor(cy), np.ceil(cy)
    best = np.float32(0.0)
    for col in (c0, c1):
        if col < 0 or col >= width:
            continue
        for row in (r0, r1):
            if row < 0 or row >= height:
                continue
            value = depth_map[int(row), int(col)]
            if value > best:
                best = value
    return not (best > 0 and best < occlusion_ratio * x)


@njit(cache=True, nogil=True)
def screen_points(points_box, camera_from_box, shift_camera, world_step, camera, depth_maps,
                  occlusion_ratio, duration_s, box_speed_mps, max_speed_deviation_mps,
                  status, speeds):
    """Which candidates survive, and their speeds; returns the number kept.

    Args:
        points_box: float64 [N, 3], metres, box frame.
        camera_from_box: float64 [T, 4, 4] (camera at the image pose of each clip frame).
        shift_camera: float64 [T, 3], metres, object motion between frame and image time.
        world_step: float64 [T-1, 4, 4], ``world_from_box[tau+1] - world_from_box[tau]``.
        camera: float64 [11], :func:`camera_parameters`.
        depth_maps: float32 [T, H, W], z-depth, metres, 0 = unknown.
        occlusion_ratio: occluded iff ``0 < surface < occlusion_ratio * z``.
        duration_s: clip duration; the speed is NaN when T < 2 or this is <= 0.
        box_speed_mps, max_speed_deviation_mps: the speed filter drops a visible point whose
            ``|speed - box_speed_mps|`` is not <= the deviation; a NaN of either disables it.
        status: int8 [N] output, ``KEPT``, ``DROPPED_INVISIBLE`` or ``DROPPED_SPEED``.
        speeds: float64 [N] output, m/s, mean world-frame speed over the clip.
    """
    n = points_box.shape[0]
    t_count = camera_from_box.shape[0]
    use_speed_filter = not (np.isnan(box_speed_mps) or np.isnan(max_speed_deviation_mps))
    kept = 0
    for i in range(n):
        px, py, pz = points_box[i, 0], points_box[i, 1], points_box[i, 2]
        if t_count > 1 and duration_s > 0:
            path = 0.0
            for tau in range(t_count - 1):
                m = world_step[tau]
                sx = m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + m[0, 3]
                sy = m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + m[1, 3]
                sz = m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3]
                path += np.sqrt(sx * sx + sy * sy + sz * sz)
            speeds[i] = path / duration_s
        else:
            speeds[i] = np.nan
        seen = False
        for tau in range(t_count):
            pix_x, pix_y, x, valid = _project(camera_from_box, shift_camera, tau, px, py, pz, camera)
            if _visible(depth_maps[tau], pix_x, pix_y, x, valid, occlusion_ratio):
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


@njit(cache=True, nogil=True)
def fill_tracks(points_box, camera_from_box, shift_camera, vehicle_from_box, camera, depth_maps,
                occlusion_ratio, tracks, visibles, points3d):
    """Tracks of the points ``points_box`` float64 [K, 3] (box frame), written in [K, T] order.

    Outputs (filled in place): ``tracks`` float32 [K, T, 2] pixels (invalid projections hold the
    nearest frame's valid position, ties to the earlier; all NaN when no frame is valid),
    ``visibles`` bool [K, T], ``points3d`` float32 [K, T, 3] metres in the vehicle frame of each
    clip frame. Other arguments as :func:`screen_points`.
    """
    n = points_box.shape[0]
    t_count = camera_from_box.shape[0]
    pixel_x = np.empty(t_count)
    pixel_y = np.empty(t_count)
    valid_at = np.zeros(t_count, dtype=np.bool_)
    before = np.empty(t_count, dtype=np.int64)
    for i in range(n):
        px, py, pz = points_box[i, 0], points_box[i, 1], points_box[i, 2]
        any_invalid = False
        for tau in range(t_count):
            pix_x, pix_y, x, valid = _project(camera_from_box, shift_camera, tau, px, py, pz, camera)
            pixel_x[tau] = pix_x
            pixel_y[tau] = pix_y
            # finite as stored (float32), like the numpy path's test on the float32 tracks
            valid_at[tau] = valid and np.isfinite(np.float32(pix_x)) and np.isfinite(np.float32(pix_y))
            any_invalid |= not valid_at[tau]
            visibles[i, tau] = _visible(depth_maps[tau], pix_x, pix_y, x, valid, occlusion_ratio)
            m = vehicle_from_box[tau]
            points3d[i, tau, 0] = m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + m[0, 3]
            points3d[i, tau, 1] = m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + m[1, 3]
            points3d[i, tau, 2] = m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3]
        if any_invalid:
            # nearest valid frame in time (ties: the earlier), as core.fill_invalid_positions
            last = -1
            for tau in range(t_count):
                if valid_at[tau]:
                    last = tau
                before[tau] = last
            following = t_count
            for tau in range(t_count - 1, -1, -1):
                if valid_at[tau]:
                    following = tau
                    source = tau
                else:
                    previous = before[tau]
                    if previous < 0 or (following < t_count and following - tau < tau - previous):
                        source = following
                    else:
                        source = previous
                if 0 <= source < t_count:
                    tracks[i, tau, 0] = pixel_x[source]
                    tracks[i, tau, 1] = pixel_y[source]
                else:
                    tracks[i, tau, 0] = np.nan
                    tracks[i, tau, 1] = np.nan
            continue
        for tau in range(t_count):
            tracks[i, tau, 0] = pixel_x[tau]
            tracks[i, tau, 1] = pixel_y[tau]
