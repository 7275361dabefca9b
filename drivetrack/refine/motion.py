"""The motion model: constant velocity and yaw rate in the world, as a linear residual operator."""
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
    over ``accel_sigma_mps2``) and of the world heading (1 row, over ``yaw_accel_sigma_radps2``).
    World centre of frame t: ``R_t c_t + p_t``; world heading: ``psi_t + yaw(R_t)`` (unwrapped).
    With ``heading`` [T] given (the labels' headings, radians), the state has D = 6 per frame and
    two more rows: the second divided difference of the world pitch and roll (over
    ``tilt_accel_sigma_radps2``), linearised as ``tilt_t + _world_tilt_offset(t)``: the ego's own
    pitch and roll (braking, turning, bumps) are in ``world_from_vehicle`` and must not be asked of
    the object. Returns (S scipy.sparse csr [D(T-2), DT], e0 float64 [D(T-2)]), or (None, None)
    when T < 3.
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
    return S, e0
