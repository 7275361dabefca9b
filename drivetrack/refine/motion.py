"""The motion model: constant velocity and yaw rate in the world (and, softly, constant
acceleration: the jerk term), as a linear residual operator."""
from __future__ import annotations

import numpy as np

from drivetrack.geometry import box_from_center_heading, tilt_from_poses
from drivetrack.refine.config import RefineConfig


def _world_tilt_offset(world_from_vehicle: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """float64 [T, 2]: (pitch, roll) in the world of a box of heading ``heading`` [T] and no tilt in
    the vehicle frame, i.e. the ego's tilt seen in the box's axes (to first order the world tilt
    of a box is its vehicle-frame tilt plus this)."""
    return tilt_from_poses(world_from_vehicle[:, :3, :3] @ box_from_center_heading(np.zeros((heading.size, 3)),
                                                                                  heading)[:, :3, :3])


def _motion_operator(world_from_vehicle: np.ndarray, timestamps_s: np.ndarray, config: RefineConfig,
                     heading: np.ndarray | None = None):
    """Linear motion-model residuals ``e = S x + e0`` over the stacked state x [DT].

    Rows: for every interior frame, the second divided difference of the world centre (3 rows,
    over ``accel_sigma_mps2``) and of the world heading (1 row, over ``yaw_accel_sigma_radps2``);
    then, with ``jerk_sigma_mps3`` set and T >= 4, the world centre's jerk over every four
    consecutive frames (3 rows each, :func:`_jerk_operator`).
    World centre of frame t: ``R_t c_t + p_t``; world heading: ``psi_t + yaw(R_t)`` (unwrapped).
    With ``heading`` [T] given (the labels' headings, radians), the state has D = 6 per frame and
    two more rows: the second divided difference of the world pitch and roll (over
    ``tilt_accel_sigma_radps2``), linearised as ``tilt_t + _world_tilt_offset(t)``: the ego's own
    pitch and roll (braking, turning, bumps) are in ``world_from_vehicle`` and must not be asked of
    the object. Returns (S scipy.sparse csr [R, DT], e0 float64 [R]) with R = D(T-2), plus 3(T-3)
    with the jerk term, or (None, None) when T < 3.
    """
    import scipy.sparse as sp

    t_count = timestamps_s.shape[0]
    dof = 4 if heading is None else 6
    if t_count < 3:
        return None, None
    dt = np.diff(timestamps_s)
    dt1, dt2 = dt[:-1], dt[1:]
    coef = np.stack([2.0 / (dt1 * (dt1 + dt2)), -2.0 / (dt1 * dt2), 2.0 / (dt2 * (dt1 + dt2))], axis=-1)  # [T-2, 3]
    rotation = world_from_vehicle[:, :3, :3]
    offset = world_from_vehicle[:, :3, 3]
    yaw_w = np.unwrap(np.arctan2(rotation[:, 1, 0], rotation[:, 0, 0]))
    interior = np.arange(1, t_count - 1)
    frames = interior[:, None] + np.arange(-1, 2)[None, :]                  # [T-2, 3]
    sigma = np.array([config.accel_sigma_mps2, config.accel_sigma_mps2, config.vertical_accel_sigma_mps2])
    rows, cols, vals = [], [], []
    base_row = dof * (interior - 1)
    for k in range(3):                                                      # 3 frames per stencil
        fk = frames[:, k]
        for a in range(3):                                                  # world axis (row)
            for b in range(3):                                              # state centre axis
                rows.append(base_row + a)
                cols.append(dof * fk + b)
                vals.append(coef[:, k] * rotation[fk, a, b] / sigma[a])
        rows.append(base_row + 3)
        cols.append(dof * fk + 3)
        vals.append(coef[:, k] / config.yaw_accel_sigma_radps2)
        if dof == 6:
            for a in (4, 5):                                                # pitch, roll
                rows.append(base_row + a)
                cols.append(dof * fk + a)
                vals.append(coef[:, k] / config.pitch_roll_accel_sigma_radps2)
    S = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(dof * (t_count - 2), dof * t_count))
    e0 = np.zeros(dof * (t_count - 2))
    e0_pos = np.einsum("tk,tki->ti", coef, offset[frames]) / sigma
    e0_yaw = np.einsum("tk,tk->t", coef, yaw_w[frames]) / config.yaw_accel_sigma_radps2
    e0.reshape(-1, dof)[:, :3] = e0_pos
    e0.reshape(-1, dof)[:, 3] = e0_yaw
    if dof == 6:
        tilt_w = _world_tilt_offset(world_from_vehicle, heading)            # [T, 2]
        e0.reshape(-1, dof)[:, 4:] = np.einsum("tk,tka->ta", coef, tilt_w[frames]) / config.pitch_roll_accel_sigma_radps2
    if config.jerk_sigma_mps3 is not None and t_count >= 4:
        S_jerk, e0_jerk = _jerk_operator(rotation, offset, timestamps_s, dof, config.jerk_sigma_mps3)
        S = sp.vstack([S, S_jerk]).tocsr()
        e0 = np.concatenate([e0, e0_jerk])
    return S, e0


def _jerk_operator(rotation: np.ndarray, offset: np.ndarray, timestamps_s: np.ndarray, dof: int, sigma: float):
    """Rows ``(S [3(T-3), dof T] csr, e0 [3(T-3)])`` of the world centre's jerk over ``sigma``
    (m/s^3): per four consecutive frames, 6 x their third divided difference (exact for a cubic
    in time, any spacing) of ``R_t c_t + p_t`` (``rotation`` [T, 3, 3], ``offset`` [T, 3]: the
    frames' ``world_from_vehicle``)."""
    import scipy.sparse as sp

    t_count = timestamps_s.shape[0]
    frames, coef = _divided_differences(timestamps_s, 3)                     # [T-3, 4] each
    base_row = 3 * np.arange(t_count - 3)
    rows, cols, vals = [], [], []
    for k in range(4):
        fk = frames[:, k]
        for a in range(3):
            for b in range(3):
                rows.append(base_row + a)
                cols.append(dof * fk + b)
                vals.append(coef[:, k] * rotation[fk, a, b] / sigma)
    S = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(3 * (t_count - 3), dof * t_count))
    e0 = (np.einsum("tk,tki->ti", coef, offset[frames]) / sigma).reshape(-1)
    return S, e0


#: :func:`jerk_sigma_from_labels`: the acceleration stiffnesses (m/s^2) and label noises (metres)
#: each candidate jerk stiffness's evidence is maximised over (nuisance parameters: a car that
#: brakes steadily needs a loose acceleration term, labels drawn to a centimetre a tight noise)
EVIDENCE_ACCEL_SIGMAS_MPS2 = (0.5, 2.0, 8.0)
EVIDENCE_LABEL_SIGMAS_M = (0.01, 0.02, 0.05, 0.1)


def _divided_differences(timestamps_s: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray]:
    """(frames int [T - order, order + 1], coefficients float64 [T - order, order + 1]) of
    ``order``! x the ``order``-th divided difference over every ``order + 1`` consecutive samples
    at ``timestamps_s`` [T] (seconds, increasing): exact for a polynomial of that degree at any
    spacing."""
    t_count = timestamps_s.shape[0]
    frames = np.arange(t_count - order)[:, None] + np.arange(order + 1)[None, :]
    times = timestamps_s[frames]
    diff = times[:, :, None] - times[:, None, :]                             # [R, order + 1, order + 1]
    diff[:, np.arange(order + 1), np.arange(order + 1)] = 1.0
    return frames, float(np.prod(np.arange(1, order + 1))) / diff.prod(axis=2)


def _difference_gram(timestamps_s: np.ndarray, order: int, bands: int) -> np.ndarray:
    """float64 [bands + 1, T]: ``D' D`` in the upper banded form of ``scipy.linalg.cholesky_banded``
    (``bands`` >= ``order``), D [T - order, T] the rows of ``order``! x the ``order``-th divided
    difference over every ``order + 1`` consecutive samples at ``timestamps_s`` [T] (seconds,
    increasing): exact for a polynomial of that degree at any spacing (2: the acceleration rows
    of :func:`_motion_operator`, 3: the jerk rows of :func:`_jerk_operator`)."""
    t_count = timestamps_s.shape[0]
    frames, coef = _divided_differences(timestamps_s, order)                          # [R, order + 1]
    first = frames[:, 0]
    gram = np.zeros((bands + 1, t_count))
    for a in range(order + 1):
        for b in range(a, order + 1):
            np.add.at(gram[bands - (b - a)], first + b, coef[:, a] * coef[:, b])
    return gram


def _log_evidence(values: np.ndarray, accel_gram: np.ndarray, jerk_gram: np.ndarray, accel_sigma: float,
                  jerk_sigma: float, label_sigmas: tuple[float, ...]) -> float:
    """The largest over ``label_sigmas`` of the log marginal likelihood of ``values`` float [T, D]
    (D independent axes, metres) under the motion prior ``exp(-x' P x / 2)``, ``P = accel_gram /
    accel_sigma^2 + jerk_gram / jerk_sigma^2`` (banded grams, :func:`_difference_gram`; improper
    along the straight lines at constant speed, which it leaves free) and white label noise of
    that sigma, up to a constant shared by every (accel_sigma, jerk_sigma, label sigma):
    ``-1/2 (lam |y|^2 - lam^2 y' M^-1 y) - 1/2 log det M + T/2 log lam + 1/2 log pdet P`` per axis,
    ``M = P + lam I``, ``lam = label_sigma^-2``. ``log pdet P`` is ``log det`` of P without its
    first two rows and columns (the lines are fixed by two samples) plus a constant of the
    timestamps alone. All factorisations banded: O(T)."""
    import scipy.linalg

    t_count, dims = values.shape
    bands = accel_gram.shape[0] - 1
    prior = accel_gram / accel_sigma ** 2 + jerk_gram / jerk_sigma ** 2                  # [bands + 1, T]
    log_pdet = 2.0 * np.sum(np.log(scipy.linalg.cholesky_banded(prior[:, 2:], check_finite=False)[bands]))
    best = -np.inf
    for label_sigma in label_sigmas:
        lam = 1.0 / label_sigma ** 2
        banded = prior.copy()
        banded[bands] += lam
        factor = scipy.linalg.cholesky_banded(banded, check_finite=False)
        log_det = 2.0 * np.sum(np.log(factor[bands]))
        solved = scipy.linalg.cho_solve_banded((factor, False), values, check_finite=False)
        quadratic = lam * np.sum(values * values) - lam ** 2 * np.sum(values * solved)
        best = max(best, -0.5 * quadratic + dims * (-0.5 * log_det + 0.5 * t_count * np.log(lam) + 0.5 * log_pdet))
    return float(best)


def jerk_sigma_from_labels(world_xy: np.ndarray, timestamps_s: np.ndarray, candidates: tuple[float, ...],
                           evidence_nats: float) -> tuple[float, dict[float, float]]:
    """The jerk stiffness (m/s^3) an object's labels support: the stiffest of ``candidates`` whose
    evidence is within ``evidence_nats`` of the best; and each candidate's log evidence.

    ``world_xy`` float [T, 2]: the labels' horizontal centres in the world (metres) at
    ``timestamps_s`` [T] (seconds, increasing). Each candidate's evidence is the marginal
    likelihood of those centres under the motion model (acceleration rows over
    :data:`EVIDENCE_ACCEL_SIGMAS_MPS2`, jerk rows over the candidate; the acceleration stiffness
    and the label noise, :data:`EVIDENCE_LABEL_SIGMAS_M`, each at its best): empirical Bayes, with
    a preference for the stiffer (simpler) model until the labels speak against it by
    ``evidence_nats`` (3: "strong" on Kass and Raftery's scale). Labels of a car that keeps its
    speed or brakes steadily cannot tell a stiff jerk term from a loose one (within a fraction of a
    nat over 20 frames of 5 cm labels), and get the stiff one, which steadies the directions
    their returns do not observe; a car that starts or stops braking (2 m/s^2 or more from one
    frame to the next) shows in 2 s of its labels by 5-35 nats, and keeps a loose one, which does
    not smooth the change away (docs/refinement.md, "The jerk term's stiffness from the labels").
    Fewer than 4 frames: the softest candidate (no jerk rows)."""
    candidates = tuple(sorted(float(c) for c in candidates))
    t_count = timestamps_s.shape[0]
    if t_count < 4 or len(candidates) == 1:
        return candidates[-1], {}
    values = np.asarray(world_xy, dtype=np.float64)
    values = values - values.mean(axis=0)
    ts = np.asarray(timestamps_s, dtype=np.float64)
    ts = ts - ts.mean()
    accel_gram, jerk_gram = _difference_gram(ts, 2, 3), _difference_gram(ts, 3, 3)
    evidence = {c: max(_log_evidence(values, accel_gram, jerk_gram, a, c, EVIDENCE_LABEL_SIGMAS_M)
                       for a in EVIDENCE_ACCEL_SIGMAS_MPS2) for c in candidates}
    top = max(evidence.values())
    return min(c for c in candidates if evidence[c] >= top - evidence_nats), evidence


#: prior sigma (metres) of the no-slip point's offset from the box centre, towards 0 (a car's rear
#: axle lies 1-1.5 m behind its centre; the prior only matters while the object drives straight,
#: where the offset is not observed and changes nothing)
SLIP_OFFSET_SIGMA_M = 1.0


def slip_offset_guess(center: np.ndarray, heading: np.ndarray, world_from_vehicle: np.ndarray,
                      timestamps_s: np.ndarray, sigma_mps: float, max_offset_m: float,
                      offset_sigma_m: float = SLIP_OFFSET_SIGMA_M) -> float:
    """The least-squares ``offset_m`` of :func:`_slip_terms` at a fixed state (metres along the
    box's x axis, clipped to +-``max_offset_m``): where to start it."""
    v_lat, omega = _slip_velocities(center, heading, world_from_vehicle, timestamps_s)[:2]
    b = -float(np.sum(v_lat * omega)) / (float(np.sum(omega * omega)) + (sigma_mps / offset_sigma_m) ** 2)
    return float(np.clip(b, -max_offset_m, max_offset_m))


def _slip_velocities(center, heading, world_from_vehicle, timestamps_s):
    """(lateral velocity [T-1] m/s of the box centre across the mid heading, yaw rate [T-1]
    rad/s, half the along-heading velocity [T-1] m/s, lateral unit [T-1, 3], dt [T-1] s) between
    consecutive frames of a state (center [T, 3] and heading [T] in the vehicle frames)."""
    rotation, offset = world_from_vehicle[:, :3, :3], world_from_vehicle[:, :3, 3]
    w = np.einsum("tij,tj->ti", rotation, center) + offset
    psi = heading + np.unwrap(np.arctan2(rotation[:, 1, 0], rotation[:, 0, 0]))
    dt = np.diff(timestamps_s)
    dpsi = np.angle(np.exp(1j * np.diff(psi)))
    mid = psi[:-1] + 0.5 * dpsi
    lateral = np.stack([-np.sin(mid), np.cos(mid), np.zeros_like(mid)], axis=-1)      # [T-1, 3]
    forward = np.stack([np.cos(mid), np.sin(mid), np.zeros_like(mid)], axis=-1)
    dw = np.diff(w, axis=0)
    return (np.einsum("ti,ti->t", lateral, dw) / dt, dpsi / dt, 0.5 * np.einsum("ti,ti->t", forward, dw) / dt,
            lateral, dt)


def _slip_terms(center: np.ndarray, heading: np.ndarray, world_from_vehicle: np.ndarray, timestamps_s: np.ndarray,
                sigma_mps: float, dof: int, offset_m: float):
    """Gauss-Newton terms of the no-side-slip prior of a wheeled object at state (center [T, 3]
    vehicle frame, heading [T] rad, vehicle frame; ``offset_m`` the no-slip point's):
    ``(H float64 [DT, DT], g float64 [DT], h_xb float64 [DT], h_bb float, g_b float, r float64 [T-1])``,
    the blocks of the normal equations in (state, offset) and the residuals.

    A wheeled vehicle moves along its heading: the point on its long axis above the rear axle
    (``offset_m`` along the box's x from its centre, negative behind it) has no lateral
    velocity. Between consecutive frames, with the world centres ``w``, world headings ``psi``,
    the mid heading's lateral unit ``n`` and ``omega = dpsi / dt``, the residual is
    ``(n . dw / dt + omega * offset_m) / sigma_mps`` (the box centre's lateral velocity plus that
    of the axle point relative to it). It ties a car's lateral position (along its rear face, not
    observed by a lidar behind it) to its heading (which that face observes well). The offset is
    an unknown of the solve (observed only while the object turns; the caller adds its prior).
    """
    t_count = center.shape[0]
    n_state = dof * t_count
    rotation = world_from_vehicle[:, :3, :3]
    v_lat, omega, along, lateral, dt = _slip_velocities(center, heading, world_from_vehicle, timestamps_s)
    b = float(offset_m)
    r = (v_lat + omega * b) / sigma_mps
    jac = np.zeros((t_count - 1, 2 * 4))
    jac[:, 0:3] = -np.einsum("tji,tj->ti", rotation[:-1], lateral) / dt[:, None]
    jac[:, 3] = -along - b / dt
    jac[:, 4:7] = np.einsum("tji,tj->ti", rotation[1:], lateral) / dt[:, None]
    jac[:, 7] = -along + b / dt
    jac /= sigma_mps
    jac_b = omega / sigma_mps                                                         # d r / d offset
    frames = np.arange(t_count - 1)
    cols = np.concatenate([dof * frames[:, None] + np.arange(4), dof * (frames[:, None] + 1) + np.arange(4)], axis=1)
    flat = (cols[:, :, None] * n_state + cols[:, None, :]).reshape(-1)
    H = np.bincount(flat, weights=(jac[:, :, None] * jac[:, None, :]).reshape(-1),
                    minlength=n_state * n_state).reshape(n_state, n_state)
    g = np.bincount(cols.reshape(-1), weights=(jac * r[:, None]).reshape(-1), minlength=n_state)
    h_xb = np.bincount(cols.reshape(-1), weights=(jac * jac_b[:, None]).reshape(-1), minlength=n_state)
    return H, g, h_xb, float(jac_b @ jac_b), float(jac_b @ r), r
