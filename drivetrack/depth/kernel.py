"""Fused numba kernel of the sparse depth maps: transform, project and keep the nearest return.

:func:`project_nearest` does in one pass over the returns what
:func:`drivetrack.depth.sparse_depth_from_points`' numpy reference does with [M, 3] temporaries
and ``np.minimum.at``: the optional move into the image's vehicle frame, the vehicle-to-camera
transform (both in the float64 operations and order of :func:`drivetrack.geometry.transform_points`),
the Brown-Conrady projection (:func:`drivetrack.camera.kernel.pixel_from_camera_point`), the
inside-image test and the per-pixel minimum of z-depth. The maps are bit-identical to the
reference (tests/test_depth.py). It releases the GIL, so cameras can run in threads.

Two more one-pass kernels replace full-image numpy passes of the completion step (each a few
temporaries of a 1920x1280 map): :func:`bound_in_place` (the blind-zone bounds) and
:func:`nearest_from_labels` (the nearest completer's read-out of the distance transform); both
give the numpy forms' maps bit for bit (tests/test_depth.py). :func:`blind_zone_in_place` does the
same for the sparse map's blind-zone bounds (:func:`drivetrack.depth.bound_blind_zone`).
"""
from __future__ import annotations

import numpy as np

from drivetrack.camera.kernel import pixel_from_camera_point
from drivetrack.numba_compat import NUMBA_AVAILABLE, njit

__all__ = ["NUMBA_AVAILABLE", "project_nearest", "bound_in_place", "nearest_from_labels", "blind_zone_in_place"]


@njit(cache=True, nogil=True)
def project_nearest(points, first, camera_from_vehicle, camera, subset, depth, depth_subset, skip):
    """Minimum z-depth per pixel of the returns that project into the image (in place).

    The maps hold float32 depths: rounding is monotonic, so the float32 of the float64 minimum is
    the minimum of the float32-rounded depths (what the reference computes).

    Args:
        points: float64 [M, 3], metres, in the frame ``first`` maps from.
        first: float64 [4, 4], applied before ``camera_from_vehicle`` (the image's vehicle frame
            from the return's); an empty [0, 0] array skips it.
        camera_from_vehicle: float64 [4, 4].
        camera: float64 [11], :func:`drivetrack.camera.kernel.camera_parameters`.
        subset: bool [M] or an empty [0] array (no subset map).
        depth: float32 [H * W], 0 where no return yet; takes the minimum z-depth (> 0) of the returns.
        depth_subset: float32 [H * W] (or [0] without subset): the same over the subset only.
        skip: bool [M] or an empty [0] array: returns left out (another pass places them elsewhere).
    """
    f_u, f_v, c_u, c_v = camera[0], camera[1], camera[2], camera[3]
    k1, k2, k3, p1, p2 = camera[4], camera[5], camera[6], camera[7], camera[8]
    width = camera[9]
    height = camera[10]
    columns = int(width)
    moved = first.shape[0] == 4
    with_subset = subset.shape[0] > 0
    with_skip = skip.shape[0] > 0
    c = camera_from_vehicle
    for m in range(points.shape[0]):
        if with_skip and skip[m]:
            continue
        x0 = points[m, 0]
        y0 = points[m, 1]
        z0 = points[m, 2]
        if moved:
            x1 = first[0, 0] * x0 + first[0, 1] * y0 + first[0, 2] * z0 + first[0, 3]
            y1 = first[1, 0] * x0 + first[1, 1] * y0 + first[1, 2] * z0 + first[1, 3]
            z1 = first[2, 0] * x0 + first[2, 1] * y0 + first[2, 2] * z0 + first[2, 3]
        else:
            x1 = x0
            y1 = y0
            z1 = z0
        x = c[0, 0] * x1 + c[0, 1] * y1 + c[0, 2] * z1 + c[0, 3]
        y = c[1, 0] * x1 + c[1, 1] * y1 + c[1, 2] * z1 + c[1, 3]
        z = c[2, 0] * x1 + c[2, 1] * y1 + c[2, 2] * z1 + c[2, 3]
        pix_x, pix_y, valid = pixel_from_camera_point(x, y, z, f_u, f_v, c_u, c_v, k1, k2, k3, p1, p2)
        if not valid:
            continue
        if not (pix_x >= 0.0 and pix_x < width and pix_y >= 0.0 and pix_y < height):
            continue
        index = int(np.floor(pix_y)) * columns + int(np.floor(pix_x))
        depth32 = np.float32(x)
        if depth[index] == 0 or depth32 < depth[index]:
            depth[index] = depth32
        if with_subset and subset[m]:
            if depth_subset[index] == 0 or depth32 < depth_subset[index]:
                depth_subset[index] = depth32


@njit(cache=True, nogil=True)
def bound_in_place(dense, sparse):
    """``drivetrack.depth.apply_depth_bounds`` in one pass, in place: where ``sparse[i] < 0`` (a
    blind-zone bound ``-b``), ``dense[i] = min(dense[i], b)`` if ``dense[i] > 0`` else ``b``.

    Args:
        dense: float32 [N], completed z-depth (0 = unknown), written.
        sparse: float32 [N], the sparse map it was completed from.
    """
    for i in range(dense.shape[0]):
        s = sparse[i]
        if s < 0:
            b = -s
            d = dense[i]
            dense[i] = (d if d < b else b) if d > 0 else b


@njit(cache=True, nogil=True)
def nearest_from_labels(labels, distance, depth_of_label, seed_index, width, reach_f64, far, low, dense):
    """The nearest completer's read-out of OpenCV's labelled distance transform, in one pass.

    ``dense[p] = depth_of_label[labels[p]]``, then 0 where the chamfer ``distance[p] > far``; where
    ``low <= distance[p] <= far`` the exact Euclidean distance from pixel ``p`` to its seed decides
    (0 when it is more than ``reach_f64``), as ``NearestCompleter._complete_opencv`` did with
    masks (``far`` / ``low`` float32 like the comparisons there).

    Args:
        labels: int32 [H, W], 1-based seed labels (raster order); distance: float32 [H, W].
        depth_of_label: float32 [S + 1] (label 0: 0); seed_index: int64 [S], flat index of each seed.
        width: W; reach_f64: float64 reach in pixels (inf: no limit, nothing reset).
        far, low: float32 thresholds (reach +- margin).
        dense: float32 [H, W], written.
    """
    rows, cols = labels.shape
    limited = reach_f64 < np.inf
    for r in range(rows):
        for c in range(cols):
            label = labels[r, c]
            value = depth_of_label[label]
            if limited:
                dist = distance[r, c]
                if dist > far:
                    value = np.float32(0.0)
                elif dist >= low and label > 0:
                    seed = seed_index[label - 1]
                    if np.hypot(float(seed // width - r), float(seed % width - c)) > reach_f64:
                        value = np.float32(0.0)
            dense[r, c] = value


@njit(cache=True, nogil=True)
def blind_zone_in_place(out, reference, cell, ratio, scale, has_scale):
    """:func:`drivetrack.depth.bound_blind_zone` on ``out`` (float32 [H, W], a copy of the sparse
    map, written in place) in three passes over the image; float32 arithmetic as the numpy form
    (``ratio``: float32). Returns False when no reference return is visible (``out`` unchanged)."""
    height, width = out.shape
    cells = -(-width // cell)
    lowest = np.full(cells, -1, np.int64)
    any_seen = False
    for y in range(height):                      # lowest visible reference row per column cell
        for x in range(width):
            d = reference[y, x]
            if d > 0 and d <= out[y, x]:
                any_seen = True
                c = x // cell
                if y > lowest[c]:
                    lowest[c] = y
    if not any_seen:
        return False
    top = height
    for c in range(cells):
        if lowest[c] >= 0 and lowest[c] < top:
            top = lowest[c]
    bound = np.zeros(cells, np.float32)
    for y in range(max(top - cell, 0), height):   # the farthest return of each cell's lowest scan line
        for x in range(width):
            d = reference[y, x]
            if d > 0 and d <= out[y, x]:
                c = x // cell
                if y >= lowest[c] - cell:
                    horizontal = d / scale[y, x] if has_scale else d / np.float32(1.0)
                    if horizontal > bound[c]:
                        bound[c] = horizontal
    for y in range(top + 1, height):              # below the lowest scan line: bounded
        for x in range(width):
            c = x // cell
            if lowest[c] >= 0 and y > lowest[c]:
                region = out[y, x]
                bounded = bound[c] * scale[y, x] if has_scale else bound[c]
                if region <= 0 or ratio * region > bounded:
                    out[y, x] = -bounded
    return True
