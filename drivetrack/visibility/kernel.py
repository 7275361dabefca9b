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

__all__ = ["shifted_neighbourhoods", "project_in_window", "project_points", "facing_test"]


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
    min_cos = np.cos(np.radians(max_angle_deg))
    for tau in range(centres_box.shape[0]):
        ex, ey, ez = centres_box[tau, 0], centres_box[tau, 1], centres_box[tau, 2]
        for i in range(points_box.shape[0]):
            if not reliable[i]:
                facing[tau, i] = True
                margin_deg[tau, i] = np.inf
                continue
            dx, dy, dz = ex - points_box[i, 0], ey - points_box[i, 1], ez - points_box[i, 2]
            cosine = ((dx * normal[i, 0] + dy * normal[i, 1] + dz * normal[i, 2])
                      / max(np.sqrt(dx * dx + dy * dy + dz * dz), 1e-9))
            facing[tau, i] = cosine > min_cos
            margin_deg[tau, i] = max_angle_deg - np.degrees(np.arccos(min(max(cosine, -1.0), 1.0)))
