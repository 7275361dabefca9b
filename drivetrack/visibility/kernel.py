"""numba kernels of the visibility stage: the back-face normals
(:func:`drivetrack.visibility.facing.cloud_normals`) and the projection of an occluder's surfels
into an image window (:func:`project_in_window`), the tracked points' projection for the
z-buffer test (:func:`project_points`) and the back-face test (:func:`facing_test`).

Shapes: m cloud points, k neighbours; metres, box frame.
"""
from __future__ import annotations

import numpy as np

from drivetrack.camera.kernel import pixel_from_camera_point as _pixel
from drivetrack.numba_compat import njit

__all__ = ["shifted_neighbourhoods", "project_in_window", "project_points", "facing_test", "facing_test_rows",
           "zbuffer_points",
           "zbuffer_near", "splat_groups", "scatter_min", "merge_spread", "merge_nearer", "zbuffer_on", "zbuffer_decide"]


@njit(cache=True, nogil=True)
def _shifted_kernel(cloud, index, normal, centroid, eigen, tolerance_m, sigmas, min_cos, choice):
    m, k = index.shape
    for i in range(m):
        best, best_variation = index[i, 0], np.inf
        for a in range(k):
            j = index[i, a]
            if a > 0:
                # its plane must pass through the point, within the tolerance ...
                off = abs(normal[j, 0] * (cloud[i, 0] - centroid[j, 0]) + normal[j, 1] * (cloud[i, 1] - centroid[j, 1])
                          + normal[j, 2] * (cloud[i, 2] - centroid[j, 2]))
                if off > max(tolerance_m, sigmas * np.sqrt(max(eigen[j, 0], 0.0))):
                    continue
                # ... and lean the way the point's own neighbourhood does
                cos = normal[j, 0] * normal[i, 0] + normal[j, 1] * normal[i, 1] + normal[j, 2] * normal[i, 2]
                if abs(cos) < min_cos:
                    continue
            variation = eigen[j, 0] / max(eigen[j, 0] + eigen[j, 1] + eigen[j, 2], 1e-300)
            if variation < best_variation:
                best, best_variation = j, variation
        choice[i] = best


def shifted_neighbourhoods(cloud: np.ndarray, index: np.ndarray, normal: np.ndarray, centroid: np.ndarray,
                           eigen: np.ndarray, tolerance_m: float, sigmas: float, max_tilt_deg: float) -> np.ndarray:
    """int64 [m]: for each point of ``cloud`` float64 [m, 3] the neighbour (an index into
    ``cloud``) whose neighbourhood's plane to take (see
    :func:`drivetrack.visibility.facing.cloud_normals`).

    ``index`` int [m, k]: each point's k nearest (itself first); ``normal``, ``centroid`` float64
    [m, 3] and ``eigen`` float64 [m, 3] (ascending, square metres): each neighbourhood's plane
    (``drivetrack.refine.kernel.plane_fits``). Among the neighbourhoods of a point's neighbours,
    its own always and the others when their plane passes within ``max(tolerance_m, sigmas *
    sqrt(l1))`` of the point and their normal lies within ``max_tilt_deg`` of the point's own
    neighbourhood's (either sign), the flattest (smallest ``l1 / (l1 + l2 + l3)``) wins.
    """
    choice = np.empty(cloud.shape[0], dtype=np.int64)
    _shifted_kernel(np.ascontiguousarray(cloud, dtype=np.float64), np.ascontiguousarray(index, dtype=np.int64),
                    np.ascontiguousarray(normal, dtype=np.float64), np.ascontiguousarray(centroid, dtype=np.float64),
                    np.ascontiguousarray(eigen, dtype=np.float64), float(tolerance_m), float(sigmas),
                    float(np.cos(np.radians(max_tilt_deg))), choice)
    return choice


@njit(cache=True, nogil=True)
def project_in_window(points_box, camera_from_box, camera, x_lo, x_hi, y_lo, y_hi, pixels, depth, index):
    """Projects box-frame points and keeps those that land in a window of the image.

    ``points_box`` float64 [m, 3] (metres, box frame) through ``camera_from_box`` float64 [4, 4]
    (with any shift already in its translation) to the camera ``camera`` float64 [11]
    (``drivetrack.camera.kernel.camera_parameters``). A point is kept when its projection is valid
    (``CameraModel.pixels_from_camera``: in front, trusted distortion) with a finite pixel (x, y)
    in ``[x_lo, x_hi] x [y_lo, y_hi]`` (pixels; infinite bounds: anywhere). The first ``s`` rows of
    ``pixels`` float64 [m, 2], ``depth`` float64 [m] (z-depth, metres) and ``index`` int64 [m]
    (the kept points' rows, in order) are written. Returns ``(s, valid)``: how many were kept,
    and how many projected validly anywhere.
    """
    f_u, f_v, c_u, c_v, k1, k2, k3, p1, p2 = (camera[0], camera[1], camera[2], camera[3], camera[4],
                                              camera[5], camera[6], camera[7], camera[8])
    m = camera_from_box
    kept = 0
    valid_count = 0
    for i in range(points_box.shape[0]):
        px, py, pz = points_box[i, 0], points_box[i, 1], points_box[i, 2]
        x = m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + m[0, 3]
        y = m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + m[1, 3]
        z = m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3]
        pix_x, pix_y, valid = _pixel(x, y, z, f_u, f_v, c_u, c_v, k1, k2, k3, p1, p2)
        if valid:
            valid_count += 1
        if not (valid and pix_x >= x_lo and pix_x <= x_hi and pix_y >= y_lo and pix_y <= y_hi):
            continue                                  # NaN pixels fail every comparison
        pixels[kept, 0] = pix_x
        pixels[kept, 1] = pix_y
        depth[kept] = x
        index[kept] = i
        kept += 1
    return kept, valid_count


@njit(cache=True, nogil=True)
def project_points(points_box, camera_from_box, camera, pixels, depth, valid):
    """Projects box-frame points ``points_box`` float64 [n, 3] through ``camera_from_box`` float64
    [4, 4] (any shift in its translation) to the camera ``camera`` float64 [11], as
    ``CameraModel.pixels_from_camera``: fills ``pixels`` float64 [n, 2] (NaN where invalid),
    ``depth`` float64 [n] (the z-depth x, metres) and ``valid`` bool [n] (in front, trusted
    distortion)."""
    f_u, f_v, c_u, c_v, k1, k2, k3, p1, p2 = (camera[0], camera[1], camera[2], camera[3], camera[4],
                                              camera[5], camera[6], camera[7], camera[8])
    m = camera_from_box
    for i in range(points_box.shape[0]):
        px, py, pz = points_box[i, 0], points_box[i, 1], points_box[i, 2]
        x = m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + m[0, 3]
        y = m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + m[1, 3]
        z = m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3]
        pixels[i, 0], pixels[i, 1], valid[i] = _pixel(x, y, z, f_u, f_v, c_u, c_v, k1, k2, k3, p1, p2)
        depth[i] = x


@njit(cache=True, nogil=True)
def facing_test(points_box, normal, reliable, centres_box, max_angle_deg, facing, margin_deg):
    """The back-face test of ``drivetrack.visibility.facing.facing_test`` in one pass: fills
    ``facing`` bool [T, n] and ``margin_deg`` float32 [T, n] of points ``points_box`` float64
    [n, 3] with unit normals ``normal`` float64 [n, 3] (``reliable`` bool [n]) and camera centres
    ``centres_box`` float64 [T, 3] (box frame, metres)."""
    facing_test_rows(points_box, normal, reliable, centres_box, max_angle_deg,
                     np.arange(points_box.shape[0]), facing, margin_deg)


@njit(cache=True, nogil=True)
def facing_test_rows(points_box, normal, reliable, centres_box, max_angle_deg, rows, facing, margin_deg):
    """:func:`facing_test` of the points ``rows`` (int64 [k]) alone: their columns of ``facing``
    and ``margin_deg`` are written, the others left as they are."""
    min_cos = np.cos(np.radians(max_angle_deg))
    for tau in range(centres_box.shape[0]):
        ex, ey, ez = centres_box[tau, 0], centres_box[tau, 1], centres_box[tau, 2]
        for i in rows:
            if not reliable[i]:
                facing[tau, i] = True
                margin_deg[tau, i] = np.inf
                continue
            dx, dy, dz = ex - points_box[i, 0], ey - points_box[i, 1], ez - points_box[i, 2]
            cosine = ((dx * normal[i, 0] + dy * normal[i, 1] + dz * normal[i, 2])
                      / max(np.sqrt(dx * dx + dy * dy + dz * dz), 1e-9))
            facing[tau, i] = cosine > min_cos
            margin_deg[tau, i] = max_angle_deg - np.degrees(np.arccos(min(max(cosine, -1.0), 1.0)))


# ---- the z-buffer of the other objects (drivetrack.visibility.zbuffer): the per-pixel and
# per-return passes around OpenCV's morphology, which stays in zbuffer.py (its separable SIMD
# filters beat a numba loop: measured, docs/visibility.md "Cost") ----

@njit(cache=True, nogil=True)
def zbuffer_points(pixels, valid, scale, width, height, col, row, inside):
    """The tracked points' buffer pixels, as ``zbuffer.hidden_by_others`` takes them: ``pixels``
    float64 [n, 2] (image pixels) times ``scale``, a coordinate that is not finite (or a point not
    ``valid``) read as -1; fills ``col``, ``row`` int64 [n] (their floors) and ``inside`` bool [n]
    (valid and within ``width`` x ``height``). Returns ``(c_lo, c_hi, r_lo, r_hi)`` over the points
    inside (``c_hi`` -1: none)."""
    c_lo, c_hi, r_lo, r_hi = width, -1, height, -1
    for i in range(valid.shape[0]):
        x = pixels[i, 0] * scale
        y = pixels[i, 1] * scale
        if not (valid[i] and np.isfinite(x)):
            x = -1.0
        if not (valid[i] and np.isfinite(y)):
            y = -1.0
        fx, fy = np.floor(x), np.floor(y)
        inside[i] = valid[i] and fx >= 0 and fx < width and fy >= 0 and fy < height
        if inside[i]:
            col[i], row[i] = int(fx), int(fy)
            c_lo, c_hi = min(c_lo, col[i]), max(c_hi, col[i])
            r_lo, r_hi = min(r_lo, row[i]), max(r_hi, row[i])
        else:
            col[i], row[i] = -1, -1
    return c_lo, c_hi, r_lo, r_hi


@njit(cache=True, nogil=True)
def zbuffer_near(occ_pixels, scale, c0, c1, r0, r1, max_px, pixels_out):
    """int64 [s]: the returns ``occ_pixels`` float64 [m, 2] (image pixels) whose buffer pixel
    (times ``scale``, floored) lies within ``max_px`` of the window ``[c0, c1) x [r0, r1)``; their
    buffer pixels relative to the window (``pixels * scale - (c0, r0)``) in the first s rows of
    ``pixels_out`` float64 [m, 2]."""
    chosen = np.empty(occ_pixels.shape[0], np.int64)
    s = 0
    for j in range(occ_pixels.shape[0]):
        x = occ_pixels[j, 0] * scale
        y = occ_pixels[j, 1] * scale
        fx, fy = np.floor(x), np.floor(y)
        if fx >= c0 - max_px and fx < c1 + max_px and fy >= r0 - max_px and fy < r1 + max_px:
            chosen[s] = j
            pixels_out[s, 0] = x - c0
            pixels_out[s, 1] = y - r0
            s += 1
    return chosen[:s]


@njit(cache=True, nogil=True)
def splat_groups(pixels, depth, radius_m, width, height, focal, max_px, order, flat, starts):
    """Sorts returns ``pixels`` float64 [m, 2] (buffer pixels), ``depth``, ``radius_m`` float64 [m]
    by their footprint ``r = min(max_px, rint(focal * radius_m / depth))`` pixels, keeping those
    whose square reaches the ``width`` x ``height`` buffer (``zbuffer.nearest_depth``): fills
    ``order`` int64 [m] (the kept returns, by r, then in their own order), ``flat`` int64 [m] (each
    one's flat pixel in the buffer padded by ``max_px`` each side) and ``starts`` int64 [max_px + 2]
    (footprint r's returns are ``starts[r]:starts[r + 1]``); returns the count kept."""
    pad = max_px
    m = depth.shape[0]
    stride = width + 2 * pad
    size = np.empty(m, np.int64)
    where = np.empty(m, np.int64)
    counts = np.zeros(max_px + 2, np.int64)
    for j in range(m):
        c = int(np.floor(pixels[j, 0])) + pad
        r_ = int(np.floor(pixels[j, 1])) + pad
        r = int(min(np.rint(focal * radius_m[j] / depth[j]), max_px))
        if r_ >= pad - r and r_ < height + pad + r and c >= pad - r and c < width + pad + r:
            size[j] = r
            where[j] = r_ * stride + c
            counts[r + 1] += 1
        else:
            size[j] = -1
    for r in range(max_px + 1):
        counts[r + 1] += counts[r]
    starts[:] = counts
    fill = counts.copy()
    for j in range(m):
        r = size[j]
        if r >= 0:
            order[fill[r]] = j
            flat[fill[r]] = where[j]
            fill[r] += 1
    return counts[max_px + 1]


@njit(cache=True, nogil=True)
def scatter_min(centres, flat, order, depth, start, stop):
    """``np.minimum.at(centres.ravel(), flat[a], float32(depth[order[a]]))`` for a in [start, stop)."""
    out = centres.ravel()
    for a in range(start, stop):
        v = np.float32(depth[order[a]])
        if v < out[flat[a]]:
            out[flat[a]] = v


@njit(cache=True, nogil=True)
def merge_spread(buffer, footprint, spread, r):
    """Keeps the nearer of ``buffer`` and ``spread`` float32 [H, W] in ``buffer``; ``footprint``
    int8 [H, W] takes ``r`` where ``spread`` is nearer, and the larger of the two where equal and
    finite (``zbuffer.nearest_depth``'s footprint of the return holding each pixel's depth)."""
    h, w = buffer.shape
    for y in range(h):
        for x in range(w):
            v = spread[y, x]
            b = buffer[y, x]
            if v < b:
                buffer[y, x] = v
                footprint[y, x] = r
            elif v == b and np.isfinite(b) and footprint[y, x] < r:
                footprint[y, x] = r


@njit(cache=True, nogil=True)
def merge_nearer(window, footprint, own, own_footprint):
    """Where ``own`` float32 [H, W] is nearer than ``window`` (a view), both take ``own``'s depth and footprint."""
    h, w = own.shape
    for y in range(h):
        for x in range(w):
            if own[y, x] < window[y, x]:
                window[y, x] = own[y, x]
                footprint[y, x] = own_footprint[y, x]


@njit(cache=True, nogil=True)
def zbuffer_on(buffer, footprint, col, row, inside, depth, c0, r0, focal, radius_m, max_px, on, size):
    """The points whose own pixel holds an occluder's depth (``on`` int64 [n], first s), each
    one's window radius (``size`` int64 [n]): the larger of its own footprint ``min(max_px,
    rint(focal * radius_m / z))`` and the footprint at its pixel. Returns s."""
    s = 0
    spread = focal * radius_m
    for i in range(inside.shape[0]):
        if not inside[i]:
            continue
        y, x = row[i] - r0, col[i] - c0
        if not np.isfinite(buffer[y, x]):
            continue
        z = depth[i]
        r = int(min(np.rint(spread / (z if z > 0 else np.inf)), max_px))
        on[s] = i
        size[s] = max(r, int(footprint[y, x]))
        s += 1
    return s


@njit(cache=True, nogil=True)
def zbuffer_decide(covered, on, size, r, col, row, c0, r0, depth, abs_m, rel, hidden, margin):
    """For the points ``on`` whose window radius ``size`` is ``r``: the farthest buffer depth over
    the window (``covered``: the buffer's square maximum of radius r) against the threshold ``z -
    (abs_m + rel z)``: ``hidden`` bool [n], and ``margin`` float32 [n] where it is finite."""
    for a in range(on.shape[0]):
        if size[a] != r:
            continue
        i = on[a]
        far = np.float64(covered[row[i] - r0, col[i] - c0])
        z = depth[i]
        threshold = z - (abs_m + rel * z)
        hidden[i] = far < threshold
        if np.isfinite(far):
            margin[i] = np.float32(far - threshold)
