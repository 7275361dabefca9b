"""The data term: model normals, leave-one-frame-out association, point-to-plane normal equations."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivetrack.refine.config import RefineConfig, _use_kernel
from drivetrack.refine.select import _Selection


def _normals(model: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals float64 [P, 3] by PCA over neighbour lists int [P, k] into ``model`` [*, 3],
    and the planarity float64 [P] ((l2 - l1) / l3 of the eigenvalues l1 <= l2 <= l3) of each.

    Closed-form eigen-decomposition of the 3x3 covariances (trigonometric solution of the
    characteristic cubic; the normal is the largest cross product of two rows of ``C - l1 I``):
    an order of magnitude cheaper than batched LAPACK on thousands of 3x3 matrices. The sign of
    a normal is arbitrary (residual and Jacobian flip together).
    """
    gathered = model[neighbours]                                           # [P, k, 3]
    mean_point = gathered.mean(axis=1)
    cov = np.matmul(gathered.transpose(0, 2, 1), gathered) / neighbours.shape[1] \
        - mean_point[:, :, None] * mean_point[:, None, :]
    off = cov[:, 0, 1] ** 2 + cov[:, 0, 2] ** 2 + cov[:, 1, 2] ** 2
    mean = np.trace(cov, axis1=1, axis2=2) / 3.0
    diag = np.diagonal(cov, axis1=1, axis2=2) - mean[:, None]
    p = np.sqrt(((diag ** 2).sum(axis=1) + 2.0 * off) / 6.0)
    safe = np.where(p > 0, p, 1.0)
    b = (cov - mean[:, None, None] * np.eye(3)) / safe[:, None, None]
    half_det = np.clip(np.linalg.det(b) / 2.0, -1.0, 1.0)
    phi = np.arccos(half_det) / 3.0
    l3 = mean + 2.0 * p * np.cos(phi)                                      # largest
    l1 = mean + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)                  # smallest
    l2 = 3.0 * mean - l1 - l3
    m = cov - l1[:, None, None] * np.eye(3)
    crosses = np.stack([np.cross(m[:, 0], m[:, 1]), np.cross(m[:, 0], m[:, 2]), np.cross(m[:, 1], m[:, 2])], axis=1)
    norms = np.linalg.norm(crosses, axis=-1)                               # [P, 3]
    best = np.argmax(norms, axis=1)
    rows = np.arange(cov.shape[0])
    normal = crosses[rows, best] / np.maximum(norms[rows, best], 1e-300)[:, None]
    normal[norms[rows, best] == 0] = (0.0, 0.0, 1.0)                       # isotropic: any direction
    planarity = (l2 - l1) / np.maximum(l3, 1e-12)
    return normal, planarity


@dataclass
class _Data:
    """Point-to-plane terms at the current state: dense normal equations and diagnostics."""
    hessian: np.ndarray      # [4T, 4T] (dense: cheaper to accumulate than sparse, measured)
    gradient: np.ndarray     # [4T]
    residual: np.ndarray     # [C] point-to-plane residuals of correspondences
    frame: np.ndarray        # [C] frame of the query point
    scale: float             # robust scale of residual (metres)
    num_points: np.ndarray   # [T] returns taking part


@dataclass
class _Pairs:
    """Correspondences of one association, at the state they were found at.

    A pair joins a used return ``a`` (row ``src`` of the selection, frame ``fa``) with its
    nearest model point ``b`` of another frame (row ``dst``, frame ``fb``); ``qa``, ``qb`` are
    their body points and ``normal`` the model normal at ``b`` (body frame), all at the state of
    the association (the terms are always evaluated there: nothing is transformed twice).
    """
    src: np.ndarray             # int64 [C] rows into the selection's points
    dst: np.ndarray             # int64 [C]
    fa: np.ndarray              # int64 [C]
    fb: np.ndarray              # int64 [C]
    qa: np.ndarray              # float64 [C, 3] body points of a
    qb: np.ndarray              # float64 [C, 3] body points of b
    normal: np.ndarray          # float64 [C, 3] unit body normal at b
    planarity_weight: np.ndarray    # float64 [C] in [0, 1]
    num_points: np.ndarray      # int64 [T]


def _point_jacobian(n: np.ndarray, q: np.ndarray, heading: np.ndarray, tilt: np.ndarray | None = None) -> np.ndarray:
    """float64 [C, 4] (yaw only: d (n . q) / d (c, psi) for body points q = Rz(-psi) (x - c)) or,
    with tilt [C, 2] = (pitch theta, roll phi), float64 [C, 6]: d (n . q) / d (c, psi, theta, phi)
    for q = Rx(-phi) Ry(-theta) Rz(-psi) (x - c), body normals n [C, 3] held fixed.

    With v = Rx q, u = Ry v (= Rz^T (x - c)), k = Rx n, m = Ry k:
    dq/dc = -R^T, so d/dc = -(Rz m); d/dpsi = m . (u_y, -u_x, 0); d/dtheta = k . (-v_z, 0, v_x);
    d/dphi = n . (0, q_z, -q_y)."""
    if tilt is None:
        c, s = np.cos(heading), np.sin(heading)
        return np.stack([-(c * n[:, 0] - s * n[:, 1]), -(s * n[:, 0] + c * n[:, 1]), -n[:, 2],
                         n[:, 0] * q[:, 1] - n[:, 1] * q[:, 0]], axis=-1)
    ct, st, cr, sr = np.cos(tilt[:, 0]), np.sin(tilt[:, 0]), np.cos(tilt[:, 1]), np.sin(tilt[:, 1])
    vy, vz = cr * q[:, 1] - sr * q[:, 2], sr * q[:, 1] + cr * q[:, 2]          # v = Rx q (v_x = q_x)
    ux, uy = ct * q[:, 0] + st * vz, vy                                        # u = Ry v
    ky, kz = cr * n[:, 1] - sr * n[:, 2], sr * n[:, 1] + cr * n[:, 2]          # k = Rx n (k_x = n_x)
    mx, mz = ct * n[:, 0] + st * kz, -st * n[:, 0] + ct * kz                   # m = Ry k (m_y = k_y)
    c, s = np.cos(heading), np.sin(heading)
    return np.stack([-(c * mx - s * ky), -(s * mx + c * ky), -mz, mx * uy - ky * ux,
                     -n[:, 0] * vz + kz * q[:, 0], n[:, 1] * q[:, 2] - n[:, 2] * q[:, 1]], axis=-1)


#: :func:`normal_neighbours`: the returns a frame's subset holds at which a model normal takes
#: ``RefineConfig.normal_neighbours`` of them (the cap of earlier defaults)
NORMALS_REFERENCE_POINTS_PER_FRAME = 120


def normal_neighbours(config: RefineConfig, num_points: np.ndarray) -> int:
    """The model points in the PCA of a model normal: ``config.normal_neighbours`` while the
    frames' subsets hold :data:`NORMALS_REFERENCE_POINTS_PER_FRAME` returns or fewer (median over
    the frames with any, ``num_points`` int [T]), more in proportion when they hold more (a near
    object under ``max_points_per_frame`` 400: 40), so that a normal is fitted over the same
    patch of surface however densely the frames are sampled, and 2 cm of range noise does not
    turn it (docs/refinement.md, "Returns per frame")."""
    present = num_points[num_points > 0]
    per_frame = float(np.median(present)) if present.size else 0.0
    return int(round(config.normal_neighbours * max(1.0, per_frame / NORMALS_REFERENCE_POINTS_PER_FRAME)))


def _associate(selection: _Selection, center: np.ndarray, heading: np.ndarray, gate_m: float,
               config: RefineConfig, t_count: int, tilt: np.ndarray | None = None) -> _Pairs | None:
    """Correspondences at state (center, heading): one ``cKDTree`` over all used body points,
    one k-nearest query serving both the leave-one-frame-out association (within ``gate_m``) and
    the neighbourhood of each target's PCA normal. None when there is too little to pair."""
    from scipy.spatial import cKDTree

    q, f, rows = selection.select(center, heading, config.inlier_margin_m, config.ground_clearance_m, tilt)
    num_points = np.bincount(f, minlength=t_count).astype(np.int64)
    if q.shape[0] < 4 or np.count_nonzero(num_points) < 2:
        return _Pairs(*(np.zeros(0, np.int64),) * 4, *(np.zeros((0, 3)),) * 3, np.zeros(0), num_points)
    kn = normal_neighbours(config, num_points)
    k = int(min(max(config.association_neighbours, kn), q.shape[0]))
    use_kernel = _use_kernel(config)
    if use_kernel:                                                       # one query serves both uses
        from drivetrack.refine import kernel

        dist, nbr = kernel.knn(q, k)
    else:
        dist, nbr = cKDTree(q).query(q, k=k)
        dist, nbr = dist.reshape(-1, k), nbr.reshape(-1, k)
    ka = min(config.association_neighbours, k)
    other = (dist[:, :ka] <= gate_m) & (f[nbr[:, :ka]] != f[:, None])    # leave-one-frame-out
    has = other.any(axis=1)
    first = np.argmax(other, axis=1)
    src = np.flatnonzero(has)
    dst = nbr[src, first[src]]
    targets, target_of = np.unique(dst, return_inverse=True)
    neighbours = nbr[targets, :min(kn, k)]
    normal_t, planarity_t = (kernel.normals(q, neighbours) if use_kernel else _normals(q, neighbours))
    weight = np.clip(planarity_t[target_of] / config.min_planarity, 0.0, 1.0)
    return _Pairs(rows[src], rows[dst], f[src], f[dst], q[src], q[dst], normal_t[target_of], weight, num_points)


def _pair_terms(selection: _Selection, pairs: _Pairs | None, center: np.ndarray, heading: np.ndarray,
                config: RefineConfig, t_count: int, normal_equations: bool = True,
                tilt: np.ndarray | None = None) -> _Data:
    """Point-to-plane normal equations of the correspondences ``pairs``, found at state
    (center, heading[, tilt]) (their body points and normals are at that state).

    The residual ``n . (q_a - q_b)`` depends on both poses, so both move (2 x 4 Jacobian non-zeros
    per row, 2 x 6 with tilt, accumulated straight into the dense [DT, DT] normal equations, D = 4
    or 6); the normal rotates with frame b's pose. ``normal_equations=False`` computes the
    residuals only.
    """
    dof = 4 if tilt is None else 6
    n_state = dof * t_count
    num_points = pairs.num_points if pairs is not None else np.zeros(t_count, np.int64)
    if pairs is None or pairs.src.size < 4:
        return _Data(np.zeros((n_state, n_state)), np.zeros(n_state), np.zeros(0), np.zeros(0, np.int64),
                     float("nan"), num_points)
    fa, fb = pairs.fa, pairs.fb
    qa, qb, n = pairs.qa, pairs.qb, pairs.normal
    r = np.einsum("ni,ni->n", n, qa - qb)
    scale = max(1.4826 * float(np.median(np.abs(r))), config.point_sigma_floor_m)
    if not normal_equations:
        return _Data(np.zeros((0, 0)), np.zeros(0), r, fa, scale, num_points)
    w = np.minimum(1.0, config.huber_k * scale / np.maximum(np.abs(r), 1e-12)) / scale ** 2
    w = w * pairs.planarity_weight
    if _use_kernel(config):
        from drivetrack.refine import kernel

        hessian, gradient = kernel.normal_equations(n, qa, qb, fa, fb, w, r, heading, tilt)
        return _Data(hessian, gradient, r, fa, scale, num_points)
    tilt_a, tilt_b = (None, None) if tilt is None else (tilt[fa], tilt[fb])
    jac = np.concatenate([_point_jacobian(n, qa, heading[fa], tilt_a),
                          -_point_jacobian(n, qb, heading[fb], tilt_b)], axis=1)                  # [C, 2D]
    cols = np.concatenate([dof * fa[:, None] + np.arange(dof), dof * fb[:, None] + np.arange(dof)], axis=1)
    blocks = (w[:, None, None] * jac[:, :, None] * jac[:, None, :]).reshape(-1)           # [C * 4D^2]
    flat = (cols[:, :, None] * n_state + cols[:, None, :]).reshape(-1)
    hessian = np.bincount(flat, weights=blocks, minlength=n_state * n_state).reshape(n_state, n_state)
    gradient = np.bincount(cols.reshape(-1), weights=(jac * (w * r)[:, None]).reshape(-1), minlength=n_state)
    return _Data(hessian, gradient, r, fa, scale, num_points)


def _data_terms(selection: _Selection, center: np.ndarray, heading: np.ndarray, gate_m: float,
                config: RefineConfig, t_count: int, normal_equations: bool = True,
                tilt: np.ndarray | None = None) -> _Data:
    """Associate at (center, heading[, tilt]) within ``gate_m`` and evaluate the terms there."""
    pairs = _associate(selection, center, heading, gate_m, config, t_count, tilt)
    return _pair_terms(selection, pairs, center, heading, config, t_count, normal_equations, tilt)
