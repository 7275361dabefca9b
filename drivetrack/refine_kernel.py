"""Fused numba kernels of the pose refinement's inner loop (``drivetrack.refine``).

Three pieces of a Gauss-Newton iteration that numpy/scipy do with large temporaries or a general
tree, each with the numpy/scipy reference it must reproduce:

- :func:`knn`: exact k nearest neighbours of every point among the same points (itself
  included, distance 0), ascending. Reference: ``scipy.spatial.cKDTree(p).query(p, k)``. A dense
  voxel grid (the object's points fill a few metres) searched in growing Chebyshev shells until the
  k-th distance is inside the searched block; ties are broken by the lower index.
- :func:`normals`: PCA normals and planarity of neighbour lists, the same closed-form 3x3 eigen
  decomposition as ``drivetrack.refine._normals`` (same formulas, same order of operations).
- :func:`normal_equations`: the dense [4T, 4T] normal equations and gradient of weighted
  point-to-plane pairs (8 Jacobian non-zeros per pair), as ``drivetrack.refine._pair_terms``
  assembles them with ``np.bincount``.

numba compiles on first use and caches the machine code on disk (``cache=True``).
"""
from __future__ import annotations

import numpy as np

__all__ = ["NUMBA_AVAILABLE", "knn", "normals", "normal_equations"]

try:  # numba is a declared dependency; the numpy path remains when it cannot be imported
    from numba import njit
    NUMBA_AVAILABLE = True
except ImportError:  # pragma: no cover - exercised only in environments without numba
    NUMBA_AVAILABLE = False

    def njit(*args, **kwargs):
        def wrap(fn):
            return fn
        return wrap

#: at most this many grid cells; the cell grows beyond ``cell_m`` to respect it
_MAX_CELLS = 1 << 22


@njit(cache=True, nogil=True)
def _knn_grid(points, k, cell, dist, index):
    n = points.shape[0]
    lo = np.empty(3)
    dims = np.empty(3, np.int64)
    for a in range(3):
        lo[a] = points[:, a].min()
        dims[a] = int((points[:, a].max() - lo[a]) / cell) + 1
    ncell = dims[0] * dims[1] * dims[2]
    ci = np.empty((n, 3), np.int64)
    key = np.empty(n, np.int64)
    for i in range(n):
        for a in range(3):
            c = int((points[i, a] - lo[a]) / cell)
            ci[i, a] = min(max(c, 0), dims[a] - 1)
        key[i] = (ci[i, 0] * dims[1] + ci[i, 1]) * dims[2] + ci[i, 2]
    order = np.argsort(key, kind="mergesort")              # stable: index order within a cell
    start = np.zeros(ncell + 1, np.int64)
    for i in range(n):
        start[key[i] + 1] += 1
    for c in range(ncell):
        start[c + 1] += start[c]
    max_ring = max(dims[0], max(dims[1], dims[2]))
    best_d = np.empty(k)
    best_i = np.empty(k, np.int64)
    for i in range(n):
        found = 0
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        r = 0
        while True:
            for di in range(-r, r + 1):
                gi = ci[i, 0] + di
                if gi < 0 or gi >= dims[0]:
                    continue
                for dj in range(-r, r + 1):
                    gj = ci[i, 1] + dj
                    if gj < 0 or gj >= dims[1]:
                        continue
                    for dk in range(-r, r + 1):
                        if abs(di) != r and abs(dj) != r and abs(dk) != r:
                            continue                        # inner cells: scanned at a smaller r
                        gk = ci[i, 2] + dk
                        if gk < 0 or gk >= dims[2]:
                            continue
                        c = (gi * dims[1] + gj) * dims[2] + gk
                        if start[c] == start[c + 1]:
                            continue
                        if found == k:                  # skip cells farther than the k-th so far
                            gap = 0.0
                            for a, g in ((0, gi), (1, gj), (2, gk)):
                                p = points[i, a]
                                cell_lo = lo[a] + g * cell
                                if p < cell_lo:
                                    gap += (cell_lo - p) ** 2
                                elif p > cell_lo + cell:
                                    gap += (p - cell_lo - cell) ** 2
                            if gap > best_d[k - 1]:
                                continue
                        for s in range(start[c], start[c + 1]):
                            j = order[s]
                            d = (points[j, 0] - x) ** 2 + (points[j, 1] - y) ** 2 + (points[j, 2] - z) ** 2
                            if found == k and (d > best_d[k - 1] or (d == best_d[k - 1] and j > best_i[k - 1])):
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
            # every point closer to point i than the faces of the block of rings <= r is in it
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


def knn(points: np.ndarray, k: int, cell_m: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
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
def _normals_kernel(model, neighbours, normal, planarity):
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
    ``model`` [*, 3]; see ``drivetrack.refine._normals`` (the reference)."""
    neighbours = np.ascontiguousarray(neighbours, dtype=np.int64)
    normal = np.empty((neighbours.shape[0], 3))
    planarity = np.empty(neighbours.shape[0])
    _normals_kernel(np.ascontiguousarray(model, dtype=np.float64), neighbours, normal, planarity)
    return normal, planarity


@njit(cache=True, nogil=True)
def _normal_equations_kernel(n, qa, qb, heading_a, heading_b, fa, fb, w, r, hessian, gradient):
    jac = np.empty(8)
    col = np.empty(8, np.int64)
    for i in range(n.shape[0]):
        for side in range(2):
            q = qa if side == 0 else qb
            psi = heading_a[i] if side == 0 else heading_b[i]
            sign = 1.0 if side == 0 else -1.0
            c, s = np.cos(psi), np.sin(psi)
            o = 4 * side
            jac[o + 0] = -sign * (c * n[i, 0] - s * n[i, 1])
            jac[o + 1] = -sign * (s * n[i, 0] + c * n[i, 1])
            jac[o + 2] = -sign * n[i, 2]
            jac[o + 3] = sign * (n[i, 0] * q[i, 1] - n[i, 1] * q[i, 0])
            f = fa[i] if side == 0 else fb[i]
            for m in range(4):
                col[o + m] = 4 * f + m
        wi, wr = w[i], w[i] * r[i]
        for a in range(8):
            gradient[col[a]] += jac[a] * wr
            wa = wi * jac[a]
            for b in range(8):
                hessian[col[a], col[b]] += wa * jac[b]


def normal_equations(n: np.ndarray, qa: np.ndarray, qb: np.ndarray, heading_a: np.ndarray,
                     heading_b: np.ndarray, fa: np.ndarray, fb: np.ndarray, w: np.ndarray, r: np.ndarray,
                     t_count: int) -> tuple[np.ndarray, np.ndarray]:
    """(hessian float64 [4T, 4T], gradient float64 [4T]) of pairs with body normals n [C, 3],
    body points qa, qb [C, 3] of frames fa, fb [C] at headings heading_a, heading_b [C] (radians),
    weights w [C] and residuals r [C]; see ``drivetrack.refine._pair_terms`` (the reference)."""
    hessian = np.zeros((4 * t_count, 4 * t_count))
    gradient = np.zeros(4 * t_count)
    f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)   # noqa: E731
    _normal_equations_kernel(f64(n), f64(qa), f64(qb), f64(heading_a), f64(heading_b),
                             np.ascontiguousarray(fa, dtype=np.int64), np.ascontiguousarray(fb, dtype=np.int64),
                             f64(w), f64(r), hessian, gradient)
    return hessian, gradient
