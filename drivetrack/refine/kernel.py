"""Fused numba kernels of the pose refinement's inner loop (``drivetrack.refine``).

Pieces of a Gauss-Newton iteration that numpy/scipy do with large temporaries or a general
tree, each with the numpy/scipy reference it must reproduce:

- :func:`knn`: exact k nearest neighbours of every point among the same points (itself
  included, distance 0), ascending. Reference: ``scipy.spatial.cKDTree(p).query(p, k)``. A dense
  voxel grid (the object's points fill a few metres) searched in growing Chebyshev shells until the
  k-th distance is inside the searched block; ties are broken by the lower index.
- :func:`normals`: PCA normals and planarity of neighbour lists, the same closed-form 3x3 eigen
  decomposition as ``drivetrack.refine.terms._normals`` (same formulas, same order of operations).
- :func:`normal_equations`: the dense [DT, DT] normal equations and gradient of weighted
  point-to-plane pairs (2 x D Jacobian non-zeros per pair; D = 4: centre and heading, D = 6: and
  pitch, roll), as ``drivetrack.refine.terms._pair_terms`` assembles them with ``np.bincount``.
- :func:`select`: the capped per-frame point selection with the body points, in one pass per
  frame (reference: ``drivetrack.refine.select._Selection.select``); :func:`inside_counts`: how
  many returns each frame's box holds (reference: ``_inside`` of ``_body_points``).
- :func:`cholesky_solve`: single-threaded Cholesky solve of the normal equations on their
  envelope (reference: ``scipy.linalg.cho_solve``).
- :func:`gather`: the candidate returns of every box (reference: ``drivetrack.boxes.gather_candidates``).
- :func:`ground_under_boxes`: the ground's height under every box, from the ring of returns round
  it (reference: ``drivetrack.boxes.ground_under_boxes``).
- :func:`claimed_by_other_boxes`: the returns another object's box holds more deeply than their own
  (reference: ``drivetrack.boxes.claimed_by_other_boxes``).
- :func:`frame_time_candidates`: an object's candidates moved to the frame (label) time, the
  grown-box test and the kept returns back in the vehicle frame, in one pass (reference:
  ``drivetrack.refine.scene._frame_time_candidates``).

numba compiles on first use and caches the machine code on disk (``cache=True``).
"""
from __future__ import annotations

import numpy as np

__all__ = ["NUMBA_AVAILABLE", "knn", "normals", "normal_equations", "gather", "select", "cholesky_solve",
           "frame_time_candidates", "inside_counts", "ground_under_boxes",
           "claimed_by_other_boxes"]

from drivetrack.numba_compat import NUMBA_AVAILABLE, njit
from drivetrack.parallel import pool_map

#: at most this many grid cells; the cell grows beyond ``cell_m`` to respect it
_MAX_CELLS = 1 << 22


@njit(cache=True, nogil=True, inline="always")
def _gap2(v, cell_lo, cell):
    """Squared distance from coordinate ``v`` to the interval [cell_lo, cell_lo + cell] (0 inside)."""
    if v < cell_lo:
        return (cell_lo - v) ** 2
    if v > cell_lo + cell:
        return (v - cell_lo - cell) ** 2
    return 0.0


@njit(cache=True, nogil=True)
def _knn_grid(points, k, cell, dist, index):
    n = points.shape[0]
    lo = np.empty(3)
    dims = np.empty(3, np.int64)
    for a in range(3):
        lo[a] = points[:, a].min()
        dims[a] = int((points[:, a].max() - lo[a]) / cell) + 1
    d1, d2 = dims[1], dims[2]
    ncell = dims[0] * d1 * d2
    ci = np.empty((n, 3), np.int64)
    key = np.empty(n, np.int64)
    for i in range(n):
        for a in range(3):
            c = int((points[i, a] - lo[a]) / cell)
            ci[i, a] = min(max(c, 0), dims[a] - 1)
        key[i] = (ci[i, 0] * d1 + ci[i, 1]) * d2 + ci[i, 2]
    order = np.argsort(key, kind="mergesort")              # stable: index order within a cell
    # the points copied in cell order: a cell's points are contiguous in memory
    sp = np.empty((n, 3))
    for s in range(n):
        for a in range(3):
            sp[s, a] = points[order[s], a]
    start = np.zeros(ncell + 1, np.int64)
    for i in range(n):
        start[key[i] + 1] += 1
    for c in range(ncell):
        start[c + 1] += start[c]
    max_ring = max(dims[0], max(d1, d2))
    best_d = np.empty(k)
    best_i = np.empty(k, np.int64)
    for i in range(n):
        found = 0
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        c0, c1, c2 = ci[i, 0], ci[i, 1], ci[i, 2]
        r = 0
        while True:
            for gi in range(max(c0 - r, 0), min(c0 + r + 1, dims[0])):
                edge_i = gi == c0 - r or gi == c0 + r
                gx = _gap2(x, lo[0] + gi * cell, cell)
                for gj in range(max(c1 - r, 0), min(c1 + r + 1, d1)):
                    edge_j = edge_i or gj == c1 - r or gj == c1 + r
                    gy = gx + _gap2(y, lo[1] + gj * cell, cell)
                    if found == k and gy > best_d[k - 1]:
                        continue                            # the whole row is farther than the k-th
                    base = (gi * d1 + gj) * d2
                    if edge_j:                              # rows inside the shell: only its two z ends
                        klo, khi, kstep = max(c2 - r, 0), min(c2 + r + 1, d2), 1
                    else:
                        klo, khi, kstep = c2 - r, c2 + r + 1, 2 * r
                    gk = klo
                    while gk < khi:
                        if gk < 0 or gk >= d2:
                            gk += kstep if kstep > 0 else 1
                            continue
                        c = base + gk
                        if start[c] != start[c + 1]:
                            ok = True
                            if found == k:
                                ok = gy + _gap2(z, lo[2] + gk * cell, cell) <= best_d[k - 1]
                            if ok:
                                for s in range(start[c], start[c + 1]):
                                    d = (sp[s, 0] - x) ** 2 + (sp[s, 1] - y) ** 2 + (sp[s, 2] - z) ** 2
                                    if found == k and d > best_d[k - 1]:
                                        continue
                                    j = order[s]
                                    if found == k and d == best_d[k - 1] and j > best_i[k - 1]:
                                        continue
                                    m = found if found < k else k - 1
                                    while m > 0 and (best_d[m - 1] > d or (best_d[m - 1] == d and best_i[m - 1] > j)):
                                        best_d[m] = best_d[m - 1]
                                        best_i[m] = best_i[m - 1]
                                        m -= 1
                                    best_d[m] = d
                                    best_i[m] = j
                                    if found < k:
                                        found += 1
                        if kstep == 0:
                            break
                        gk += kstep
            reach = np.inf
            for a in range(3):
                p = points[i, a]
                reach = min(reach, p - (lo[a] + (ci[i, a] - r) * cell), lo[a] + (ci[i, a] + r + 1) * cell - p)
            if (found == k and best_d[k - 1] <= reach * reach) or r > max_ring:
                break
            r += 1
        for m in range(k):
            dist[i, m] = np.sqrt(best_d[m])
            index[i, m] = best_i[m]


def knn(points: np.ndarray, k: int, cell_m: float = 0.15) -> tuple[np.ndarray, np.ndarray]:
    """(distances float64 [N, k], indices int64 [N, k]): each point's k nearest among ``points``
    [N, 3] (itself first), ascending; exactly ``cKDTree(points).query(points, k)`` up to ties.
    ``cell_m``: grid cell (metres), about the spacing of k neighbours; only speed depends on it."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    n = points.shape[0]
    if not (1 <= k <= n):
        raise ValueError(f"knn: k must be in [1, {n}] for {n} points, got {k}")
    extent = np.ptp(points, axis=0) if n else np.zeros(3)
    cell = float(cell_m)
    while np.prod(np.floor(extent / cell) + 1.0) > _MAX_CELLS:
        cell *= 2.0
    dist = np.empty((n, k))
    index = np.empty((n, k), np.int64)
    _knn_grid(points, int(k), cell, dist, index)
    return dist, index


@njit(cache=True, nogil=True)
def _normals_kernel(model, neighbours, normal, planarity, centroid, eigen):
    p_count, k = neighbours.shape
    cov = np.empty((3, 3))
    b = np.empty((3, 3))
    mean_point = np.empty(3)
    third = 2.0 * np.pi / 3.0
    for i in range(p_count):
        for a in range(3):
            s = 0.0
            for j in range(k):
                s += model[neighbours[i, j], a]
            mean_point[a] = s / k
            centroid[i, a] = mean_point[a]
        for a in range(3):
            for c in range(3):
                s = 0.0
                for j in range(k):
                    s += model[neighbours[i, j], a] * model[neighbours[i, j], c]
                cov[a, c] = s / k - mean_point[a] * mean_point[c]
        off = cov[0, 1] ** 2 + cov[0, 2] ** 2 + cov[1, 2] ** 2
        mean = (cov[0, 0] + cov[1, 1] + cov[2, 2]) / 3.0
        p = np.sqrt(((cov[0, 0] - mean) ** 2 + (cov[1, 1] - mean) ** 2 + (cov[2, 2] - mean) ** 2 + 2.0 * off) / 6.0)
        safe = p if p > 0 else 1.0
        for a in range(3):
            for c in range(3):
                b[a, c] = (cov[a, c] - (mean if a == c else 0.0)) / safe
        det = (b[0, 0] * (b[1, 1] * b[2, 2] - b[1, 2] * b[2, 1]) - b[0, 1] * (b[1, 0] * b[2, 2] - b[1, 2] * b[2, 0])
               + b[0, 2] * (b[1, 0] * b[2, 1] - b[1, 1] * b[2, 0]))
        half_det = min(max(det / 2.0, -1.0), 1.0)
        phi = np.arccos(half_det) / 3.0
        l3 = mean + 2.0 * p * np.cos(phi)
        l1 = mean + 2.0 * p * np.cos(phi + third)
        l2 = 3.0 * mean - l1 - l3
        eigen[i, 0], eigen[i, 1], eigen[i, 2] = l1, l2, l3
        for a in range(3):
            cov[a, a] -= l1
        best, bx, by, bz = -1.0, 0.0, 0.0, 1.0
        for r0, r1 in ((0, 1), (0, 2), (1, 2)):
            cx = cov[r0, 1] * cov[r1, 2] - cov[r0, 2] * cov[r1, 1]
            cy = cov[r0, 2] * cov[r1, 0] - cov[r0, 0] * cov[r1, 2]
            cz = cov[r0, 0] * cov[r1, 1] - cov[r0, 1] * cov[r1, 0]
            norm = np.sqrt(cx * cx + cy * cy + cz * cz)
            if norm > best:
                best, bx, by, bz = norm, cx, cy, cz
        if best > 0:
            normal[i, 0], normal[i, 1], normal[i, 2] = bx / best, by / best, bz / best
        else:                                               # isotropic: any direction
            normal[i, 0], normal[i, 1], normal[i, 2] = 0.0, 0.0, 1.0
        planarity[i] = (l2 - l1) / max(l3, 1e-12)


def normals(model: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals float64 [P, 3] and planarity float64 [P] of neighbour lists int [P, k] into
    ``model`` [*, 3]; see ``drivetrack.refine.terms._normals`` (the reference)."""
    normal, planarity, _, _ = plane_fits(model, neighbours)
    return normal, planarity


def plane_fits(model: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(normal float64 [P, 3], planarity float64 [P], centroid float64 [P, 3], eigen float64 [P,
    3])``: :func:`normals` of neighbour lists int [P, k] into ``model`` [*, 3], with each
    neighbourhood's centroid (the plane passes through it) and the eigenvalues l1 <= l2 <= l3 of
    its covariance (square metres; l1 is the variance about the plane)."""
    neighbours = np.ascontiguousarray(neighbours, dtype=np.int64)
    normal = np.empty((neighbours.shape[0], 3))
    planarity = np.empty(neighbours.shape[0])
    centroid = np.empty((neighbours.shape[0], 3))
    eigen = np.empty((neighbours.shape[0], 3))
    _normals_kernel(np.ascontiguousarray(model, dtype=np.float64), neighbours, normal, planarity, centroid, eigen)
    return normal, planarity, centroid, eigen


@njit(cache=True, nogil=True)
def _normal_equations_kernel(n, qa, qb, fa, fb, trig, dof, w, r, hessian, gradient):
    jac = np.empty(2 * dof)
    col = np.empty(2 * dof, np.int64)
    for i in range(n.shape[0]):
        for side in range(2):
            q = qa if side == 0 else qb
            f = fa[i] if side == 0 else fb[i]
            sign = 1.0 if side == 0 else -1.0
            c, s = trig[f, 0], trig[f, 1]
            o = dof * side
            if dof == 4:
                jac[o + 0] = -sign * (c * n[i, 0] - s * n[i, 1])
                jac[o + 1] = -sign * (s * n[i, 0] + c * n[i, 1])
                jac[o + 2] = -sign * n[i, 2]
                jac[o + 3] = sign * (n[i, 0] * q[i, 1] - n[i, 1] * q[i, 0])
            else:                               # same formulas as refine.terms._point_jacobian
                ct, st, cr, sr = trig[f, 2], trig[f, 3], trig[f, 4], trig[f, 5]
                vy, vz = cr * q[i, 1] - sr * q[i, 2], sr * q[i, 1] + cr * q[i, 2]
                ux, uy = ct * q[i, 0] + st * vz, vy
                ky, kz = cr * n[i, 1] - sr * n[i, 2], sr * n[i, 1] + cr * n[i, 2]
                mx, mz = ct * n[i, 0] + st * kz, -st * n[i, 0] + ct * kz
                jac[o + 0] = -sign * (c * mx - s * ky)
                jac[o + 1] = -sign * (s * mx + c * ky)
                jac[o + 2] = -sign * mz
                jac[o + 3] = sign * (mx * uy - ky * ux)
                jac[o + 4] = sign * (-n[i, 0] * vz + kz * q[i, 0])
                jac[o + 5] = sign * (n[i, 1] * q[i, 2] - n[i, 2] * q[i, 1])
            for m in range(dof):
                col[o + m] = dof * f + m
        wi, wr = w[i], w[i] * r[i]
        for a in range(2 * dof):
            gradient[col[a]] += jac[a] * wr
            wa = wi * jac[a]
            for b in range(2 * dof):
                hessian[col[a], col[b]] += wa * jac[b]


def normal_equations(n: np.ndarray, qa: np.ndarray, qb: np.ndarray, fa: np.ndarray, fb: np.ndarray,
                     w: np.ndarray, r: np.ndarray, heading: np.ndarray,
                     tilt: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(hessian float64 [DT, DT], gradient float64 [DT]) of pairs with body normals n [C, 3] and
    body points qa, qb [C, 3] of frames fa, fb [C], weights w [C] and residuals r [C], at the
    per-frame headings ``heading`` [T] (radians) and, for D = 6, tilts ``tilt`` [T, 2] = (pitch,
    roll) radians (None: D = 4, centre and heading); see ``drivetrack.refine.terms._pair_terms`` (the
    reference). Sines and cosines are taken once per frame."""
    dof = 4 if tilt is None else 6
    t_count = heading.shape[0]
    trig = np.zeros((t_count, 6))
    trig[:, 0], trig[:, 1] = np.cos(heading), np.sin(heading)
    if tilt is not None:
        trig[:, 2], trig[:, 3] = np.cos(tilt[:, 0]), np.sin(tilt[:, 0])
        trig[:, 4], trig[:, 5] = np.cos(tilt[:, 1]), np.sin(tilt[:, 1])
    hessian = np.zeros((dof * t_count, dof * t_count))
    gradient = np.zeros(dof * t_count)
    f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)   # noqa: E731
    i64 = lambda a: np.ascontiguousarray(a, dtype=np.int64)     # noqa: E731
    _normal_equations_kernel(f64(n), f64(qa), f64(qb), i64(fa), i64(fb), trig, dof, f64(w), f64(r), hessian,
                             gradient)
    return hessian, gradient


@njit(cache=True, nogil=True)
def _frame_runs(box_frame):
    """``(by_frame, starts)``: the boxes' indices int64 [B] sorted by frame (stable), and int64
    [R + 1] where each frame's run of them starts (the last entry B)."""
    n_box = box_frame.shape[0]
    by_frame = np.argsort(box_frame, kind="mergesort")
    count = 0
    for m in range(n_box):
        if m == 0 or box_frame[by_frame[m]] != box_frame[by_frame[m - 1]]:
            count += 1
    starts = np.empty(count + 1, np.int64)
    r = 0
    for m in range(n_box):
        if m == 0 or box_frame[by_frame[m]] != box_frame[by_frame[m - 1]]:
            starts[r] = m
            r += 1
    starts[count] = n_box
    return by_frame, starts


@njit(cache=True, nogil=True)
def _gather_kernel(points, laser, return_index, laser_ok, return_ok, frame_offsets, box_frame, box_center,
                   box_radius, count_only, counts, index, owner, frame_lo, frame_hi):
    # boxes grouped by frame, so each return of a frame is read once whatever the number of boxes;
    # only boxes of frames [frame_lo, frame_hi) (calls on disjoint ranges write disjoint entries)
    n_box = box_frame.shape[0]
    by_frame, starts = _frame_runs(box_frame)
    fill = np.zeros(n_box, np.int64)
    if not count_only:
        for b in range(1, n_box):
            fill[b] = fill[b - 1] + counts[b - 1]                  # output in (box, row) order
    for run in range(starts.shape[0] - 1):
        s, e = starts[run], starts[run + 1]
        f = box_frame[by_frame[s]]
        if f < frame_lo or f >= frame_hi:
            continue
        for i in range(frame_offsets[f], frame_offsets[f + 1]):
            if not (laser_ok[laser[i] + 128] and return_ok[return_index[i] + 128]):
                continue
            x, y, z = points[i, 0], points[i, 1], points[i, 2]
            for m in range(s, e):
                b = by_frame[m]
                r = box_radius[b]
                if abs(x - box_center[b, 0]) <= r and abs(y - box_center[b, 1]) <= r and \
                        abs(z - box_center[b, 2]) <= r:
                    if count_only:
                        counts[b] += 1
                    else:
                        index[fill[b]] = i
                        owner[fill[b]] = b
                        fill[b] += 1


def _value_table(values) -> np.ndarray:
    """bool [256]: entry v + 128 is True iff int8 value v is in ``values`` (None: all)."""
    ok = np.zeros(256, np.bool_)
    if values is None:
        ok[:] = True
    else:
        ok[np.asarray(values, dtype=np.int64).reshape(-1) + 128] = True
    return ok


def gather(points: np.ndarray, laser: np.ndarray, return_index: np.ndarray, lasers, returns,
           frame_offsets: np.ndarray, box_frame: np.ndarray, box_center: np.ndarray,
           box_radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index int64 [K], owner int64 [K]): the returns within each box's bounding cube.

    ``points`` float64 [M, 3] sorted by frame (``frame_offsets`` int64 [T + 1]: rows of frame t are
    ``[frame_offsets[t], frame_offsets[t+1])``), ``laser`` / ``return_index`` int8 [M]; only rows
    whose laser is in ``lasers`` and return index in ``returns`` (None: all) take part. Per box b
    (``box_frame`` int [B], ``box_center`` float64 [B, 3], ``box_radius`` float64 [B], metres): the
    rows i of its frame with ``|points[i] - box_center[b]| <= box_radius[b]`` on every axis, in
    (box, row) order; ``owner`` is b. One pass over each box's frame, no sort of all returns.
    Reference: ``drivetrack.boxes.gather_candidates``."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    args = (points, np.ascontiguousarray(laser, dtype=np.int8), np.ascontiguousarray(return_index, dtype=np.int8),
            _value_table(lasers), _value_table(returns), np.ascontiguousarray(frame_offsets, dtype=np.int64),
            np.ascontiguousarray(box_frame, dtype=np.int64), np.ascontiguousarray(box_center, dtype=np.float64),
            np.ascontiguousarray(box_radius, dtype=np.float64))
    counts = np.zeros(box_frame.shape[0], np.int64)
    empty = np.empty(0, np.int64)
    # two halves of the frames on the segment's pool (drivetrack.parallel; the kernel releases the
    # GIL): each pass writes only its own boxes' counts and output slots
    n_frames = frame_offsets.shape[0] - 1
    ranges = [(0, n_frames // 2), (n_frames // 2, n_frames)] if n_frames > 1 else [(0, n_frames)]
    pool_map(lambda r: _gather_kernel(*args, True, counts, empty, empty, *r), ranges)
    index, owner = np.empty(int(counts.sum()), np.int64), np.empty(int(counts.sum()), np.int64)
    pool_map(lambda r: _gather_kernel(*args, False, counts, index, owner, *r), ranges)
    return index, owner


@njit(cache=True, nogil=True)
def _ground_kernel(points, laser, return_index, laser_ok, return_ok, frame_offsets, box_frame, center, cos_h, sin_h,
                   half, radius, inner, outer, window, min_returns, quantile, out, frame_lo, frame_hi):
    # per frame: its chosen returns bucketed by vehicle x (1 m cells or coarser, a counting sort),
    # so each box reads only the cells its bounding cube spans; the tests of ground_under_boxes
    # in its order of operations, then the quantile of the ring's heights
    by_frame, starts = _frame_runs(box_frame)
    for run in range(starts.shape[0] - 1):
        s, e = starts[run], starts[run + 1]
        f = box_frame[by_frame[s]]
        if f < frame_lo or f >= frame_hi:
            continue
        lo, hi = frame_offsets[f], frame_offsets[f + 1]
        rows = np.empty(hi - lo, np.int64)
        k = 0
        x_min, x_max = np.inf, -np.inf
        for i in range(lo, hi):
            if laser_ok[laser[i] + 128] and return_ok[return_index[i] + 128]:
                rows[k] = i
                k += 1
                x_min = min(x_min, points[i, 0])
                x_max = max(x_max, points[i, 0])
        if k == 0:
            continue
        cell = max(1.0, (x_max - x_min) / 4096.0)
        n_cell = int((x_max - x_min) / cell) + 1
        start = np.zeros(n_cell + 1, np.int64)
        cell_of = np.empty(k, np.int64)
        for j in range(k):
            c = min(int((points[rows[j], 0] - x_min) / cell), n_cell - 1)
            cell_of[j] = c
            start[c + 1] += 1
        for c in range(n_cell):
            start[c + 1] += start[c]
        fill = start[:-1].copy()
        bucketed = np.empty(k, np.int64)
        for j in range(k):
            bucketed[fill[cell_of[j]]] = rows[j]
            fill[cell_of[j]] += 1
        heights = np.empty(k)
        for m in range(s, e):
            b = by_frame[m]
            r = radius[b]
            cx, cy, cz = center[b, 0], center[b, 1], center[b, 2]
            c_lo = int(np.floor((cx - r - x_min) / cell)) - 1          # a cell either side: rounding
            c_hi = int(np.floor((cx + r - x_min) / cell)) + 1
            c_lo, c_hi = max(c_lo, 0), min(c_hi, n_cell - 1)
            if c_lo > c_hi:
                continue
            co, si = cos_h[b], sin_h[b]
            hx, hy, hz = half[b, 0], half[b, 1], half[b, 2]
            count = 0
            for j in range(start[c_lo], start[c_hi + 1]):
                i = bucketed[j]
                dx, dy, dz = points[i, 0] - cx, points[i, 1] - cy, points[i, 2] - cz
                if abs(dx) > r or abs(dy) > r or abs(dz) > r:
                    continue
                if abs(dz + hz) > window:
                    continue
                ax, ay = abs(co * dx + si * dy), abs(-si * dx + co * dy)
                if ax > hx + outer or ay > hy + outer:
                    continue
                if ax <= hx + inner and ay <= hy + inner:
                    continue
                heights[count] = dz
                count += 1
            if count >= min_returns:
                ordered = np.sort(heights[:count])
                out[b] = ordered[int(np.floor(quantile * (count - 1)))]


def ground_under_boxes(points: np.ndarray, laser: np.ndarray, return_index: np.ndarray, frame_offsets: np.ndarray,
                       box_frame: np.ndarray, center: np.ndarray, heading: np.ndarray, size: np.ndarray,
                       lasers=None, returns=None) -> np.ndarray:
    """float64 [B]: the ground's height under each box (body-frame z, NaN where unmeasured), the
    same values as ``drivetrack.boxes.ground_under_boxes`` (same arguments, no ``gather``) without
    its temporaries: each frame's returns are bucketed by x once and each box reads only the
    buckets its bounding cube spans, testing the ring as it goes; the frames' two halves run on
    the segment's pool."""
    from drivetrack.boxes import GROUND_MIN_RETURNS, GROUND_QUANTILE, GROUND_RING_M, GROUND_WINDOW_M, ground_reach

    count = np.shape(box_frame)[0]
    out = np.full(count, np.nan)
    if count == 0:
        return out
    inner, outer = GROUND_RING_M
    half, radius = ground_reach(size)
    heading = np.asarray(heading, np.float64)
    args = (np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(laser, dtype=np.int8),
            np.ascontiguousarray(return_index, dtype=np.int8), _value_table(lasers), _value_table(returns),
            np.ascontiguousarray(frame_offsets, dtype=np.int64), np.ascontiguousarray(box_frame, dtype=np.int64),
            np.ascontiguousarray(center, dtype=np.float64), np.cos(heading), np.sin(heading),
            np.ascontiguousarray(half), radius, float(inner), float(outer), float(GROUND_WINDOW_M),
            int(GROUND_MIN_RETURNS), float(GROUND_QUANTILE), out)
    n_frames = frame_offsets.shape[0] - 1
    ranges = [(0, n_frames // 2), (n_frames // 2, n_frames)] if n_frames > 1 else [(0, n_frames)]
    pool_map(lambda r: _ground_kernel(*args, *r), ranges)
    return out


@njit(cache=True, nogil=True)
def _claim_pairs_kernel(points, owner, box_frame, box_object, center, cos_h, sin_h, half):
    # claimed_by_other_boxes' pairs: each owner row's reach, then the boxes of its frame and
    # another object within it, as lists per row (CSR); and every point's depth in its own box
    n_box = box_frame.shape[0]
    reach = np.zeros(n_box)
    used = np.zeros(n_box, np.bool_)
    own_depth = np.empty(owner.shape[0])
    for n in range(owner.shape[0]):
        o = owner[n]
        used[o] = True
        dx, dy, dz = points[n, 0] - center[o, 0], points[n, 1] - center[o, 1], points[n, 2] - center[o, 2]
        reach[o] = max(reach[o], np.hypot(dx, dy))
        own_depth[n] = min(half[o, 0] - abs(cos_h[o] * dx + sin_h[o] * dy),
                           half[o, 1] - abs(-sin_h[o] * dx + cos_h[o] * dy), half[o, 2] - abs(dz))
    by_frame = np.argsort(box_frame, kind="mergesort")
    frame_start = np.searchsorted(box_frame[by_frame], box_frame, side="left")
    frame_end = np.searchsorted(box_frame[by_frame], box_frame, side="right")
    start = np.zeros(n_box + 1, np.int64)
    for a in range(n_box):
        if used[a]:
            for m in range(frame_start[a], frame_end[a]):
                b = by_frame[m]
                if box_object[b] != box_object[a] and np.hypot(center[a, 0] - center[b, 0], center[a, 1] - center[b, 1]) \
                        <= reach[a] + np.hypot(half[b, 0], half[b, 1]):
                    start[a + 1] += 1
    for a in range(n_box):
        start[a + 1] += start[a]
    pair = np.empty(start[n_box], np.int64)
    for a in range(n_box):
        k = start[a]
        if used[a]:
            for m in range(frame_start[a], frame_end[a]):
                b = by_frame[m]
                if box_object[b] != box_object[a] and np.hypot(center[a, 0] - center[b, 0], center[a, 1] - center[b, 1]) \
                        <= reach[a] + np.hypot(half[b, 0], half[b, 1]):
                    pair[k] = b
                    k += 1
    return own_depth, start, pair


@njit(cache=True, nogil=True)
def _claim_kernel(points, owner, center, cos_h, sin_h, half, own_depth, start, pair, tolerance, claimed, lo, hi):
    for n in range(lo, hi):
        o = owner[n]
        for k in range(start[o], start[o + 1]):
            b = pair[k]
            dx, dy, dz = points[n, 0] - center[b, 0], points[n, 1] - center[b, 1], points[n, 2] - center[b, 2]
            depth = min(half[b, 0] - abs(cos_h[b] * dx + sin_h[b] * dy),
                        half[b, 1] - abs(-sin_h[b] * dx + cos_h[b] * dy), half[b, 2] - abs(dz))
            if depth > -tolerance and depth > own_depth[n]:
                claimed[n] = True
                break


def claimed_by_other_boxes(points: np.ndarray, owner: np.ndarray, box_frame: np.ndarray, box_object: np.ndarray,
                           center: np.ndarray, heading: np.ndarray, size: np.ndarray,
                           tolerance_m: float = 0.02) -> np.ndarray:
    """bool [N]: the points another object's box holds more deeply than their own, the same values
    as ``drivetrack.boxes.claimed_by_other_boxes`` (same arguments) without its pair temporaries:
    each owner row's neighbouring boxes are listed once, then every point is tested against its
    row's list; the points' two halves run on the segment's pool."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    owner = np.ascontiguousarray(owner, dtype=np.int64)
    claimed = np.zeros(owner.size, dtype=bool)
    if owner.size == 0:
        return claimed
    heading = np.asarray(heading, np.float64)
    cos_h, sin_h = np.cos(heading), np.sin(heading)
    center = np.ascontiguousarray(center, dtype=np.float64)
    half = np.ascontiguousarray(0.5 * np.asarray(size, np.float64))
    codes = np.unique(np.asarray(box_object), return_inverse=True)[1].reshape(-1).astype(np.int64)
    own_depth, start, pair = _claim_pairs_kernel(points, owner, np.ascontiguousarray(box_frame, dtype=np.int64),
                                                 codes, center, cos_h, sin_h, half)
    middle = owner.size // 2
    pool_map(lambda r: _claim_kernel(points, owner, center, cos_h, sin_h, half, own_depth, start, pair,
                                     float(tolerance_m), claimed, *r), [(0, middle), (middle, owner.size)])
    return claimed


@njit(cache=True, nogil=True)
def _frame_time_kernel(points, index, owner, row_of, offsets, label_offset, has_label_offset, center, heading,
                       velocity, yaw_rate, pitch, roll, has_tilt, size, margin, local, vehicle, kept, at):
    # the operations of points_box_at_capture / vectors_to_box, inside_box and vectors_from_box,
    # in their order, one candidate at a time; returns the number kept
    m = 0
    for i in range(index.shape[0]):
        j, o = index[i], owner[i]
        k = row_of[o]
        dt = np.float64(offsets[j])
        if has_label_offset:
            dt = dt - label_offset[k]
        vx = points[j, 0] - (center[k, 0] + velocity[k, 0] * dt)
        vy = points[j, 1] - (center[k, 1] + velocity[k, 1] * dt)
        vz = points[j, 2] - (center[k, 2] + velocity[k, 2] * dt)
        yaw = heading[k] + yaw_rate[k] * dt
        c, s = np.cos(yaw), np.sin(yaw)
        ct, st, cr, sr = 1.0, 0.0, 1.0, 0.0
        if has_tilt:
            ct, st, cr, sr = np.cos(pitch[k]), np.sin(pitch[k]), np.cos(roll[k]), np.sin(roll[k])
        q0, q1, q2 = _to_box(vx, vy, vz, c, s, ct, st, cr, sr, has_tilt)
        if abs(q0) <= size[k, 0] / 2.0 + margin and abs(q1) <= size[k, 1] / 2.0 + margin and \
                abs(q2) <= size[k, 2] / 2.0 + margin:
            local[m, 0], local[m, 1], local[m, 2] = q0, q1, q2
            if has_tilt:
                ry, rz = cr * q1 - sr * q2, sr * q1 + cr * q2
                b0, b1, b2 = ct * q0 + st * rz, ry, -st * q0 + ct * rz
            else:
                b0, b1, b2 = q0, q1, q2
            ch, sh = np.cos(heading[k]), np.sin(heading[k])
            vehicle[m, 0] = (ch * b0 - sh * b1) + center[k, 0]
            vehicle[m, 1] = (sh * b0 + ch * b1) + center[k, 1]
            vehicle[m, 2] = b2 + center[k, 2]
            kept[m] = o
            at[m] = i
            m += 1
    return m


def frame_time_candidates(points, index, owner, rows, offsets, label_offset_s, center, heading, velocity,
                          yaw_rate, pitch, roll, size, margin):
    """(body points float64 [P, 3], vehicle-frame points float64 [P, 3], owner int64 [P], position
    int64 [P] in ``index``) of the candidates that lie in their grown box once moved to the box's
    time. The fused twin of ``drivetrack.refine.scene._frame_time_candidates`` (same arguments and
    results)."""
    def f64(a):
        return np.ascontiguousarray(a, dtype=np.float64)

    n = index.shape[0]
    has_tilt = pitch is not None or roll is not None
    row_count = center.shape[0]
    zeros = np.zeros(row_count)
    local, vehicle, kept, at = np.empty((n, 3)), np.empty((n, 3)), np.empty(n, np.int64), np.empty(n, np.int64)
    m = _frame_time_kernel(f64(points), np.ascontiguousarray(index, dtype=np.int64),
                           np.ascontiguousarray(owner, dtype=np.int64), np.ascontiguousarray(rows, dtype=np.int64),
                           np.ascontiguousarray(offsets),
                           zeros if label_offset_s is None else f64(label_offset_s), label_offset_s is not None,
                           f64(center), f64(heading), f64(velocity), f64(yaw_rate),
                           zeros if pitch is None else f64(pitch), zeros if roll is None else f64(roll), has_tilt,
                           f64(size), float(margin), local, vehicle, kept, at)
    return local[:m].copy(), vehicle[:m].copy(), kept[:m].copy(), at[:m].copy()


@njit(cache=True, nogil=True, inline="always")
def _trig(heading, tilt, has_tilt, t):
    c, s = np.cos(heading[t]), np.sin(heading[t])
    ct, st, cr, sr = 1.0, 0.0, 1.0, 0.0
    if has_tilt:
        ct, st, cr, sr = np.cos(tilt[t, 0]), np.sin(tilt[t, 0]), np.cos(tilt[t, 1]), np.sin(tilt[t, 1])
    return c, s, ct, st, cr, sr


@njit(cache=True, nogil=True, inline="always")
def _to_box(x, y, z, c, s, ct, st, cr, sr, has_tilt):
    """``R^T v`` of vector (x, y, z): ``vectors_to_box`` operation for operation."""
    ux, uy, uz = c * x + s * y, -s * x + c * y, z                 # Rz^T
    if has_tilt:
        vx, vz = ct * ux - st * uz, st * ux + ct * uz             # Ry^T
        ux, uy, uz = vx, cr * uy + sr * vz, -sr * uy + cr * vz    # Rx^T
    return ux, uy, uz


@njit(cache=True, nogil=True, inline="always")
def _body(points, i, center, t, c, s, ct, st, cr, sr, has_tilt):
    """Body point of row i in frame t's box."""
    return _to_box(points[i, 0] - center[t, 0], points[i, 1] - center[t, 1], points[i, 2] - center[t, 2],
                   c, s, ct, st, cr, sr, has_tilt)


@njit(cache=True, nogil=True)
def _select_kernel(points, start, counts, half, cap, center, heading, tilt, has_tilt, margin, clearance,
                   q, frame, rows):
    m = 0
    for t in range(start.shape[0]):
        c, s, ct, st, cr, sr = _trig(heading, tilt, has_tilt, t)
        hx, hy, hz = half[t, 0] + margin, half[t, 1] + margin, half[t, 2]
        kept = 0
        for i in range(start[t], start[t] + counts[t]):
            if kept == cap:
                break
            ux, uy, uz = _body(points, i, center, t, c, s, ct, st, cr, sr, has_tilt)
            if abs(ux) <= hx and abs(uy) <= hy and uz <= hz + margin and uz >= -hz + clearance:
                q[m, 0], q[m, 1], q[m, 2] = ux, uy, uz
                frame[m] = t
                rows[m] = i
                m += 1
                kept += 1
    return m


@njit(cache=True, nogil=True)
def _inside_counts_kernel(points, start, counts, half, center, heading, tilt, has_tilt, margin, clearance, out):
    for t in range(start.shape[0]):
        c, s, ct, st, cr, sr = _trig(heading, tilt, has_tilt, t)
        hx, hy, hz = half[t, 0] + margin, half[t, 1] + margin, half[t, 2]
        n = 0
        for i in range(start[t], start[t] + counts[t]):
            ux, uy, uz = _body(points, i, center, t, c, s, ct, st, cr, sr, has_tilt)
            if abs(ux) <= hx and abs(uy) <= hy and uz <= hz + margin and uz >= -hz + clearance:
                n += 1
        out[t] = n


def inside_counts(points: np.ndarray, frame: np.ndarray, half: np.ndarray, center: np.ndarray,
                  heading: np.ndarray, tilt: np.ndarray | None, margin: float, clearance: float) -> np.ndarray:
    """int64 [T]: per frame, how many of ``points`` [N, 3] (vehicle frame, metres; ``frame`` int [N]
    non-decreasing, 0..T-1) lie inside the frame's box (centre [T, 3], heading [T], tilt [T, 2] or
    None, half-size [T, 3]) grown by ``margin`` and at least ``clearance`` above its bottom.
    Reference: ``np.bincount(frame[_inside(_body_points(...), ...)])`` (``drivetrack.refine.select``)."""
    t_count = center.shape[0]
    counts = np.bincount(frame, minlength=t_count).astype(np.int64)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    out = np.zeros(t_count, np.int64)
    f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)   # noqa: E731
    _inside_counts_kernel(f64(points), start, counts, f64(half), f64(center), f64(heading),
                          np.zeros((0, 2)) if tilt is None else f64(tilt), tilt is not None, float(margin),
                          float(clearance), out)
    return out


def select(points: np.ndarray, start: np.ndarray, counts: np.ndarray, half: np.ndarray, cap: int,
           center: np.ndarray, heading: np.ndarray, tilt: np.ndarray | None, margin: float,
           clearance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(body points float64 [P, 3], frames int64 [P], rows int64 [P]): per frame t the first
    ``cap`` of its rows ``[start[t], start[t] + counts[t])`` of ``points`` [N, 3] (vehicle frame,
    metres; each frame's rows in priority order) that lie inside the box (centre [T, 3], heading
    [T], tilt [T, 2] = (pitch, roll) or None, half-size ``half`` [T, 3]) grown by ``margin`` and at
    least ``clearance`` above its bottom, in row order. Reference:
    ``drivetrack.refine.select._Selection.select`` (the same subset and body points)."""
    t_count = start.shape[0]
    size = int(min(points.shape[0], cap * t_count))
    q = np.empty((size, 3))
    frame = np.empty(size, np.int64)
    rows = np.empty(size, np.int64)
    f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)   # noqa: E731
    m = _select_kernel(f64(points), np.ascontiguousarray(start, dtype=np.int64),
                       np.ascontiguousarray(counts, dtype=np.int64), f64(half), int(cap), f64(center), f64(heading),
                       np.zeros((0, 2)) if tilt is None else f64(tilt), tilt is not None, float(margin),
                       float(clearance), q, frame, rows)
    return q[:m], frame[:m], rows[:m]


@njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _cholesky_solve_kernel(a, b):
    n = a.shape[0]
    first = np.empty(n, np.int64)          # envelope: row i of L is zero left of first[i]
    for i in range(n):
        f = i
        for j in range(i):
            if a[i, j] != 0.0:
                f = j
                break
        first[i] = f
    for i in range(n):
        fi = first[i]
        row_i = a[i]
        for j in range(fi, i + 1):
            row_j = a[j]
            s = 0.0
            for k in range(max(fi, first[j]), j):
                s += row_i[k] * row_j[k]
            s = row_i[j] - s
            if j < i:
                a[i, j] = s / a[j, j]
            elif s > 0.0:
                a[i, i] = np.sqrt(s)
            else:
                return False
    for i in range(n):                     # L y = b
        s = b[i]
        for k in range(first[i], i):
            s -= a[i, k] * b[k]
        b[i] = s / a[i, i]
    for i in range(n - 1, -1, -1):         # L^T x = y
        b[i] /= a[i, i]
        xi = b[i]
        for k in range(first[i], i):
            b[k] -= a[i, k] * xi
    return True


def cholesky_solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """float64 [n]: ``a^-1 b`` for a symmetric positive definite a [n, n] (its lower triangle is
    read) and b [n], by a single-threaded Cholesky factorisation on the envelope of ``a`` (rows
    are zero left of their first non-zero, fill-in stays inside): dense for the normal equations
    of short clips, where every frame pairs with every other, and banded-like on long clips.
    All NaN when ``a`` is not positive definite. Reference: ``scipy.linalg.cho_solve``."""
    a = np.array(a, dtype=np.float64, order="C")
    x = np.array(b, dtype=np.float64)
    if a.ndim != 2 or a.shape[0] != a.shape[1] or x.shape != (a.shape[0],):
        raise ValueError(f"cholesky_solve: a must be [n, n] and b [n], got {a.shape} and {x.shape}")
    if not _cholesky_solve_kernel(a, x):
        x[:] = np.nan
    return x
