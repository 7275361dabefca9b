"""Segment planning: which (camera, object) clips to annotate, and why the others are not.

Everything here is cheap (boxes and their LiDAR points only, no depth maps) so the depth stage
can be restricted to the frames that accepted clips need. Terms, used the same way everywhere:

- *in view* at frame t, for a camera: the object is labelled at t, the camera has an image at t,
  and at least one of ``fov_samples_per_axis**3`` grid samples of the box (corners, edges, faces,
  interior) projects inside the image, in front of the camera, with trusted distortion. Occluded
  objects count as in view (the paper: "either visible or occluded"). Global-shutter projection
  at the image pose.
- *run*: a maximal set of consecutive frames in view. The *clip* of an accepted job is one run.
- an object whose in-view frames form several runs "left and came back". With the default policy
  ``fov_runs="reject"`` it is rejected, under ``label_gap`` if a frame between the runs has no
  label for the object (a hole in the labels), ``image_gap`` if a frame between the runs has no
  camera image, ``left_and_returned`` otherwise. ``fov_runs="longest"`` keeps the longest run
  (earliest on ties).
- *camera distance*: from the camera centre (at the image pose) to the box centre, metres.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from drivetrack.boxes import returns_in_boxes
from drivetrack.geometry import invert_rigid, transform_points
from drivetrack.outputs import RejectionReason
from drivetrack.scene import Scene
from drivetrack.tracks.config import TrackConfig
from drivetrack.waymo.schema import BoxType, CameraName

__all__ = ["CameraGeometry", "ObjectJob", "SegmentPlan", "label_jitter_m", "plan_segment",
           "box_members", "camera_geometry", "continuous_runs", "select_object_points"]


@dataclass
class CameraGeometry:
    """Per-frame poses of one camera over a segment (T frames).

    Attributes:
        camera: ``CameraName`` value.
        camera_from_vehicle: float64 [T, 4, 4]; *vehicle* is the vehicle frame of frame t (the
            frame of that frame's LiDAR returns and boxes); the camera sits at the image's pose
            (``camera_image.pose``; the frame pose where the image pose is missing).
        camera_from_world: float64 [T, 4, 4].
        camera_centre_world: float64 [T, 3], metres.
        has_image: bool [T], the camera has an image at frame t.
    """
    camera: int
    camera_from_vehicle: np.ndarray
    camera_from_world: np.ndarray
    camera_centre_world: np.ndarray
    has_image: np.ndarray


@dataclass
class ObjectJob:
    """One (segment, camera, object) clip that passed the planning filters.

    Attributes:
        camera: ``CameraName`` value.
        object_id: ``key.laser_object_id``.
        object_type: ``BoxType`` value.
        frames: int64 [T], the clip's frame indices in the segment (consecutive).
        box_rows: int64 [T], row of the object's box in ``scene.boxes`` at each clip frame.
        min_camera_distance_m: closest camera-to-box-centre distance over the clip, metres.
        num_points: LiDAR returns inside the box over the clip (candidate tracks).
    """
    camera: int
    object_id: str
    object_type: int
    frames: np.ndarray
    box_rows: np.ndarray
    min_camera_distance_m: float
    num_points: int

    @property
    def camera_name(self) -> str:
        return CameraName(self.camera).name

    @property
    def key(self) -> tuple[int, str]:
        return (self.camera, self.object_id)


@dataclass
class SegmentPlan:
    """Result of :func:`plan_segment`.

    Attributes:
        scene, config: inputs (shared, never copied).
        cameras: camera value -> :class:`CameraGeometry` for every camera in the scene.
        box_point_offsets: int64 [K + 1]; returns of box row k are
            ``box_point_index[box_point_offsets[k]:box_point_offsets[k + 1]]`` (rows of
            ``scene.lidar``), selected by type, laser, return, margin and ground clearance.
            Rows of objects whose type is not selected have no points.
        box_point_index: int64 [P].
        jobs: accepted clips.
        rejections: one dict per rejected clip: camera, object_id, object_type, reason, detail.
        num_objects_labelled: distinct object ids in the segment.
        num_clips_considered: (camera in scene) x (object) pairs examined.
    """
    scene: Scene
    config: TrackConfig
    cameras: dict[int, CameraGeometry]
    box_point_offsets: np.ndarray
    box_point_index: np.ndarray
    jobs: list[ObjectJob] = field(default_factory=list)
    rejections: list[dict] = field(default_factory=list)
    num_objects_labelled: int = 0
    num_clips_considered: int = 0
    #: object id -> float64 [m, 3], its selected returns over the segment in its box frame, thinned
    #: (drivetrack.tracks.core.segment_surface): the z-buffer's occluder surfaces and the back-face
    #: normals' neighbourhoods, reused across clips.
    occluder_cache: dict = field(default_factory=dict, repr=False, compare=False)

    def box_points(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """LiDAR rows of box rows ``rows`` (int [R]) and, for each, its position in ``rows``."""
        return box_members(self.box_point_offsets, self.box_point_index, rows)


def box_members(offsets: np.ndarray, index: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(members, owner)`` of box rows ``rows`` (int [R]) in the CSR ``(offsets int [K + 1],
    index int [P])`` of :func:`select_object_points`: their members in order, and for each the
    position of its box row in ``rows``."""
    rows = np.asarray(rows, dtype=np.int64)
    starts, stops = offsets[rows], offsets[rows + 1]
    counts = stops - starts
    owner = np.repeat(np.arange(rows.shape[0]), counts)
    within = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
    return index[np.repeat(starts, counts) + within], owner


def label_jitter_m(scene: Scene) -> float:
    """The labels' frame-to-frame jitter in the segment (metres, the sigma per ground-plane axis),
    from the second differences of each object's label centres in the world frame over three
    consecutive frames (``c[t+1] - 2 c[t] + c[t-1]``: 0 for a still object and for steady
    motion, ``a dt^2`` under an acceleration ``a``, 1 cm at 1 m/s^2 and 10 Hz): the median over
    the objects of each one's median step, over ``sqrt(6) * sqrt(2 ln 2)`` (the median length of
    that difference for independent jitters of that sigma per axis), to the micrometre. 0 for
    exact labels (and for a still object whose box was copied from frame to frame), centimetres
    for hand labels; NaN when no object has three consecutive boxes. Measured on the labels as
    delivered (``scene.box_labels`` where the boxes were refined: the refinement smooths them)."""
    boxes = scene.box_labels if getattr(scene, "box_labels", None) is not None else scene.boxes
    if boxes.center.shape[0] == 0:
        return float("nan")
    centre_vehicle = np.concatenate([boxes.center, np.ones((boxes.center.shape[0], 1))], axis=1)
    centre_world = np.einsum("nij,nj->ni", scene.world_from_vehicle[boxes.frame], centre_vehicle)[:, :2]
    order = np.lexsort((boxes.frame, boxes.object_id))
    frame, owner, xy = boxes.frame[order], boxes.object_id[order], centre_world[order]
    # triples of one object in three consecutive frames
    whole = (owner[2:] == owner[:-2]) & (frame[1:-1] == frame[:-2] + 1) & (frame[2:] == frame[:-2] + 2)
    if not whole.any():
        return float("nan")
    step = np.linalg.norm(xy[2:] - 2.0 * xy[1:-1] + xy[:-2], axis=1)[whole]
    ids, inverse = np.unique(owner[:-2][whole], return_inverse=True)
    per_object = [float(np.median(step[inverse == k])) for k in range(ids.size)]
    return round(float(np.median(per_object) / (np.sqrt(6.0) * np.sqrt(2.0 * np.log(2.0)))), 6)


def continuous_runs(mask: np.ndarray) -> np.ndarray:
    """int64 [R, 2] (first, last) frame of each run of True in bool [T] (inclusive), in order."""
    mask = np.asarray(mask, dtype=bool)
    padded = np.concatenate([[False], mask, [False]])
    edges = np.flatnonzero(padded[1:] != padded[:-1])
    return np.stack([edges[0::2], edges[1::2] - 1], axis=-1).astype(np.int64)


def _check_scene(scene: Scene) -> None:
    t = scene.num_frames
    where = f"segment {scene.segment!r}"
    if scene.world_from_vehicle.shape != (t, 4, 4):
        raise ValueError(f"{where}: world_from_vehicle has shape {scene.world_from_vehicle.shape}, "
                         f"expected ({t}, 4, 4)")
    if not np.all(np.isfinite(scene.world_from_vehicle)):
        bad = np.flatnonzero(~np.isfinite(scene.world_from_vehicle).all(axis=(1, 2)))
        raise ValueError(f"{where}: vehicle_pose is missing or not finite at frames {bad[:10].tolist()}")
    if np.any(np.diff(scene.timestamps_micros) <= 0):
        raise ValueError(f"{where}: timestamps_micros are not strictly increasing")
    boxes = scene.boxes
    if len(boxes) and (boxes.frame.min() < 0 or boxes.frame.max() >= t):
        raise ValueError(f"{where}: lidar_box frame index out of range [0, {t}): "
                         f"{int(boxes.frame.min())}..{int(boxes.frame.max())}")
    if len(boxes):
        order = np.lexsort((boxes.frame, boxes.object_id.astype(str)))
        ids, frames = boxes.object_id[order].astype(str), boxes.frame[order]
        dup = np.flatnonzero((ids[1:] == ids[:-1]) & (frames[1:] == frames[:-1]))
        if dup.size:
            i = dup[0]
            raise ValueError(f"{where}: object {ids[i]!r} has {int(np.sum((ids == ids[i]) & (frames == frames[i])))} "
                             f"boxes at frame {int(frames[i])} (lidar_box key not unique)")
        finite = (np.isfinite(boxes.center).all(axis=1) & np.isfinite(boxes.size).all(axis=1)
                  & np.isfinite(boxes.heading))
        if not finite.all():
            i = int(np.flatnonzero(~finite)[0])
            raise ValueError(f"{where}: box of object {boxes.object_id[i]!r} at frame {int(boxes.frame[i])} "
                             f"has a non-finite center/size/heading")
    lidar = scene.lidar
    if lidar.frame_offsets.shape != (t + 1,):
        raise ValueError(f"{where}: lidar.frame_offsets has shape {lidar.frame_offsets.shape}, expected ({t + 1},)")


def camera_geometry(scene: Scene, camera: int) -> CameraGeometry:
    """Per-frame poses of camera ``camera`` (see :class:`CameraGeometry`)."""
    frames = scene.cameras[camera]
    t = scene.num_frames
    image_world_from_vehicle = np.asarray(frames.world_from_vehicle, dtype=np.float64)
    if image_world_from_vehicle.shape != (t, 4, 4):
        raise ValueError(f"segment {scene.segment!r} camera {CameraName(camera).name}: image poses have "
                         f"shape {image_world_from_vehicle.shape}, expected ({t}, 4, 4)")
    missing = ~np.isfinite(image_world_from_vehicle).all(axis=(1, 2))
    image_world_from_vehicle = np.where(missing[:, None, None], scene.world_from_vehicle,
                                        image_world_from_vehicle)
    camera_from_world = frames.model.camera_from_vehicle @ invert_rigid(image_world_from_vehicle)
    camera_from_vehicle = camera_from_world @ scene.world_from_vehicle
    camera_centre_world = (image_world_from_vehicle @ frames.model.vehicle_from_camera)[:, :3, 3]
    if len(frames.jpeg) != t:
        raise ValueError(f"segment {scene.segment!r} camera {CameraName(camera).name}: {len(frames.jpeg)} "
                         f"images for {t} frames")
    has_image = np.array([j is not None for j in frames.jpeg], dtype=bool)
    return CameraGeometry(camera, camera_from_vehicle, camera_from_world, camera_centre_world, has_image)


def select_object_points(scene: Scene, config: TrackConfig, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """LiDAR returns inside box rows ``rows`` (int [R]) as CSR over all K box rows.

    A return belongs to a box when it is of a selected laser and return index, lies inside the
    box grown by ``box_margin_m`` and at least ``ground_clearance_m`` above the box bottom. With
    ``config.compensate_sweep_motion`` and ``lidar.capture_offset_s``, the box is moved to each
    return's capture time first, from the box's label time under ``time_model="trajectory"``
    (:func:`drivetrack.tracks.trajectory.scene_label_times`). See :func:`drivetrack.boxes.returns_in_boxes`.

    Returns:
        ``(offsets int64 [K + 1], index int64 [P])`` (rows not in ``rows`` get no points).
    """
    label_offset_s = None
    if config.time_model == "trajectory" and config.compensate_sweep_motion:
        from drivetrack.tracks.trajectory import scene_label_times

        label_offset_s = scene_label_times(scene, config)[0]
    return returns_in_boxes(scene, rows, config.laser_values, config.returns, config.box_margin_m,
                            config.ground_clearance_m, config.compensate_sweep_motion, label_offset_s)


def _unit_grid(n: int) -> np.ndarray:
    """float64 [n**3, 3] grid over [-0.5, 0.5]^3."""
    axis = np.linspace(-0.5, 0.5, n)
    return np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)


def _boxes_in_view(scene: Scene, geometry: CameraGeometry, rows: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """bool [R]: box rows ``rows`` in view of the camera at their frame (see module docstring)."""
    boxes = scene.boxes
    model = scene.cameras[geometry.camera].model
    vehicle_from_box = boxes.vehicle_from_box(rows)
    samples_box = grid[None, :, :] * boxes.size[rows][:, None, :]
    camera_from_box = geometry.camera_from_vehicle[boxes.frame[rows]] @ vehicle_from_box
    pixels, valid = model.pixels_from_camera(transform_points(camera_from_box, samples_box))
    seen = (valid & model.inside_image(pixels)).any(axis=-1)
    return seen & geometry.has_image[boxes.frame[rows]]


def plan_segment(scene: Scene, config: TrackConfig, select_points: bool = True) -> SegmentPlan:
    """Apply the cheap filters to every (camera, object) of ``scene``; see the module docstring.

    Rejections are recorded in ``plan.rejections`` with one reason from
    :class:`drivetrack.outputs.RejectionReason` each; accepted clips become ``plan.jobs``.

    ``select_points=False`` skips the selection of each box's LiDAR returns (the costly part on a
    full segment) and with it the ``no_points`` filter: enough to know which clips pass the
    camera, type, view, frames and distance filters (pose refinement asks only that); the plan's
    :meth:`SegmentPlan.box_points` then returns no points.
    """
    _check_scene(scene)
    boxes = scene.boxes
    object_ids = boxes.object_id.astype(str)
    ids = sorted(set(object_ids.tolist()))
    type_ok_rows = np.flatnonzero(np.isin(boxes.type, config.object_type_values))
    if select_points:
        # the occluders' returns too (TrackConfig.occluder_types): the z-buffer splats them
        offsets, index = select_object_points(scene, config,
                                              np.flatnonzero(np.isin(boxes.type, config.returns_type_values)))
    else:
        offsets, index = np.zeros(len(boxes) + 1, dtype=np.int64), np.zeros(0, dtype=np.int64)
    cameras = {int(c): camera_geometry(scene, int(c)) for c in sorted(scene.cameras)}
    plan = SegmentPlan(scene, config, cameras, offsets, index, num_objects_labelled=len(ids))
    points_per_row = np.diff(offsets)
    grid = _unit_grid(config.fov_samples_per_axis)
    t_count = scene.num_frames

    rows_of = {oid: np.flatnonzero(object_ids == oid) for oid in ids}
    in_view_rows = {c: np.zeros(len(boxes), dtype=bool) for c in cameras}
    for c in cameras:
        if c in config.camera_values and type_ok_rows.size:
            in_view_rows[c][type_ok_rows] = _boxes_in_view(scene, cameras[c], type_ok_rows, grid)

    for c, geometry in cameras.items():
        for oid in ids:
            rows = rows_of[oid]
            rows = rows[np.argsort(boxes.frame[rows])]
            object_type = int(np.bincount(boxes.type[rows].astype(np.int64)).argmax())
            plan.num_clips_considered += 1

            def reject(reason: RejectionReason, detail: str = "") -> None:
                plan.rejections.append({"camera": c, "object_id": oid, "object_type": object_type,
                                        "reason": reason, "detail": detail})

            if c not in config.camera_values:
                reject(RejectionReason.CAMERA, f"camera {CameraName(c).name} not in {list(config.cameras)}")
                continue
            if object_type not in config.object_type_values:
                reject(RejectionReason.OBJECT_TYPE,
                       f"type {BoxType(object_type).name} not in {list(config.object_types)}")
                continue
            labelled = np.zeros(t_count, dtype=bool)
            labelled[boxes.frame[rows]] = True
            row_at = np.full(t_count, -1, dtype=np.int64)
            row_at[boxes.frame[rows]] = rows
            in_view = np.zeros(t_count, dtype=bool)
            in_view[boxes.frame[rows]] = in_view_rows[c][rows]
            runs = continuous_runs(in_view)
            if runs.shape[0] == 0:
                reject(RejectionReason.NOT_IN_VIEW)
                continue
            if runs.shape[0] > 1:
                spans = ", ".join(f"{a}-{b}" for a, b in runs.tolist())
                between = np.arange(runs[0, 0], runs[-1, 1] + 1)
                between = between[~in_view[between]]
                if config.fov_runs == "reject":
                    if (~labelled[between]).any():
                        missing = between[~labelled[between]]
                        reject(RejectionReason.LABEL_GAP, f"in view in frames {spans}; no label at frames "
                                            f"{missing[:10].tolist()}")
                    elif (~geometry.has_image[between]).any():
                        missing = between[~geometry.has_image[between]]
                        reject(RejectionReason.IMAGE_GAP, f"in view in frames {spans}; no image at frames "
                                            f"{missing[:10].tolist()}")
                    else:
                        reject(RejectionReason.LEFT_AND_RETURNED, f"in view in frames {spans}")
                    continue
                lengths = runs[:, 1] - runs[:, 0]
                run = runs[int(np.argmax(lengths))]
            else:
                run = runs[0]
            frames = np.arange(run[0], run[1] + 1, dtype=np.int64)
            if frames.size < config.min_frames:
                reject(RejectionReason.TOO_FEW_FRAMES, f"in view for {frames.size} frames ({run[0]}-{run[1]}), "
                                         f"need {config.min_frames}")
                continue
            clip_rows = row_at[frames]
            centres_world = transform_points(scene.world_from_vehicle[frames], boxes.center[clip_rows][:, None, :])[:, 0]
            distance = float(np.min(np.linalg.norm(centres_world - geometry.camera_centre_world[frames], axis=-1)))
            if distance > config.max_camera_distance_m:
                reject(RejectionReason.TOO_FAR, f"closest {distance:.1f} m > {config.max_camera_distance_m} m")
                continue
            num_points = int(points_per_row[clip_rows].sum())
            if num_points == 0 and select_points:
                reject(RejectionReason.NO_POINTS, f"no LiDAR return in the box over frames {run[0]}-{run[1]}")
                continue
            plan.jobs.append(ObjectJob(c, oid, object_type, frames, clip_rows, distance, num_points))
    return plan
