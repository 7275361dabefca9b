"""One object's refinement: :func:`refine_object_poses` (the Gauss-Newton driver) and its result."""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from drivetrack.geometry import (box_from_center_heading, center_heading_from_poses, tilt_from_poses, vectors_from_box,
                                 wrap_angle)
from drivetrack.refine.config import RefineConfig, RefineReason, _use_kernel
from drivetrack.refine.extent import EXTENT_MIN_FRAMES, end_candidates, extent_shifts
from drivetrack.refine.motion import (SLIP_OFFSET_SIGMA_M, _motion_operator, _slip_terms, jerk_sigma_from_labels,
                                      slip_offset_guess)
from drivetrack.refine.select import _body_points, _inside, _Selection, normal_priority, point_priority, spread_priority
from drivetrack.refine.solver import _solve_spd
from drivetrack.refine.terms import _associate, _data_terms, _pair_terms

__all__ = ["RefinedPoses", "refine_object_poses"]


@dataclass
class RefinedPoses:
    """Result of :func:`refine_object_poses` for one object over its T frames.

    Attributes:
        vehicle_from_box: float64 [T, 4, 4], refined box poses (the labels on fallback), vehicle
            frame of each frame; rotation ``Rz(heading) Ry(pitch) Rx(roll)`` (yaw-only, like a
            label, with ``RefineConfig.pitch_roll_sigma_deg=None``).
        world_from_box: float64 [T, 4, 4] = ``world_from_vehicle @ vehicle_from_box``.
        center_vehicle: float64 [T, 3] metres and heading: float64 [T] radians in (-pi, pi] of
            the returned boxes (vehicle frame of each frame).
        size: float64 [T, 3] metres, of the returned boxes: the input sizes, grown on refined
            objects with ``RefineConfig.fit_extent``.
        correction_translation_m: float64 [T, 3], returned centre minus label centre (vehicle
            frame), zero on fallback.
        correction_rotation_deg: float64 [T], returned heading minus label heading, wrapped to
            (-180, 180], zero on fallback.
        pitch, roll: float64 [T] radians of the returned boxes (the labels' on fallback: 0 for
            yaw-only labels; 0 with 4 DOF).
        residual_m: robust point-to-plane residual (1.4826 x median |r|, metres) of the refined
            poses; NaN when never computed (too few points, disabled).
        residual_label_m: the same measure at the labels (the labels' own consistency).
        residual_per_frame_m: float64 [T], RMS of the Huber-inlier residuals per frame at the
            refined poses (NaN where a frame has no correspondence).
        num_points: int64 [T], returns taking part in the registration per frame.
        refined: True when refined poses are returned.
        used_fallback: True when refinement ran but the labels are returned.
        reason: a :class:`RefineReason`; ``detail``: human-readable numbers behind it.
        iterations: Gauss-Newton iterations run.
        cpu_seconds: process CPU time spent in the call.
        slip_offset_m: with the no-side-slip prior (``RefineConfig.slip_sigma_mps``, wheeled
            objects), where the point without lateral slip lies along the box's x axis from its
            centre (metres, negative behind it: a car's rear axle) at the refined poses; NaN
            when the prior was not applied.
        jerk_sigma_mps3: the jerk term's stiffness (m/s^3) the registration ran with
            (``RefineConfig.jerk_sigma_choices_mps3``: chosen from the labels); NaN when it did
            not run or had no jerk term.
    """
    vehicle_from_box: np.ndarray
    world_from_box: np.ndarray
    center_vehicle: np.ndarray
    heading: np.ndarray
    size: np.ndarray
    correction_translation_m: np.ndarray
    correction_rotation_deg: np.ndarray
    residual_m: float
    residual_label_m: float
    residual_per_frame_m: np.ndarray
    num_points: np.ndarray
    refined: bool
    used_fallback: bool
    reason: RefineReason
    detail: str = ""
    iterations: int = 0
    cpu_seconds: float = 0.0
    pitch: np.ndarray | None = None
    roll: np.ndarray | None = None
    slip_offset_m: float = float("nan")
    jerk_sigma_mps3: float = float("nan")

    def summary(self) -> dict:
        """Flat dict for the statistics tables and the gates (one row per object)."""
        translation = np.linalg.norm(self.correction_translation_m, axis=-1)
        rotation = np.abs(self.correction_rotation_deg)
        has = translation.size > 0
        return {
            "refine_reason": str(self.reason),
            "refine_applied": bool(self.refined),
            "refine_fallback": bool(self.used_fallback),
            "refine_translation_p50_m": float(np.median(translation)) if has else 0.0,
            "refine_translation_max_m": float(translation.max()) if has else 0.0,
            "refine_rotation_p50_deg": float(np.median(rotation)) if has else 0.0,
            "refine_rotation_max_deg": float(rotation.max()) if has else 0.0,
            "refine_tilt_max_deg": float(np.rad2deg(np.max(np.hypot(self.pitch, self.roll))))
            if has and self.pitch is not None else 0.0,
            "refine_residual_m": float(self.residual_m),
            "refine_residual_label_m": float(self.residual_label_m),
            "refine_num_points": int(self.num_points.sum()),
            "refine_frames_without_points": int((self.num_points == 0).sum()),
            "refine_iterations": int(self.iterations),
            "refine_cpu_seconds": float(self.cpu_seconds),
            "refine_jerk_sigma_mps3": float(self.jerk_sigma_mps3),
        }


def grown_extent(points_body: np.ndarray, half: np.ndarray, config: RefineConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(grow_lo, grow_hi)`` float64 [3] each, metres: how far to move the box's -x -y -z and
    +x +y +z faces outwards so that it holds ``points_body`` (float [N, 3], body frame; ``half``
    float [N, 3] or [3], the box's half size at each) with ``config.extent_margin_m`` to spare,
    never shrinking, at most ``config.max_extent_growth_m``, never lowering the bottom (ground)."""
    grow_hi = np.clip(np.max(points_body - half, axis=0) + config.extent_margin_m, 0.0, config.max_extent_growth_m)
    grow_lo = np.clip(np.max(-points_body - half, axis=0) + config.extent_margin_m, 0.0, config.max_extent_growth_m)
    grow_lo[2] = 0.0
    return grow_lo, grow_hi


def _check_inputs(vehicle_from_box, size, world_from_vehicle, points_vehicle, point_frame, timestamps_s, name):
    where = f"refine_object_poses({name})" if name else "refine_object_poses"
    vehicle_from_box = np.asarray(vehicle_from_box, dtype=np.float64)
    if vehicle_from_box.ndim != 3 or vehicle_from_box.shape[1:] != (4, 4) or vehicle_from_box.shape[0] < 1:
        raise ValueError(f"{where}: vehicle_from_box must be [T, 4, 4] with T >= 1, got {vehicle_from_box.shape}")
    t_count = vehicle_from_box.shape[0]
    size = np.asarray(size, dtype=np.float64)
    if size.shape == (3,):
        size = np.broadcast_to(size, (t_count, 3))
    if size.shape != (t_count, 3):
        raise ValueError(f"{where}: size must be [3] or [{t_count}, 3], got {size.shape}")
    if not (np.all(np.isfinite(size)) and np.all(size > 0)):
        raise ValueError(f"{where}: size must be finite and positive, got {size[~(np.isfinite(size) & (size > 0)).all(-1)][0].tolist()}")
    world_from_vehicle = np.asarray(world_from_vehicle, dtype=np.float64)
    if world_from_vehicle.shape != (t_count, 4, 4):
        raise ValueError(f"{where}: world_from_vehicle must be [{t_count}, 4, 4], got {world_from_vehicle.shape}")
    for label, arr in (("vehicle_from_box", vehicle_from_box), ("world_from_vehicle", world_from_vehicle)):
        bad = np.flatnonzero(~np.isfinite(arr).all(axis=(1, 2)))
        if bad.size:
            raise ValueError(f"{where}: {label} is not finite at frames {bad[:10].tolist()}")
    points_vehicle = np.asarray(points_vehicle, dtype=np.float64)
    if points_vehicle.ndim != 2 or points_vehicle.shape[1] != 3:
        raise ValueError(f"{where}: points_vehicle must be [M, 3], got {points_vehicle.shape}")
    point_frame = np.asarray(point_frame)
    if point_frame.shape != (points_vehicle.shape[0],) or not (point_frame.size == 0 or np.issubdtype(point_frame.dtype, np.integer)):
        raise ValueError(f"{where}: point_frame must be int [{points_vehicle.shape[0]}], got "
                         f"{point_frame.dtype} {point_frame.shape}")
    point_frame = point_frame.astype(np.int64)
    if point_frame.size and (point_frame.min() < 0 or point_frame.max() >= t_count):
        raise ValueError(f"{where}: point_frame out of range [0, {t_count}): "
                         f"{int(point_frame.min())}..{int(point_frame.max())}")
    if not np.all(np.isfinite(points_vehicle)):
        raise ValueError(f"{where}: points_vehicle has {int((~np.isfinite(points_vehicle).all(-1)).sum())} "
                         f"non-finite rows")
    timestamps_s = np.asarray(timestamps_s, dtype=np.float64)
    if timestamps_s.shape != (t_count,):
        raise ValueError(f"{where}: timestamps_s must be [{t_count}], got {timestamps_s.shape}")
    if np.any(~np.isfinite(timestamps_s)) or np.any(np.diff(timestamps_s) <= 0):
        i = int(np.flatnonzero(~(np.diff(timestamps_s) > 0))[0]) if t_count > 1 else 0
        raise ValueError(f"{where}: timestamps_s must be finite and strictly increasing; frames {i} and {i + 1} "
                         f"have {timestamps_s[i:i + 2].tolist()}")
    return vehicle_from_box, np.ascontiguousarray(size), world_from_vehicle, points_vehicle, point_frame, timestamps_s


def _result(center, heading, label_center, label_heading, world_from_vehicle, tilt=None, **kw) -> RefinedPoses:
    vehicle_from_box = (box_from_center_heading(center, heading) if tilt is None else
                        box_from_center_heading(center, heading, tilt[:, 0], tilt[:, 1]))
    tilt = np.zeros((heading.shape[0], 2)) if tilt is None else tilt
    return RefinedPoses(
        vehicle_from_box=vehicle_from_box, world_from_box=world_from_vehicle @ vehicle_from_box,
        center_vehicle=center, heading=wrap_angle(heading), pitch=tilt[:, 0].copy(), roll=tilt[:, 1].copy(),
        correction_translation_m=center - label_center,
        correction_rotation_deg=np.rad2deg(wrap_angle(heading - label_heading)), **kw)


def refine_object_poses(vehicle_from_box: np.ndarray, size: np.ndarray, world_from_vehicle: np.ndarray,
                        points_vehicle: np.ndarray, point_frame: np.ndarray, timestamps_s: np.ndarray,
                        config: RefineConfig | None = None, name: str = "",
                        points_measured: np.ndarray | None = None, wheeled: bool = False) -> RefinedPoses:
    """Refine one object's per-frame box poses from its own LiDAR (see the module docstring).

    Args:
        vehicle_from_box: float64 [T, 4, 4], labelled box poses, vehicle frame of each frame
            (yaw-only, as ``box_from_center_heading`` makes them from a label; any roll/pitch is
            the start and prior mean of the 6-DOF refinement and dropped by the 4-DOF one).
        size: float64 [3] or [T, 3], box size (length, width, height), metres.
        world_from_vehicle: float64 [T, 4, 4], vehicle pose of each frame.
        points_vehicle: float64 [M, 3], metres, candidate returns near the object (e.g. inside
            the label box grown by ``config.candidate_margin_m``), vehicle frame of their frame.
            Ground, background and other objects among them are tolerated.
        point_frame: int [M], frame index (0..T-1) of each candidate.
        timestamps_s: float64 [T], seconds, strictly increasing.
        config: :class:`RefineConfig` (defaults when None).
        name: object name used in error messages (e.g. ``segment/object_id``).
        points_measured: float64 [M, 3] or None: the returns as measured when ``points_vehicle``
            are moved copies of them (onto their sweep's surface, ``sweep_surface_max_m``): the
            poses are solved on ``points_vehicle``, but whether they beat the labels by
            ``min_improvement`` is decided on these, on others than the solve's subset where a
            frame has more than ``max_points_per_frame`` (a surface moved onto by the returns' own
            neighbours, and the solve's own subset, fit any pose near them better: exact labels
            would be replaced).
        wheeled: the object drives on wheels (a vehicle or a cyclist): with
            ``config.slip_sigma_mps`` the no-side-slip prior applies (``motion._slip_terms``;
            a pedestrian steps sideways, so not to it); with ``config.jerk_sigma_choices_mps3``
            its jerk term's stiffness is chosen from its labels (``jerk_sigma_mps3`` otherwise);
            with ``config.extent_sigma_m`` the extent term too (:mod:`drivetrack.refine.extent`), unless ``points_measured`` is
            given (returns with range noise).
    Returns:
        :class:`RefinedPoses`; the labels (``refined=False``) when disabled or on fallback.
    Raises:
        ValueError naming the argument, shape or value on malformed input.
    """
    config = config or RefineConfig()
    cpu0 = time.process_time()
    vehicle_from_box, size, world_from_vehicle, points, frame, timestamps_s = _check_inputs(
        vehicle_from_box, size, world_from_vehicle, points_vehicle, point_frame, timestamps_s, name)
    if points_measured is not None:
        points_measured = np.asarray(points_measured, dtype=np.float64)
        if points_measured.shape != points.shape or not np.all(np.isfinite(points_measured)):
            raise ValueError(f"{name}: points_measured must be finite and of points_vehicle's shape {points.shape}, "
                             f"got {points_measured.shape}")
    t_count = vehicle_from_box.shape[0]
    label_center, label_heading = center_heading_from_poses(vehicle_from_box)
    label_heading = np.unwrap(label_heading)
    label_tilt = tilt_from_poses(vehicle_from_box)                     # [T, 2], 0 for yaw-only labels
    six = config.pitch_roll_sigma_deg is not None
    dof = 6 if six else 4
    half = size / 2.0
    nan_frames = np.full(t_count, np.nan)

    def labels(reason: RefineReason, detail: str, residual=float("nan"), residual_label=float("nan"),
               num_points=None, iterations=0) -> RefinedPoses:
        out = _result(label_center.copy(), label_heading.copy(), label_center, label_heading,
                      world_from_vehicle, tilt=label_tilt.copy(), size=size.copy(), residual_m=residual, residual_label_m=residual_label,
                      residual_per_frame_m=nan_frames.copy(),
                      num_points=np.zeros(t_count, np.int64) if num_points is None else num_points,
                      refined=False,
                      used_fallback=reason not in (RefineReason.DISABLED, RefineReason.LABELS_CONSISTENT),
                      reason=reason, detail=detail,
                      iterations=iterations, cpu_seconds=time.process_time() - cpu0)
        out.vehicle_from_box = vehicle_from_box.copy()                    # the labels, bit for bit
        out.world_from_box = world_from_vehicle @ out.vehicle_from_box
        return out

    if not config.enabled:
        return labels(RefineReason.DISABLED, "refinement disabled by configuration")
    if frame.size > 1 and not np.all(frame[1:] >= frame[:-1]):       # (callers usually pass them sorted)
        order = np.argsort(frame, kind="stable")
        points, frame = points[order], frame[order]
        points_measured = None if points_measured is None else points_measured[order]
    # fixed per-point priority for the per-frame cap: a hash of the point's coordinates, so the
    # result does not depend on the order of the input rows
    priority = point_priority(points)
    use_kernel = _use_kernel(config)
    if config.sample_voxel_m is not None:
        # the cap spread evenly over the surface, not in proportion to the returns (select.spread_priority)
        priority = spread_priority(points, frame, priority, float(config.sample_voxel_m))
    elif config.sample_normals:
        # the cap shared among the directions the surfaces face (select.normal_priority): the first
        # sample_normals_screen x cap of each frame by hash
        priority = normal_priority(points, frame, priority, label_heading,
                                   config.sample_normals_screen * config.max_points_per_frame,
                                   use_kernel=use_kernel)

    # Selection at the labels decides whether there is enough to register at all.
    if use_kernel:
        from drivetrack.refine.kernel import inside_counts

        per_frame = inside_counts(points, frame, half, label_center, label_heading, label_tilt if six else None,
                                  config.inlier_margin_m, config.ground_clearance_m)
    else:
        q0 = _body_points(label_center, label_heading, points, frame, label_tilt if six else None)
        at_label = _inside(q0, half[frame], config.inlier_margin_m, config.ground_clearance_m)
        per_frame = np.bincount(frame[at_label], minlength=t_count).astype(np.int64)
    frames_ok = int((per_frame >= config.min_points_per_frame).sum())
    if per_frame.sum() < config.min_points_total or frames_ok < config.min_frames_with_points:
        return labels(RefineReason.TOO_FEW_POINTS, f"{int(per_frame.sum())} returns in the label boxes "
                      f"(need {config.min_points_total}); {frames_ok} frames with >= "
                      f"{config.min_points_per_frame} (need {config.min_frames_with_points})",
                      num_points=per_frame)

    if wheeled and config.jerk_sigma_mps3 is not None and config.jerk_sigma_choices_mps3:
        # the jerk term as stiff as the labels' own course allows (motion.jerk_sigma_from_labels);
        # not a pedestrian's: its centre sways with each step (centimetres at 1-2 Hz: jerks of
        # several m/s^3) where a wheeled body runs smooth
        jerk, _ = jerk_sigma_from_labels((world_from_vehicle @ vehicle_from_box)[:, :2, 3], timestamps_s,
                                         (config.jerk_sigma_mps3,) + config.jerk_sigma_choices_mps3,
                                         config.jerk_evidence_nats)
        config = dataclasses.replace(config, jerk_sigma_mps3=jerk)
    S, e0 = _motion_operator(world_from_vehicle, timestamps_s, config, label_heading if six else None)
    prior = [1.0 / config.label_sigma_m ** 2] * 3 + [1.0 / np.deg2rad(config.label_sigma_deg) ** 2]
    if six:
        prior += [1.0 / np.deg2rad(config.pitch_roll_sigma_deg) ** 2] * 2
    prior_w = np.tile(prior, t_count)
    # prior + motion, dense [DT, DT] (the data term couples most pairs of frames: dense anyway),
    # and the motion gradient's constant part S^T e0
    H_fixed = np.diag(prior_w)
    if S is not None:
        H_fixed += (S.T @ S).toarray()
        motion_g0 = S.T @ e0
    label_state = np.concatenate([label_center, label_heading[:, None]] + ([label_tilt] if six else []),
                                 axis=1).reshape(-1)
    selection = _Selection(points, frame, priority, half, config.max_points_per_frame, t_count, kernel=use_kernel)

    center, heading = label_center.copy(), label_heading.copy()
    tilt = label_tilt.copy() if six else None
    shrink = max(config.iterations // 2, 1)
    gates = np.concatenate([np.geomspace(config.max_correspondence_m, config.min_correspondence_m, shrink),
                            np.full(max(config.iterations - shrink, 0), config.min_correspondence_m)])
    gates[0] = config.max_correspondence_m
    # The labels' own consistency, measured exactly as the final result is (the first iteration
    # starts from the same terms).
    pairs = _associate(selection, center, heading, config.max_correspondence_m, config, t_count, tilt)
    data = _pair_terms(selection, pairs, center, heading, config, t_count, tilt=tilt)
    residual_label = data.scale
    # The refined residual never drops below the noise floor (``point_sigma_floor_m``): labels
    # within ``min_improvement`` of it are already consistent, whatever the iterations would do.
    if residual_label <= (1.0 + config.min_improvement) * config.point_sigma_floor_m:
        return labels(RefineReason.LABELS_CONSISTENT, f"robust residual {residual_label:.4f} m at the labels: within "
                      f"{config.min_improvement:.0%} of the noise floor {config.point_sigma_floor_m} m",
                      residual=residual_label, residual_label=residual_label, num_points=data.num_points)
    iterations = 0
    slip = wheeled and config.slip_sigma_mps is not None and t_count >= 2
    slip_offset = float("nan")
    if slip:
        sigma_slip, max_slip_offset = float(config.slip_sigma_mps), float(half[:, 0].max())
        slip_offset = slip_offset_guess(label_center, label_heading, world_from_vehicle, timestamps_s, sigma_slip,
                                        max_slip_offset)
    # not where the returns carry range noise (moved onto their sweep's surface: points_measured):
    # noise along a ray near an end runs partly along the side and scatters the ends
    extent = (wheeled and config.extent_sigma_m is not None and t_count >= EXTENT_MIN_FRAMES
              and points_measured is None)
    if extent:       # the returns that may be a side's ends, chosen once at the labels
        ends = end_candidates(points, frame, label_center, label_heading, label_tilt if six else None, half,
                              config.inlier_margin_m + config.max_correspondence_m)
        end_points, end_frame = points[ends], frame[ends]
        block = (np.arange(t_count) * dof)[:, None] + np.arange(3)                  # [T, 3] state indices
    for it in range(config.iterations):
        if it > 0:
            data = _data_terms(selection, center, heading, gates[it], config, t_count, tilt=tilt)
        if it > 0 and it == config.early_stop_iteration and \
                residual_label <= (1.0 + config.min_improvement) * data.scale:
            if not data.scale <= config.max_residual_m:          # no rigid surface to register on
                return labels(RefineReason.LARGE_RESIDUAL, f"robust residual {data.scale:.3f} m after {it} "
                              f"iterations > {config.max_residual_m} m (labels: {residual_label:.3f} m)", residual=data.scale,
                              residual_label=residual_label, num_points=data.num_points, iterations=it)
            return labels(RefineReason.LABELS_CONSISTENT, f"robust residual {residual_label:.4f} m at the labels, "
                          f"{data.scale:.4f} m after {it} iterations: less than {config.min_improvement:.0%} "
                          f"better", residual=data.scale, residual_label=residual_label,
                          num_points=data.num_points, iterations=it)
        state = np.concatenate([center, heading[:, None]] + ([tilt] if six else []), axis=1).reshape(-1)
        # Normal equations of 1/2 (data + prior + motion) in the increment dx.
        g = data.gradient + prior_w * (state - label_state)
        if S is not None:
            g = g + S.T @ (S @ state) + motion_g0
        hessian = data.hessian + H_fixed
        if slip:
            # the no-slip point's offset is an unknown too, eliminated by its Schur complement
            # (a rank-one change of the state's normal equations)
            H_slip, g_slip, h_xb, h_bb, g_b, _ = _slip_terms(center, heading, world_from_vehicle, timestamps_s,
                                                             sigma_slip, dof, slip_offset)
            h_bb += 1.0 / SLIP_OFFSET_SIGMA_M ** 2
            g_b += slip_offset / SLIP_OFFSET_SIGMA_M ** 2
            hessian = hessian + H_slip - np.outer(h_xb, h_xb) / h_bb
            g = g + g_slip - h_xb * (g_b / h_bb)
        if extent:
            # each frame's ends against the median ends: a measurement along its heading
            shift, used = extent_shifts(end_points, end_frame, center, heading, tilt, half, t_count,
                                        config.inlier_margin_m, config.ground_clearance_m)
            if used.any():
                along = np.stack([np.cos(heading), np.sin(heading), np.zeros(t_count)], axis=-1)   # [T, 3]
                weight = used / config.extent_sigma_m ** 2
                g[block] -= (weight * shift)[:, None] * along
                hessian[block[:, :, None], block[:, None, :]] += weight[:, None, None] * along[:, :, None] * along[:, None, :]
        dx = _solve_spd(hessian, -g, use_kernel)
        if slip and np.all(np.isfinite(dx)):
            slip_offset = float(np.clip(slip_offset - (g_b + h_xb @ dx) / h_bb, -max_slip_offset, max_slip_offset))
        iterations = it + 1
        if not np.all(np.isfinite(dx)):
            return labels(RefineReason.NOT_FINITE, f"non-finite update at iteration {iterations}",
                          residual_label=residual_label, num_points=data.num_points, iterations=iterations)
        dx = dx.reshape(t_count, dof)
        center = center + dx[:, :3]
        heading = heading + dx[:, 3]
        if six:
            tilt = tilt + dx[:, 4:]
        # converged when the step is at the level of re-association jitter (RMS over frames: the
        # largest single-frame step keeps jittering by millimetres as correspondences change)
        small = (np.sqrt(np.mean(np.sum(dx[:, :3] ** 2, axis=1))) < config.tolerance_m
                 and np.rad2deg(np.sqrt(np.mean(np.sum(dx[:, 3:] ** 2, axis=1)))) < config.tolerance_deg)
        if small and gates[it] <= config.min_correspondence_m * 1.0001:
            break
        if small:                                   # converged at this gate: jump to the finest
            gates[it + 1:] = config.min_correspondence_m

    final_pairs = _associate(selection, center, heading, config.max_correspondence_m, config, t_count, tilt)
    final = _pair_terms(selection, final_pairs, center, heading, config, t_count, normal_equations=False, tilt=tilt)
    residual = final.scale
    inlier = np.abs(final.residual) <= config.huber_k * (residual if np.isfinite(residual) else 0.0)
    sq = np.bincount(final.frame[inlier], weights=final.residual[inlier] ** 2, minlength=t_count)
    cnt = np.bincount(final.frame[inlier], minlength=t_count)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_frame_residual = np.where(cnt > 0, np.sqrt(sq / np.maximum(cnt, 1)), np.nan)

    translation = np.linalg.norm(center - label_center, axis=-1)
    rotation = np.rad2deg(np.abs(wrap_angle(heading - label_heading)))
    if six:      # the tilt's correction counts towards the rotation bound as well
        rotation = np.maximum(rotation, np.rad2deg(np.max(np.abs(tilt - label_tilt), axis=1)))
    if not (np.all(np.isfinite(center)) and np.all(np.isfinite(heading)) and np.isfinite(residual)
            and (tilt is None or np.all(np.isfinite(tilt)))):
        return labels(RefineReason.NOT_FINITE, "the refined poses or residual are not finite",
                      residual_label=residual_label, num_points=final.num_points, iterations=iterations)
    if residual > config.max_residual_m:
        return labels(RefineReason.LARGE_RESIDUAL, f"robust residual {residual:.3f} m > {config.max_residual_m} m "
                      f"(labels: {residual_label:.3f} m)", residual=residual, residual_label=residual_label,
                      num_points=final.num_points, iterations=iterations)
    if translation.max() > config.max_correction_m or rotation.max() > config.max_correction_deg:
        t_bad = int(np.argmax(np.maximum(translation / config.max_correction_m, rotation / config.max_correction_deg)))
        return labels(RefineReason.LARGE_CORRECTION, f"frame {t_bad}: correction {translation[t_bad]:.3f} m, "
                      f"{rotation[t_bad]:.2f} deg exceeds {config.max_correction_m} m / "
                      f"{config.max_correction_deg} deg", residual=residual, residual_label=residual_label,
                      num_points=final.num_points, iterations=iterations)
    decided_label, decided, on = residual_label, residual, ""
    if points_measured is not None:
        # the returns as measured, and where a frame has more than the cap, others than those the
        # poses were solved on (a registration fits the noise of its own subset: on exact labels
        # with 2 cm range noise it measured 13.2 -> 11.5 mm on its own subset, 15.4 -> 14.7 on others)
        held_out = np.modf(priority + 0.5)[0]
        measured = _Selection(points_measured, frame, held_out, half, config.max_points_per_frame, t_count,
                              kernel=use_kernel)
        label_tilt_or_none = label_tilt if six else None
        decided_label, decided = (
            _pair_terms(measured, _associate(measured, c, h, config.max_correspondence_m, config, t_count, a),
                        c, h, config, t_count, normal_equations=False, tilt=a).scale
            for c, h, a in ((label_center, label_heading, label_tilt_or_none), (center, heading, tilt)))
        on = " (the returns as measured)"
    if decided_label <= (1.0 + config.min_improvement) * decided:
        return labels(RefineReason.LABELS_CONSISTENT, f"robust residual {decided_label:.4f} m at the labels, "
                     f"{decided:.4f} m refined{on}: less than {config.min_improvement:.0%} better",
                     residual=residual, residual_label=residual_label, num_points=final.num_points,
                     iterations=iterations)
    size_out = size.copy()
    extent_detail = ""
    if config.fit_extent and inlier.any():
        # The refined frames agree with each other, so the registered returns of all frames form
        # one body-frame model; grow the box (never shrink, never lower its bottom: ground) so it
        # holds that model. Without this the refined boxes share one small offset (the mean label
        # error, the gauge) and, with point selection at the box faces, lose whole faces in every
        # frame where noisy labels lost them in about half the frames.
        fa = final_pairs.fa[inlier]
        grow_lo, grow_hi = grown_extent(final_pairs.qa[inlier], half[fa], config)   # body points at the final state
        if np.any(grow_hi > 0) or np.any(grow_lo > 0):
            offset = (grow_hi - grow_lo) / 2.0                                   # body frame
            center = center + vectors_from_box(np.broadcast_to(offset, (t_count, 3)), heading,
                                               *((None, None) if tilt is None else (tilt[:, 0], tilt[:, 1])))
            size_out = size + (grow_hi + grow_lo)
            slip_offset -= offset[0]                    # measured from the new centre
            extent_detail = (f"; box grown to the registered returns by {np.round(grow_lo * 100, 1).tolist()} / "
                             f"{np.round(grow_hi * 100, 1).tolist()} cm (-x -y -z / +x +y +z)")
    slip_detail = ""
    if slip:
        slip_detail = f"; no-slip point {slip_offset:+.2f} m along the box from its centre"
    out = _result(center, heading, label_center, label_heading, world_from_vehicle, tilt=tilt, size=size_out,
                  residual_m=residual, residual_label_m=residual_label,
                  residual_per_frame_m=per_frame_residual, num_points=final.num_points, refined=True,
                  used_fallback=False, reason=RefineReason.REFINED,
                  detail=f"residual {residual_label:.4f} m at the labels -> {residual:.4f} m{extent_detail}{slip_detail}",
                  iterations=iterations, cpu_seconds=time.process_time() - cpu0)
    out.slip_offset_m = slip_offset
    if config.jerk_sigma_mps3 is not None and t_count >= 4:
        out.jerk_sigma_mps3 = float(config.jerk_sigma_mps3)
    return out
