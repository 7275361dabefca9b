"""numba kernels of the visibility stage: the back-face normals
(:func:`drivetrack.visibility.facing.cloud_normals`) and each tracked point's nearest cloud point
(:func:`cloud_grid`, :func:`nearest_in_grid`: ``CloudNormals.nearest``), the projection of an
occluder's surfels into an image window (:func:`project_in_window`), the tracked points'
projection for the z-buffer test (:func:`project_points`), the back-face test
(:func:`facing_test`, :func:`facing_test_rows`) and the z-buffer's passes over points, returns and
pixels around OpenCV's morphology (:func:`zbuffer_points` to :func:`zbuffer_decide`:
``drivetrack.visibility.zbuffer.hidden_by_others(use_kernel=True)``), and the surface under each
tracked return (:func:`surface_offsets`: ``drivetrack.visibility.facing.points_on_surface``).

Shapes: m cloud points, k neighbours, n query points; metres, box frame.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from drivetrack.camera.kernel import pixel_from_camera_point as _pixel
from drivetrack.numba_compat import NUMBA_AVAILABLE, njit
from drivetrack.refine.kernel import _gap2      # squared distance to a cell's interval (the k-nearest grid's)

__all__ = ["NUMBA_AVAILABLE", "CloudGrid", "cloud_grid", "grid_cell", "nearest_in_grid", "shifted_neighbourhoods",
           "surface_offsets",
           "project_in_window", "project_points", "facing_test", "facing_test_rows", "zbuffer_points", "zbuffer_near",
           "splat_groups", "scatter_min", "merge_spread", "merge_nearer", "zbuffer_on", "zbuffer_decide", "clip_convex", "hull_depths", "splat_merge"]


@njit(cache=True, nogil=True)
def _plane_offset(cloud, i, normal, centroid, j):
    """Distance (metres) of cloud point i from the plane of neighbourhood j."""
    return abs(normal[j, 0] * (cloud[i, 0] - centroid[j, 0]) + normal[j, 1] * (cloud[i, 1] - centroid[j, 1])
               + normal[j, 2] * (cloud[i, 2] - centroid[j, 2]))


@njit(cache=True, nogil=True)
def _variation(eigen, j):
    """Surface variation ``l1 / (l1 + l2 + l3)`` of neighbourhood j (0: flat)."""
    return eigen[j, 0] / max(eigen[j, 0] + eigen[j, 1] + eigen[j, 2], 1e-300)


@njit(cache=True, nogil=True)
def _shifted_kernel(cloud, index, normal, centroid, eigen, tolerance_m, sigmas, min_cos, tight_m, choice):
    m, k = index.shape
    for i in range(m):
        best, best_variation = index[i, 0], np.inf
        for a in range(k):
            j = index[i, a]
            if a > 0:
                # its plane must pass through the point, within the tolerance ...
                spread_j = sigmas * np.sqrt(max(eigen[j, 0], 0.0))
                if _plane_offset(cloud, i, normal, centroid, j) > max(tolerance_m, spread_j):
                    continue
                # ... and lean the way the point's own neighbourhood does
                cos = normal[j, 0] * normal[i, 0] + normal[j, 1] * normal[i, 1] + normal[j, 2] * normal[i, 2]
                if abs(cos) < min_cos:
                    continue
            variation = _variation(eigen, j)
            if variation < best_variation:
                best, best_variation = j, variation
        choice[i] = best
    if tight_m <= 0.0:
        return
    first = choice.copy()
    for i in range(m):
        own = first[i]
        off = _plane_offset(cloud, i, normal, centroid, own)
        spread = sigmas * np.sqrt(max(eigen[own, 0], 0.0))
        loose = off > max(tight_m, spread)
        if not loose and off <= tight_m and spread <= tight_m:
            continue
        # The chosen plane misses the point by more than its own spread (loose), or it is no
        # precise plane through the point: the point may lie on another face than the one its
        # neighbourhood leaned to (a denser face across an edge). The flattest of its neighbours'
        # chosen planes, of any tilt, that passes through it within its own spread (loose) or
        # that is a precise plane through it (otherwise), where there is one
        other, other_variation = -1, np.inf
        for a in range(k):
            j = first[index[i, a]]
            off_j = _plane_offset(cloud, i, normal, centroid, j)
            spread_j = sigmas * np.sqrt(max(eigen[j, 0], 0.0))
            if loose:
                if off_j > max(tight_m, spread_j):
                    continue
            elif off_j > tight_m or spread_j > tight_m:
                continue
            variation = _variation(eigen, j)
            if variation < other_variation:
                other, other_variation = j, variation
        if other >= 0:
            choice[i] = other


def shifted_neighbourhoods(cloud: np.ndarray, index: np.ndarray, normal: np.ndarray, centroid: np.ndarray,
                           eigen: np.ndarray, tolerance_m: float, sigmas: float, max_tilt_deg: float,
                           tight_m: float = 0.0) -> np.ndarray:
    """int64 [m]: for each point of ``cloud`` float64 [m, 3] the neighbour (an index into
    ``cloud``) whose neighbourhood's plane to take (see
    :func:`drivetrack.visibility.facing.cloud_normals`).

    ``index`` int [m, k]: each point's k nearest (itself first); ``normal``, ``centroid`` float64
    [m, 3] and ``eigen`` float64 [m, 3] (ascending, square metres): each neighbourhood's plane
    (``drivetrack.refine.kernel.plane_fits``). Among the neighbourhoods of a point's neighbours,
    its own always and the others when their plane passes within ``max(tolerance_m, sigmas *
    sqrt(l1))`` of the point and their normal lies within ``max_tilt_deg`` of the point's own
    neighbourhood's (either sign), the flattest (smallest ``l1 / (l1 + l2 + l3)``) wins. With
    ``tight_m`` > 0 a second pass follows: when the winner's plane misses the point by more than
    ``max(tight_m, sigmas * sqrt(l1))`` of its own, the flattest of its neighbours' winners whose
    plane passes within that of the point wins instead; when it passes that close but is no
    precise plane through the point (its spread ``sigmas * sqrt(l1)`` or its miss beyond
    ``tight_m``), the flattest of its neighbours' winners that is one (spread and miss both within
    ``tight_m``) wins instead. Either of any tilt, and only where there is one.
    """
    choice = np.empty(cloud.shape[0], dtype=np.int64)
    _shifted_kernel(np.ascontiguousarray(cloud, dtype=np.float64), np.ascontiguousarray(index, dtype=np.int64),
                    np.ascontiguousarray(normal, dtype=np.float64), np.ascontiguousarray(centroid, dtype=np.float64),
                    np.ascontiguousarray(eigen, dtype=np.float64), float(tolerance_m), float(sigmas),
                    float(np.cos(np.radians(max_tilt_deg))), float(tight_m), choice)
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


#: at most this many cells in a :func:`cloud_grid`; the cell grows beyond the asked one to respect it
_MAX_GRID_CELLS = 1 << 22


class CloudGrid(NamedTuple):
    """A cloud sorted into a uniform grid of cubic cells (:func:`cloud_grid`), for
    :func:`nearest_in_grid`.

    Attributes:
        lo: float64 [3], the grid's corner: the cloud's smallest coordinates (metres).
        cell: the cells' side (metres).
        dims: int64 [3], cells along each axis (x slowest in a cell's number).
        start: int64 [cells + 1], the points of cell ``c`` are the sorted rows ``start[c]:start[c + 1]``.
        order: int64 [m], the cloud row of each sorted row (ascending within a cell).
        points: float64 [m, 3], the cloud in cell order (a cell's points contiguous in memory).
    """
    lo: np.ndarray
    cell: float
    dims: np.ndarray
    start: np.ndarray
    order: np.ndarray
    points: np.ndarray


@njit(cache=True, nogil=True, inline="always")
def _cell_of(v, lo, cell, dim):
    """The cell (along one axis) holding coordinate ``v``, clamped into ``[0, dim)`` (NaN: 0)."""
    g = (v - lo) / cell
    if g >= dim:
        return dim - 1
    if g >= 0.0:
        return int(g)
    return 0


@njit(cache=True, nogil=True)
def _grid_kernel(cloud, lo, cell, dims, start, order, points):
    m = cloud.shape[0]
    key = np.empty(m, np.int64)
    for i in range(m):
        c = 0
        for a in range(3):
            c = c * dims[a] + _cell_of(cloud[i, a], lo[a], cell, dims[a])
        key[i] = c
        start[c + 1] += 1
    for c in range(start.shape[0] - 1):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    for i in range(m):                                  # counting sort: stable, rows ascending in a cell
        s = fill[key[i]]
        fill[key[i]] += 1
        order[s] = i
        for a in range(3):
            points[s, a] = cloud[i, a]


@njit(cache=True, nogil=True)
def _occupied_cells(cloud, lo, cell, dims):
    seen = np.zeros(dims[0] * dims[1] * dims[2], np.bool_)
    count = 0
    for i in range(cloud.shape[0]):
        c = 0
        for a in range(3):
            c = c * dims[a] + _cell_of(cloud[i, a], lo[a], cell, dims[a])
        if not seen[c]:
            seen[c] = True
            count += 1
    return count


def grid_cell(cloud: np.ndarray, points_per_cell: float = 4.0) -> float:
    """A :func:`cloud_grid` cell (metres) for ``cloud`` float [m >= 1, 3] holding about
    ``points_per_cell`` points where the cloud has any: from the points per occupied cell of a
    trial grid of at most about m cells (its side ``h0``: the largest extent over ``m ** (1 / 3)``),
    as for a surface (points per cell grow as the cell's square), within ``[h0 / 8, 2 h0]``. On an object's
    returns thinned to 2.5 cm cubes about 0.05-0.07 m, the fastest measured for
    :func:`nearest_in_grid`; 1 for a cloud of one point (or all at one place)."""
    cloud = np.ascontiguousarray(cloud, dtype=np.float64)
    lo = cloud.min(axis=0)
    extent = cloud.max(axis=0) - lo
    if not extent.max() > 0.0:
        return 1.0
    h0 = float(extent.max()) / cloud.shape[0] ** (1.0 / 3.0)
    dims = (np.floor(extent / h0) + 1.0).astype(np.int64)
    per_cell = cloud.shape[0] / _occupied_cells(cloud, lo, h0, dims)
    return h0 * float(np.clip(np.sqrt(points_per_cell / per_cell), 0.125, 2.0))


def cloud_grid(cloud: np.ndarray, cell_m: float) -> CloudGrid:
    """The :class:`CloudGrid` of ``cloud`` float [m, 3] (m >= 1, finite) with cells of side
    ``cell_m`` (metres; doubled until the grid has at most :data:`_MAX_GRID_CELLS` cells): built
    once, searched by :func:`nearest_in_grid` for any number of queries. Only speed depends on
    the cell: about the cloud's spacing, a few points per occupied cell."""
    cloud = np.ascontiguousarray(cloud, dtype=np.float64)
    if cloud.ndim != 2 or cloud.shape[1] != 3 or cloud.shape[0] == 0:
        raise ValueError(f"cloud_grid: cloud must be [m >= 1, 3], got shape {cloud.shape}")
    lo = cloud.min(axis=0)
    extent = cloud.max(axis=0) - lo
    cell = float(cell_m)
    if not cell > 0.0:
        raise ValueError(f"cloud_grid: cell_m must be positive, got {cell_m}")
    while np.prod(np.floor(extent / cell) + 1.0) > _MAX_GRID_CELLS:
        cell *= 2.0
    dims = (np.floor(extent / cell) + 1.0).astype(np.int64)
    start = np.zeros(int(np.prod(dims)) + 1, np.int64)
    order = np.empty(cloud.shape[0], np.int64)
    points = np.empty_like(cloud)
    _grid_kernel(cloud, lo, cell, dims, start, order, points)
    return CloudGrid(lo, cell, dims, start, order, points)


@njit(cache=True, nogil=True)
def _nearest_kernel(queries, lo, cell, dims, start, order, points, span, index):
    d0, d1, d2 = dims[0], dims[1], dims[2]
    m = order.shape[0]
    for i in range(queries.shape[0]):
        x, y, z = queries[i, 0], queries[i, 1], queries[i, 2]
        c0, c1, c2 = _cell_of(x, lo[0], cell, d0), _cell_of(y, lo[1], cell, d1), _cell_of(z, lo[2], cell, d2)
        # beyond this ring every cell has been searched
        last = max(max(c0, d0 - 1 - c0), max(max(c1, d1 - 1 - c1), max(c2, d2 - 1 - c2)))
        # rounding allowance (metres) of the cell bounds and the distances: a point sits in its
        # cell within an ulp of its coordinates
        eps = 1e-12 * (1.0 + span + abs(x) + abs(y) + abs(z))
        # squared distance along each axis from the query to the grid's range (0 inside it)
        out0 = _gap2(x, lo[0] - eps, d0 * cell + 2.0 * eps)
        out1 = _gap2(y, lo[1] - eps, d1 * cell + 2.0 * eps)
        out2 = _gap2(z, lo[2] - eps, d2 * cell + 2.0 * eps)
        best_d, best_i = np.inf, m
        r = 0
        while True:
            # the shell of cells at Chebyshev distance r from the query's (clamped) cell
            for gi in range(max(c0 - r, 0), min(c0 + r + 1, d0)):
                edge_i = gi == c0 - r or gi == c0 + r
                gx = _gap2(x, lo[0] + gi * cell - eps, cell + 2.0 * eps)
                if gx > best_d:
                    continue
                for gj in range(max(c1 - r, 0), min(c1 + r + 1, d1)):
                    gy = gx + _gap2(y, lo[1] + gj * cell - eps, cell + 2.0 * eps)
                    if gy > best_d:
                        continue                        # the whole row is farther than the best
                    base = (gi * d1 + gj) * d2
                    edge = edge_i or gj == c1 - r or gj == c1 + r
                    gk = max(c2 - r, 0) if edge else c2 - r
                    stop = min(c2 + r + 1, d2)
                    while gk < stop:
                        if gk >= 0:
                            c = base + gk
                            if (start[c] != start[c + 1]
                                    and gy + _gap2(z, lo[2] + gk * cell - eps, cell + 2.0 * eps) <= best_d):
                                for s in range(start[c], start[c + 1]):
                                    d = (points[s, 0] - x) ** 2 + (points[s, 1] - y) ** 2 + (points[s, 2] - z) ** 2
                                    if d < best_d or (d == best_d and order[s] < best_i):
                                        best_d, best_i = d, order[s]
                        gk += 1 if edge else 2 * r      # rows inside the shell: only its two z ends
            if r >= last:
                break
            # every point not searched yet lies beyond a face of the searched block that has cells
            # behind it, and inside the grid: at least sqrt(reach2) from the query (the true query,
            # not its clamped cell: outside the grid, its distance to the grid counts too)
            reach2 = np.inf
            if c0 - r > 0:
                reach2 = min(reach2, max(x - (lo[0] + (c0 - r) * cell) - eps, 0.0) ** 2 + out1 + out2)
            if c0 + r + 1 < d0:
                reach2 = min(reach2, max(lo[0] + (c0 + r + 1) * cell - x - eps, 0.0) ** 2 + out1 + out2)
            if c1 - r > 0:
                reach2 = min(reach2, max(y - (lo[1] + (c1 - r) * cell) - eps, 0.0) ** 2 + out0 + out2)
            if c1 + r + 1 < d1:
                reach2 = min(reach2, max(lo[1] + (c1 + r + 1) * cell - y - eps, 0.0) ** 2 + out0 + out2)
            if c2 - r > 0:
                reach2 = min(reach2, max(z - (lo[2] + (c2 - r) * cell) - eps, 0.0) ** 2 + out0 + out1)
            if c2 + r + 1 < d2:
                reach2 = min(reach2, max(lo[2] + (c2 + r + 1) * cell - z - eps, 0.0) ** 2 + out0 + out1)
            if best_d <= reach2:
                break
            r += 1
        index[i] = best_i


def nearest_in_grid(grid: CloudGrid, queries: np.ndarray) -> np.ndarray:
    """int64 [n]: the row of ``grid``'s cloud (:func:`cloud_grid`) nearest each of ``queries``
    float [n, 3] (metres, the cloud's frame), by Euclidean distance.

    Exact: the index of ``scipy.spatial.cKDTree(cloud).query(queries, k=1)`` (the same squared
    distances, summed in the same order), ties between exactly equidistant cloud points broken by
    the lower index. Rings of cells are searched outward from the query's cell (clamped into the
    grid: a query outside the cloud's box gets its true nearest too) until the best squared
    distance so far is within the least squared distance from the query itself (not its cell) to
    a cell not searched yet: beyond a face of the searched block, inside the grid; cell bounds are
    widened by a rounding allowance of ``1e-12`` times the size of the grid's and the query's
    coordinates. Queries must be finite (cKDTree refuses others; a NaN row gets ``m``)."""
    queries = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
    index = np.empty(queries.shape[0], np.int64)
    span = float(np.abs(grid.lo).max() + grid.cell * grid.dims.max())     # the grid's coordinates' size
    _nearest_kernel(queries, grid.lo, float(grid.cell), grid.dims, grid.start, grid.order, grid.points, span, index)
    return index


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


@njit(cache=True, nogil=True, inline="always")
def _merge_pixel(buffer, footprint, y, x, v, r):
    """Pixel (y, x) of ``buffer`` float32 / ``footprint`` int8 takes depth ``v`` of footprint ``r``
    when nearer, and the larger footprint when equal and finite (:func:`merge_spread`'s rule)."""
    b = buffer[y, x]
    if v < b:
        buffer[y, x] = v
        footprint[y, x] = r
    elif v == b and np.isfinite(b) and footprint[y, x] < r:
        footprint[y, x] = r


@njit(cache=True, nogil=True)
def merge_spread(buffer, footprint, spread, r):
    """Keeps the nearer of ``buffer`` and ``spread`` float32 [H, W] in ``buffer``; ``footprint``
    int8 [H, W] takes ``r`` where ``spread`` is nearer, and the larger of the two where equal and
    finite (``zbuffer.nearest_depth``'s footprint of the return holding each pixel's depth)."""
    h, w = buffer.shape
    for y in range(h):
        for x in range(w):
            _merge_pixel(buffer, footprint, y, x, spread[y, x], r)


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


@njit(cache=True, nogil=True)
def _offsets_kernel(queries, query_normal, lo, cell, dims, start, order, points, cloud_normal, radius, slab,
                    min_cos, min_count, offset):
    d0, d1, d2 = dims[0], dims[1], dims[2]
    r2 = radius * radius
    reach = np.sqrt(radius * radius + slab * slab)           # the cylinder lies inside this ball
    for i in range(queries.shape[0]):
        x, y, z = queries[i, 0], queries[i, 1], queries[i, 2]
        nx, ny, nz = query_normal[i, 0], query_normal[i, 1], query_normal[i, 2]
        a0, b0 = _cell_of(x - reach, lo[0], cell, d0), _cell_of(x + reach, lo[0], cell, d0)
        a1, b1 = _cell_of(y - reach, lo[1], cell, d1), _cell_of(y + reach, lo[1], cell, d1)
        a2, b2 = _cell_of(z - reach, lo[2], cell, d2), _cell_of(z + reach, lo[2], cell, d2)
        count, moment = 0, 0.0
        for gi in range(a0, b0 + 1):
            for gj in range(a1, b1 + 1):
                base = (gi * d1 + gj) * d2
                for gk in range(a2, b2 + 1):
                    c = base + gk
                    for s in range(start[c], start[c + 1]):
                        dx, dy, dz = points[s, 0] - x, points[s, 1] - y, points[s, 2] - z
                        along = dx * nx + dy * ny + dz * nz
                        if abs(along) > slab or dx * dx + dy * dy + dz * dz - along * along > r2:
                            continue
                        j = order[s]
                        if abs(cloud_normal[j, 0] * nx + cloud_normal[j, 1] * ny + cloud_normal[j, 2] * nz) < min_cos:
                            continue                    # another face (an edge within the radius)
                        count += 1
                        moment += along
        offset[i] = moment / count if count >= max(min_count, 1) else np.nan


def surface_offsets(grid: CloudGrid, cloud_normal: np.ndarray, queries: np.ndarray, query_normal: np.ndarray,
                    radius_m: float, slab_m: float, min_cos: float, min_count: int) -> np.ndarray:
    """float64 [n]: where the surface lies along each query's normal, relative to the query
    (metres; NaN where too little of it is near).

    ``grid`` the :func:`cloud_grid` of m cloud points (an object's returns), ``cloud_normal`` float
    [m, 3] their unit normals (sign arbitrary); ``queries`` float [n, 3] and ``query_normal`` float
    [n, 3] (unit). The offset is the mean of ``(q - query) . normal`` over the cloud points q
    within ``radius_m`` of the query's normal line and ``slab_m`` of the query along it whose own
    normal lies within ``arccos(min_cos)`` of the query's (either sign: the same face, not one
    across an edge), when there are ``min_count`` of them or more.
    """
    queries = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
    offset = np.empty(queries.shape[0])
    _offsets_kernel(queries, np.ascontiguousarray(query_normal, dtype=np.float64), grid.lo, float(grid.cell),
                    grid.dims, grid.start, grid.order, grid.points, np.ascontiguousarray(cloud_normal, dtype=np.float64),
                    float(radius_m), float(slab_m), float(min_cos), int(min_count), offset)
    return offset


@njit(cache=True, nogil=True)
def clip_convex(starts, rays, facets, one_start, enter, leave, by, never, inside):
    """Clips k rays against a convex hull (Cyrus-Beck): ray i is ``starts[i] + s rays[i]``
    (``starts`` float64 [k, 3], or [1, 3] for all when ``one_start``; ``rays`` float64 [k, 3]) and
    the hull ``n . p + d <= 0`` for each row (n, d) of ``facets`` float64 [F, 4]. Per ray, with
    ``a = n . start + d`` and ``b = n . ray`` per facet and ``s = -a / b``:

    - ``enter`` float64 [k]: the largest ``s`` over the facets with ``b < 0`` (-inf when none),
      ``by`` int64 [k] the first facet reaching it (0 when none);
    - ``leave`` float64 [k]: the smallest ``s`` over the facets with ``b > 0`` (+inf when none);
    - ``never`` bool [k]: some facet has ``b == 0`` and ``a > 0`` (the ray runs parallel to it, outside);
    - ``inside`` bool [k]: every ``a <= 0`` (the start lies inside the hull).

    The products and sums in the order of ``drivetrack.visibility.zbuffer._dot3``, so each figure
    equals the numpy path's bit for bit."""
    k = rays.shape[0]
    f_count = facets.shape[0]
    for i in range(k):
        j0 = 0 if one_start else i
        sx, sy, sz = starts[j0, 0], starts[j0, 1], starts[j0, 2]
        rx, ry, rz = rays[i, 0], rays[i, 1], rays[i, 2]
        best, best_at, low = -np.inf, 0, np.inf
        parallel_out, all_in = False, True
        for f in range(f_count):
            nx, ny, nz = facets[f, 0], facets[f, 1], facets[f, 2]
            a = sx * nx + sy * ny + sz * nz + facets[f, 3]
            b = rx * nx + ry * ny + rz * nz
            if a > 0:
                all_in = False
            if b < 0:
                s = -a / b
                if s > best:
                    best, best_at = s, f
            elif b > 0:
                s = -a / b
                if s < low:
                    low = s
            elif a > 0:
                parallel_out = True
        enter[i], by[i], leave[i], never[i], inside[i] = best, best_at, low, parallel_out, all_in


@njit(cache=True, nogil=True)
def hull_depths(points, facets, depth):
    """``depth`` float64 [k]: how far inside the convex hull of ``facets`` float64 [F, 4] (outward
    ``n . p + d``) each of ``points`` float64 [k, 3] lies, ``-max_f (n_f . p + d_f)`` (negative:
    outside); the products and sums in the order of ``drivetrack.visibility.zbuffer._dot3``."""
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        top = -np.inf
        for f in range(facets.shape[0]):
            v = px * facets[f, 0] + py * facets[f, 1] + pz * facets[f, 2] + facets[f, 3]
            if v > top:
                top = v
        depth[i] = -top


@njit(cache=True, nogil=True)
def splat_merge(buffer, footprint, flat, order, depth, start, stop, r, pad):
    """:func:`scatter_min` of returns ``start:stop`` (footprint ``r``) into a buffer padded by
    ``pad``, its square minimum of side 2r+1 (the erosion of ``zbuffer.nearest_depth``) and
    :func:`merge_spread` into ``buffer`` float32 [H, W] / ``footprint`` int8 [H, W], in one pass:
    each return's square written directly (min and the footprint's rule are exact and
    order-free, so the same buffer and footprints). Cheaper than the erosion when few returns
    have this footprint (their squares cover less than the padded buffer)."""
    h, w = buffer.shape
    stride = w + 2 * pad
    for a in range(start, stop):
        v = np.float32(depth[order[a]])
        yc = flat[a] // stride - pad
        xc = flat[a] % stride - pad
        for y in range(max(yc - r, 0), min(yc + r + 1, h)):
            for x in range(max(xc - r, 0), min(xc + r + 1, w)):
                _merge_pixel(buffer, footprint, y, x, v, r)
