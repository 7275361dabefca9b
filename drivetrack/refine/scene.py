"""Refinement of every object of a scene: candidate returns per box, then each object on its own
(on the segment's thread pool when one is installed, :mod:`drivetrack.parallel`)."""
from __future__ import annotations

import dataclasses

import numpy as np

from drivetrack.boxes import (claimed_by_other_boxes, fill_ground_over_time, gather_candidates, ground_under_boxes,
                              inside_box)
from drivetrack.geometry import vectors_from_box
from drivetrack.parallel import pool_map
from drivetrack.refine.config import RefineConfig, RefineReason, _use_kernel
from drivetrack.refine.poses import grown_extent, refine_object_poses
from drivetrack.refine.select import _body_points, first_per_frame, point_priority
from drivetrack.refine.static import static_object_centres
from drivetrack.waymo.schema import BoxType

#: box types on wheels: they move along their heading (``RefineConfig.slip_sigma_mps``)
WHEELED_TYPES = (int(BoxType.VEHICLE), int(BoxType.CYCLIST))

__all__ = ["refine_scene_boxes"]

#: ``RefineConfig.sweep_surface_max_m``: at most this many candidates of a frame are moved onto
#: their sweep's surface (an even subset by :func:`drivetrack.refine.select.point_priority`) and
#: registered; every candidate makes the surface
SWEEP_RETURNS_PER_FRAME = 2000
#: ``RefineConfig.ground_ring``: returns less than this above the ground measured round a box
#: (:func:`drivetrack.boxes.ground_under_boxes`) are not the object's candidates, whatever the
#: box's bottom (metres: the road's returns scatter by a few centimetres about its mean surface and
#: slope across a car's footprint). It only acts where the box reaches more than
#: ``ground_clearance_m`` minus this below the ground: a label's usual noise leaves the cut at
#: the bottom's clearance, as before.
GROUND_BAND_M = 0.1
#: A ground measured more than this above the box's bottom is not trusted (a label is not drawn
#: that deep into the road; the ring then holds a neighbour's sill or a kerb).
GROUND_MAX_RISE_M = 0.5


def refine_scene_boxes(scene, config: RefineConfig | None = None, object_ids=None, lasers=None,
                       returns=None, compensate_sweep_motion: bool = True,
                       label_offset_s: np.ndarray | None = None):
    """Refine every object of ``scene`` over its labelled frames; returns boxes usable as labels.

    For each object (``object_ids`` or all), the candidates are the returns (of ``lasers`` /
    ``returns`` when given: ``LaserName`` values and return indices 1|2) inside each label box
    grown by ``config.candidate_margin_m``; :func:`refine_object_poses` runs on them. When the
    scene carries per-return capture times (``LidarReturns.capture_offset_s``) and
    ``compensate_sweep_motion`` holds, candidates are first moved to the frame time with the
    labels' motion, as the track stage does; to each box's label time when ``label_offset_s``
    (float [K], label time minus frame time, s; :func:`drivetrack.tracks.trajectory.scene_label_times`)
    is given, else to the frame time; the labels' finite-difference motion and the motion prior
    are then timed at those label times too (an object beside the vehicle is labelled 1-1.5 ms
    later each frame as the sweep meets it later). With ``config.motion_passes`` > 1 the objects whose
    registration was applied are registered again, their candidates moved with the registered
    boxes' motion (``config.motion_window``); the objects run on the segment's thread pool
    (:func:`drivetrack.parallel.pool_map`) when one is installed, with the same results.

    Returns:
        ``(boxes, results)``: a :class:`drivetrack.scene.Boxes` equal to ``scene.boxes`` except for
        the ``center``, ``heading``, ``size`` (and, with 6 DOF, ``pitch`` and ``roll``: 0 on the
        rows of objects not refined) of refined objects, and ``{object_id: RefinedPoses}``.
        Passing ``boxes`` as the scene's labels makes the track stage select points with, and
        carry them by, the refined poses.
    """
    from drivetrack.scene import Boxes

    config = config or RefineConfig()
    boxes, lidar = scene.boxes, scene.lidar
    object_id = boxes.object_id.astype(str)
    ids = sorted(set(object_id.tolist())) if object_ids is None else [str(i) for i in object_ids]
    timestamps_s = (scene.timestamps_micros - scene.timestamps_micros[0]) * 1e-6
    center, heading, size = boxes.center.copy(), boxes.heading.copy(), boxes.size.copy()
    pitch_all, roll_all = boxes.tilt()
    tilted = pitch_all is not None or config.pitch_roll_sigma_deg is not None
    pitch = (np.zeros(len(boxes)) if pitch_all is None else pitch_all.copy()) if tilted else None
    roll = (np.zeros(len(boxes)) if roll_all is None else roll_all.copy()) if tilted else None
    object_rows = []
    for oid in ids:
        rows = np.flatnonzero(object_id == oid)
        if rows.size == 0:
            raise ValueError(f"segment {scene.segment!r}: object {oid!r} has no lidar_box row")
        object_rows.append(rows[np.argsort(boxes.frame[rows], kind="stable")])
    # Objects standing still get one world pose and are not registered (refine/static.py); from
    # here on "boxes" are these labels, so their returns are also taken into the box frame without
    # the noisy labels' finite-difference motion (0.35 m/s at 5 cm, 1.8 cm over 50 ms).
    static, replaced = set(), set()
    if config.static_objects:
        for oid, rows in zip(ids, object_rows):
            pose = static_object_centres(scene, rows, config.static_speed_mps, config.static_fit_speed_mps,
                                         config.static_max_drift_m)
            if pose is not None:
                static.add(oid)
                if pose[2]:
                    replaced.add(oid)
                    center[rows], heading[rows] = pose[0], pose[1]
        if replaced:
            boxes = Boxes(**{k: v for k, v in boxes.__dict__.items()})
            boxes.center, boxes.heading = center.copy(), heading.copy()
            scene = dataclasses.replace(scene, boxes=boxes)
    # Returns of moving objects are captured during the sweep, boxes describe the frame time:
    # move each candidate to where its surface was at the frame time (with the labels' motion in
    # the first pass) before registering, as the track stage does (drivetrack.tracks.sweep_motion).
    offsets = getattr(lidar, "capture_offset_s", None) if compensate_sweep_motion else None
    if offsets is not None:
        from drivetrack.tracks.sweep_motion import scene_box_motion

        label_motion = scene_box_motion(scene, label_offset_s=label_offset_s)
    # Candidates of every box of every object at once: the returns of the box's frame within its
    # bounding cube (radius: half the diagonal plus the margin), in (box, row) order.
    all_rows = np.concatenate(object_rows) if object_rows else np.zeros(0, np.int64)
    radius_all = 0.5 * np.linalg.norm(boxes.size[all_rows], axis=-1) + config.candidate_margin_m
    gather, frame_time_candidates = gather_candidates, _frame_time_candidates
    if _use_kernel(config):
        from drivetrack.refine.kernel import frame_time_candidates, gather
    index_all, owner_all = gather(lidar.points_vehicle, lidar.laser, lidar.return_index, lasers, returns,
                                  lidar.frame_offsets, boxes.frame[all_rows], boxes.center[all_rows], radius_all)
    index_all, owner_all = _own_candidates(lidar, boxes, scene.world_from_vehicle, all_rows, index_all, owner_all,
                                           lasers, returns, config, _use_kernel(config))
    row_start = np.concatenate([[0], np.cumsum([r.size for r in object_rows])]).astype(np.int64)
    bounds = np.searchsorted(owner_all, row_start)

    def refine_one(k: int, motion):
        """(result, {field: values at the object's rows}) of object ``k``, its candidates moved to
        the frame (label) time with ``motion`` = (velocity [K, 3], yaw rate [K]) of every box row;
        writes nothing shared."""
        oid, rows = ids[k], object_rows[k]
        update = {}
        frames = boxes.frame[rows].astype(np.int64)
        times = _box_times(timestamps_s[frames], None if label_offset_s is None else label_offset_s[rows])
        vehicle_from_box = boxes.vehicle_from_box(rows)
        row_tilt = None if pitch_all is None and roll_all is None else np.stack(boxes.tilt(rows), axis=-1)  # [R, 2]
        index = index_all[bounds[k]:bounds[k + 1]]
        owner = owner_all[bounds[k]:bounds[k + 1]] - row_start[k]               # [N] index into rows
        if offsets is None:
            p = lidar.points_vehicle[index]
            local = _body_points(boxes.center[rows], boxes.heading[rows], p, owner, row_tilt)
            inside = inside_box(local, boxes.size[rows][owner], config.candidate_margin_m)
            returns = index
        else:                          # the compensated returns, back in the vehicle frame at the box's time
            local, p, owner, position = frame_time_candidates(
                lidar.points_vehicle, index, owner, rows, offsets, label_offset_s, boxes.center, boxes.heading,
                motion[0], motion[1], pitch_all, roll_all, boxes.size, config.candidate_margin_m)
            inside = np.ones(owner.size, dtype=bool)
            returns = index[position]
        measured = None                # the candidates as measured, when p holds moved copies
        if config.sweep_surface_max_m is not None and oid not in static:
            # range noise: each return onto its own sweep's surface first (exact ranges stay); the
            # candidates fill the box grown by candidate_margin_m, both sides of a noisy surface
            from drivetrack.visibility.facing import points_on_sweep_surface, sensor_positions

            ray = lidar.points_vehicle[returns] - sensor_positions(lidar.laser[returns], scene.lidar_origins)
            # each return's own ray, from where it now sits (moved to the box's time)
            # (a dense object's sweep: an even subset of SWEEP_RETURNS_PER_FRAME is moved and
            # registered, the registration takes max_points_per_frame of them anyway)
            kept = np.flatnonzero(inside)
            kept = kept[first_per_frame(owner[kept], point_priority(p[kept]), SWEEP_RETURNS_PER_FRAME)]
            on_surface, moved = points_on_sweep_surface(p[inside], owner[inside], p[inside] - ray[inside],
                                                        float(config.sweep_surface_max_m),
                                                        rows=np.searchsorted(np.flatnonzero(inside), kept))
            if moved.any():
                measured, p, owner, local = p[kept], on_surface, owner[kept], local[kept]
                inside = np.ones(kept.size, dtype=bool)
        if oid in static:              # one pose: nothing frame to frame to register (refine/static.py)
            result = dataclasses.replace(
                refine_object_poses(vehicle_from_box, boxes.size[rows], scene.world_from_vehicle[frames],
                                    p[inside], owner[inside], times,
                                    dataclasses.replace(config, enabled=False), name=f"{scene.segment}/{oid}"),
                reason=RefineReason.STATIC,
                detail="static: " + ("one world pose, the labels' mean" if oid in replaced
                                     else "the labels already hold one world pose"),
                num_points=np.bincount(owner[inside], minlength=rows.size).astype(np.int64))
        else:
            result = refine_object_poses(vehicle_from_box, boxes.size[rows], scene.world_from_vehicle[frames],
                                         p[inside], owner[inside], times, config,
                                         name=f"{scene.segment}/{oid}", points_measured=measured,
                                         wheeled=int(boxes.type[rows[0]]) in WHEELED_TYPES)
        if result.refined:
            update = {"center": result.center_vehicle, "heading": result.heading, "size": result.size}
            if tilted:
                update.update(pitch=result.pitch, roll=result.roll)
        elif oid in replaced and config.fit_extent:
            # the one world pose is the labels' mean: a label error of a centimetre or two puts a
            # face's returns just outside the box, as after registration (poses.py), so the box
            # is grown to hold the object's returns near it (a parked car lost half its returns)
            near = inside_box(local, boxes.size[rows][owner], config.inlier_margin_m, config.ground_clearance_m)
            if near.any():
                grow_lo, grow_hi = grown_extent(local[near], 0.5 * boxes.size[rows][owner[near]], config)
                if np.any(grow_hi > 0) or np.any(grow_lo > 0):
                    offset = np.broadcast_to((grow_hi - grow_lo) / 2.0, (rows.size, 3))
                    update = {"center": center[rows] + vectors_from_box(offset, heading[rows]),
                              "size": boxes.size[rows] + (grow_hi + grow_lo)}
        return result, update

    # objects on the segment's pool (drivetrack.parallel; the registration kernels release the
    # GIL), largest candidate sets first so the threads finish together; results in object order
    work = np.diff(bounds)

    def run(indices, motion) -> dict:
        order = sorted(indices, key=lambda k: (-int(work[k]), k))
        return dict(zip(order, pool_map(lambda k: refine_one(k, motion), order)))

    def with_updates(done: dict):
        out = Boxes(**{k: v for k, v in boxes.__dict__.items()})
        fields = {"center": center.copy(), "heading": heading.copy(), "size": size.copy(),
                  "pitch": None if pitch is None else pitch.copy(), "roll": None if roll is None else roll.copy()}
        for k, (_, update) in done.items():
            for name, values in update.items():
                fields[name][object_rows[k]] = values
        for name, values in fields.items():
            setattr(out, name, values)
        return out

    done = run(range(len(ids)), None if offsets is None else label_motion)
    # The labels' finite-difference motion moves each candidate to the frame time; with 5 cm
    # labels it is off by ~0.5 m/s, a centimetre of shear across a near object's sweep. Each
    # further pass moves the candidates with the motion of the boxes registered so far (objects
    # whose registration was applied; the others' motion is their labels', as before): the
    # least-squares slope over ``motion_window`` boxes either side, which averages out the
    # registration's centimetres in the directions no face pins down.
    for _ in range(config.motion_passes - 1 if offsets is not None else 0):
        again = [k for k in range(len(ids)) if done[k][0].refined and ids[k] not in static]
        if not again:
            break
        motion = scene_box_motion(dataclasses.replace(scene, boxes=with_updates(done)),
                                  half=config.motion_window, label_offset_s=label_offset_s)
        done.update(run(again, motion))
    results = {oid: done[k][0] for k, oid in enumerate(ids)}
    return with_updates(done), results


def _box_times(frame_s: np.ndarray, label_offset_s: np.ndarray | None) -> np.ndarray:
    """float64 [R] seconds: the times an object's boxes describe (frame times ``frame_s`` [R] plus
    ``label_offset_s`` [R], or the frame times when None), the motion prior's sample times. An
    object whose label times do not advance by at least half a frame period from box to box (a
    box on the sweep's seam behind the vehicle, labelled at the start of one sweep and the end of
    the next) keeps its frame times."""
    if label_offset_s is None or frame_s.size < 2:
        return frame_s
    times = frame_s + label_offset_s
    return times if np.all(np.diff(times) > 0.5 * np.diff(frame_s)) else frame_s


def _own_candidates(lidar, boxes, world_from_vehicle: np.ndarray, all_rows: np.ndarray, index: np.ndarray,
                    owner: np.ndarray, lasers, returns, config: RefineConfig,
                    use_kernel: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The candidates ``(index, owner)`` (returns ``index`` int [N] of box ``all_rows[owner]``) that
    may be the object's: with ``config.ground_ring``, none within :data:`GROUND_BAND_M` of the
    ground measured round the box (:func:`drivetrack.boxes.ground_under_boxes`) where that is
    higher than the box's own clearance (``config.ground_clearance_m`` over its bottom, which the
    registration applies to the current box); with ``config.exclusive_returns``, none that
    another object's box of the frame holds more deeply
    (:func:`drivetrack.boxes.claimed_by_other_boxes`; every box of the scene, annotated or not).
    Loosely drawn labels reach below the road and round their neighbours; their returns do not move
    with the object (docs/refinement.md, "Returns that are not the object's"). ``use_kernel``:
    both measured by their numba twins in ``drivetrack.refine.kernel`` (the same values)."""
    if index.size == 0 or not (config.ground_ring or config.exclusive_returns):
        return index, owner
    measure_ground, claimed = ground_under_boxes, claimed_by_other_boxes
    if use_kernel:
        from drivetrack.refine.kernel import claimed_by_other_boxes as claimed
        from drivetrack.refine.kernel import ground_under_boxes as measure_ground
    rows = all_rows[owner]
    points = lidar.points_vehicle[index]
    keep = np.ones(index.size, dtype=bool)
    if config.ground_ring:
        ground = measure_ground(lidar.points_vehicle, lidar.laser, lidar.return_index, lidar.frame_offsets,
                                boxes.frame[all_rows], boxes.center[all_rows], boxes.heading[all_rows],
                                boxes.size[all_rows], lasers, returns)
        ground = fill_ground_over_time(ground, boxes.frame[all_rows], boxes.object_id[all_rows].astype(str),
                                       boxes.center[all_rows], world_from_vehicle)
        bottom = -0.5 * boxes.size[all_rows, 2]
        lift = ground - bottom
        measured = np.isfinite(lift) & (lift <= GROUND_MAX_RISE_M)
        raised = measured & (ground + GROUND_BAND_M > bottom + config.ground_clearance_m)
        if np.any(raised):
            z = points[:, 2] - boxes.center[rows, 2]              # body z: the labels are yaw-only
            keep &= ~raised[owner] | (z >= ground[owner] + GROUND_BAND_M)
    if config.exclusive_returns:
        keep &= ~claimed(points, rows, boxes.frame, boxes.object_id.astype(str), boxes.center, boxes.heading,
                         boxes.size)
    return index[keep], owner[keep]


def _frame_time_candidates(points: np.ndarray, index: np.ndarray, owner: np.ndarray, rows: np.ndarray,
                           offsets: np.ndarray, label_offset_s: np.ndarray | None, center: np.ndarray,
                           heading: np.ndarray, velocity: np.ndarray, yaw_rate: np.ndarray,
                           pitch: np.ndarray | None, roll: np.ndarray | None, size: np.ndarray, margin: float):
    """An object's candidate returns moved to its boxes' time, those inside the grown boxes kept.

    Candidate c is return ``index[c]`` (rows of ``points`` float [M, 3], vehicle frame of its frame;
    ``offsets`` float [M] capture time minus frame time, s) of the object's box ``rows[owner[c]]``
    (rows of the scene's box arrays ``center`` [K, 3], ``heading`` [K], ``velocity`` [K, 3] m/s,
    ``yaw_rate`` [K] rad/s, ``pitch`` / ``roll`` [K] or None, ``size`` [K, 3]; ``label_offset_s``
    [K] the box's time minus the frame time, None: 0). The box is moved to the capture time
    (:func:`drivetrack.tracks.sweep_motion.points_box_at_capture`), the body point tested against
    the box grown by ``margin`` (:func:`drivetrack.boxes.inside_box`), and a kept one taken back
    into the vehicle frame with the box's pose at its own time.

    Returns:
        ``(local float64 [P, 3], vehicle float64 [P, 3], owner int64 [P], position int64 [P])`` of
        the kept candidates, in candidate order (``position``: theirs in ``index``).
        ``drivetrack.refine.kernel.frame_time_candidates`` is the fused twin.
    """
    from drivetrack.tracks.sweep_motion import points_box_at_capture

    r = rows[owner]
    dt = offsets[index] if label_offset_s is None else offsets[index] - label_offset_s[r]
    tilt = (None, None) if pitch is None and roll is None else \
        tuple(np.zeros(r.size) if a is None else a[r] for a in (pitch, roll))
    local = points_box_at_capture(points[index], dt, center[r], heading[r], velocity[r], yaw_rate[r], *tilt)
    inside = inside_box(local, size[r], margin)
    local, owner, r = local[inside], np.asarray(owner, np.int64)[inside], r[inside]
    tilt = (None, None) if tilt[0] is None else (tilt[0][inside], tilt[1][inside])
    vehicle = vectors_from_box(local, heading[r], *tilt) + center[r]
    return local, vehicle, owner, np.flatnonzero(inside).astype(np.int64)
