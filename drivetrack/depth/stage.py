"""The depth stage of a segment: per (camera, frame) occlusion depth maps, staged for a queue.

Split so an orchestrator can stage it: :func:`depth_jobs` lists the (camera, frame batch) units,
:func:`sparse_depth` projects a batch's LiDAR (CPU), :func:`complete_depth` densifies it with the
configured completer (the GPU-queue unit). The pipeline's unit is a :class:`DepthBatch`
(:func:`sparse_depth_batches` -> :func:`complete_depth_batch`, re-exported by
:mod:`drivetrack.annotate`); the track stage takes the completed maps through
:func:`drivetrack.tracks.context.prepare_segment`.

Only frames that an accepted clip of that camera needs get a depth map. The track-stage modules
this one reads (``tracks.config``, ``tracks.plan``) are imported for type checking or inside the
functions, so that ``drivetrack.tracks`` may import this module without a cycle.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Iterable

import numpy as np

from drivetrack.geometry import invert_rigid, rigid_velocity_world
from drivetrack.scene import Scene
from drivetrack.waymo.schema import CameraName

if TYPE_CHECKING:
    from drivetrack.annotate import AnnotateConfig
    from drivetrack.tracks.config import TrackConfig
    from drivetrack.tracks.plan import SegmentPlan

__all__ = ["DepthJob", "DepthBatch", "needed_frames", "depth_jobs", "sparse_depth", "complete_depth", "motion_at_image_time",
           "labelled_moves", "sparse_depth_batch", "sparse_depth_batches", "complete_depth_batch"]


@dataclass(frozen=True)
class DepthJob:
    """A batch of frames of one camera whose depth maps are computed together.

    Attributes:
        camera: ``CameraName`` value.
        frames: int64 [B], frame indices (sorted).
    """
    camera: int
    frames: np.ndarray


def needed_frames(plan: SegmentPlan) -> dict[int, np.ndarray]:
    """Camera value -> int64 [F] sorted frames that an accepted clip of that camera needs."""
    needed: dict[int, set] = {}
    for job in plan.jobs:
        needed.setdefault(job.camera, set()).update(job.frames.tolist())
    return {c: np.array(sorted(f), dtype=np.int64) for c, f in sorted(needed.items())}


def depth_jobs(scene: Scene, config: TrackConfig, plan: SegmentPlan | None = None,
               batch: int | None = None) -> list[DepthJob]:
    """The depth units of a segment: per camera, its needed frames in batches of ``batch`` frames
    (default ``config.depth_batch``, the GPU-queue unit; the maps do not depend on it)."""
    from drivetrack.tracks.plan import plan_segment

    plan = plan if plan is not None else plan_segment(scene, config)
    size = int(batch) if batch is not None else config.depth_batch
    if size < 1:
        raise ValueError(f"depth_jobs: batch must be >= 1 frame, got {batch}")
    jobs = []
    for camera, frames in needed_frames(plan).items():
        for start in range(0, frames.size, size):
            jobs.append(DepthJob(camera, frames[start:start + size]))
    return jobs


def _labelled_motion(scene: Scene, config: TrackConfig, plan: SegmentPlan | None):
    """(owner int64 [M], trajectory, memo dict) for moving labelled returns to image time, or None.

    ``owner[i]`` is the box row whose object return ``i`` of ``scene.lidar`` belongs to (-1: none),
    from the track stage's point selection; the trajectory is the segment's
    (:func:`drivetrack.tracks.trajectory.segment_trajectory`). None when
    ``config.depth_object_motion`` is off or ``config.time_model`` is not ``trajectory``. Without
    ``plan`` one is made (:func:`drivetrack.tracks.plan.plan_segment`) and kept on the scene. The
    memo keeps, per frame, the labelled returns' box-frame positions (:func:`points_at_image_time`).
    """
    if not config.depth_object_motion or config.time_model != "trajectory":
        return None
    from drivetrack.tracks.plan import plan_segment
    from drivetrack.tracks.trajectory import segment_trajectory

    if plan is None:
        plans = scene.__dict__.setdefault("_depth_plans", {})
        key = repr(config.to_dict())
        if key not in plans:
            plans[key] = plan_segment(scene, config)
        plan = plans[key]
    cache = plan.__dict__.setdefault("_depth_motion", {})
    if "owner" not in cache:
        owner = np.full(scene.lidar.points_vehicle.shape[0], -1, dtype=np.int64)
        lidar_rows, box_rows = plan.box_points(np.arange(plan.box_point_offsets.size - 1))
        owner[lidar_rows] = box_rows
        cache["owner"] = owner
    return cache["owner"], segment_trajectory(plan)[0], cache.setdefault("points_box", {})


def points_at_image_time(scene: Scene, config: TrackConfig, owner: np.ndarray, trajectory, camera: int,
                         frame: int, rows: np.ndarray, points_vehicle: np.ndarray,
                         memo: dict | None = None) -> np.ndarray:
    """float64 [n, 3]: returns ``rows`` (int [n], rows of ``scene.lidar`` of ``frame``; vehicle frame
    of the frame, ``points_vehicle`` float [n, 3]) with each labelled object's returns moved on its
    trajectory from their capture time to the pose time of ``camera``'s image of ``frame``
    (vehicle frame of the frame, still). Unlabelled returns are unchanged.

    The labelled returns' box-frame positions do not depend on the camera: with ``memo`` (a dict
    kept with the plan, :func:`_labelled_motion`) they are computed once per frame; each object is
    then posed once per image, not once per return.
    """
    return motion_at_image_time(scene, config, owner, trajectory, camera, frame, rows, points_vehicle, memo,
                                with_velocity=False)[0]


def motion_at_image_time(scene: Scene, config: TrackConfig, owner: np.ndarray, trajectory, camera: int,
                         frame: int, rows: np.ndarray, points_vehicle: np.ndarray,
                         memo: dict | None = None, with_velocity: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """``(points float64 [n, 3], velocity_world float64 [n, 3])``: the points of
    :func:`points_at_image_time` and each one's world velocity (m/s) at the image's pose time, the
    rigid motion of its object (centre velocity plus yaw rate about the world z) for labelled
    returns, 0 for the others (what a rolling-shutter projection moves them by during the readout;
    None without ``with_velocity``: a global-shutter map does not need it)."""
    out = np.array(points_vehicle, dtype=np.float64)
    velocity_world = np.zeros_like(out) if with_velocity else None
    moves = labelled_moves(scene, config, owner, trajectory, camera, frame, rows, out, memo, with_velocity)
    if moves is not None:
        moving, moved, velocity, _ = moves
        out[moving] = moved
        if with_velocity:
            velocity_world[moving] = velocity
    return out, velocity_world


def labelled_moves(scene: Scene, config: TrackConfig, owner: np.ndarray, trajectory, camera: int, frame: int,
                   rows: np.ndarray, points_vehicle: np.ndarray, memo: dict | None = None,
                   with_velocity: bool = False):
    """The labelled returns of :func:`motion_at_image_time` alone, without a copy of all the
    frame's returns: ``(moving int64 [k]`` (their places in ``rows``), ``moved float64 [k, 3]``
    (their positions at the image's pose time, vehicle frame of the frame), ``velocity_world
    float64 [k, 3]`` (None without ``with_velocity``), ``skip bool [n]`` (``moving`` as a mask,
    kept with the memo)``)``; None when no return is labelled."""
    from drivetrack.tracks.core import image_time_offsets

    labelled = _labelled_points_box(scene, config, trajectory, frame, rows, owner, points_vehicle,
                                    {} if memo is None else memo)
    if labelled is None:
        return None
    moving, unique_rows, starts, points_box, skip = labelled
    image_time = trajectory.frame_time_s[unique_rows] + image_time_offsets(scene, camera, np.array([frame]))[0]
    world_from_vehicle = scene.world_from_vehicle[frame]
    world_from_box = trajectory.world_from_box(unique_rows, image_time)                            # [u, 4, 4]
    vehicle_from_box = invert_rigid(world_from_vehicle)[None] @ world_from_box
    moved = np.empty_like(points_box)
    # the returns are grouped by object (the memo's order): one small product per object
    for j in range(unique_rows.size):
        part = slice(starts[j], starts[j + 1])
        moved[part] = points_box[part] @ vehicle_from_box[j, :3, :3].T + vehicle_from_box[j, :3, 3]
    velocity_world = None
    if with_velocity:
        _, _, _, _, velocity, yaw_rate = trajectory.motion(unique_rows, image_time)
        which = np.repeat(np.arange(unique_rows.size), np.diff(starts))
        velocity_world = rigid_velocity_world(moved @ world_from_vehicle[:3, :3].T + world_from_vehicle[:3, 3],
                                              world_from_box[which, :3, 3], velocity[which], yaw_rate[which])
    return moving, moved, velocity_world, skip


def _labelled_points_box(scene: Scene, config: TrackConfig, trajectory, frame: int, rows: np.ndarray,
                         owner: np.ndarray, points_vehicle: np.ndarray, memo: dict):
    """The labelled ones of returns ``rows`` (int [n] of ``frame``, at ``points_vehicle`` float
    [n, 3] in the vehicle frame of ``frame``; ``owner`` their box rows, -1: none) in their box frame
    at their capture time, grouped by box row: ``(moving int64 [k]`` (their places in ``rows``),
    ``unique_rows int64 [u]``, ``starts int64 [u + 1]`` (each box row's returns are
    ``starts[j]:starts[j + 1]``), ``points_box float64 [k, 3]``, ``skip bool [n]``: ``moving`` as
    a mask``)``; None when none is labelled.
    Memoised in ``memo`` per frame and set of rows (the same for every camera; the rows are kept
    with the entry and compared, which costs less than hashing them)."""
    from drivetrack.tracks.trajectory import points_box_at

    key = (frame, rows.size)
    entry = memo.get(key)                           # one look-up: depth jobs share the memo across threads
    if entry is not None and np.array_equal(entry[0], rows):
        return entry[1]
    # not yet computed, or another set of rows of this frame (replaced)
    box_rows = owner[rows]
    moving = np.flatnonzero(box_rows >= 0)
    if moving.size == 0:
        memo[key] = (rows.copy(), None)
        return None
    moving = moving[np.argsort(box_rows[moving], kind="stable")]
    box_rows = box_rows[moving]
    unique_rows, starts = np.unique(box_rows, return_index=True)
    lidar = scene.lidar
    offsets = (np.nan_to_num(lidar.capture_offset_s[rows[moving]].astype(np.float64))
               if config.compensate_sweep_motion and lidar.capture_offset_s is not None else 0.0)
    world_from_vehicle = scene.world_from_vehicle[frame]
    world = points_vehicle[moving] @ world_from_vehicle[:3, :3].T + world_from_vehicle[:3, 3]
    skip = np.zeros(rows.size, dtype=bool)
    skip[moving] = True
    labelled = (moving, unique_rows, np.append(starts, moving.size).astype(np.int64),
                points_box_at(trajectory, box_rows, trajectory.frame_time_s[box_rows] + offsets, world), skip)
    memo[key] = (rows.copy(), labelled)
    return labelled


#: A rolling-shutter depth map solves the capture time of the returns within this fraction of
#: the image's larger side of the image at its pose time (:func:`sparse_depth`).
ROLLING_MARGIN = 0.25


def _near_image(points_vehicle: np.ndarray, model, vehicle_from_points: np.ndarray | None) -> np.ndarray:
    """int64 [k]: the returns float [n, 3] (vehicle frame of their frame, ``vehicle_from_points``
    float64 [4, 4] to the vehicle frame at the image pose, or None) in front of the camera and
    within ``ROLLING_MARGIN`` of the image (trusted distortion) at the image's pose time."""
    points = np.asarray(points_vehicle, np.float64)
    if vehicle_from_points is not None:
        points = points @ vehicle_from_points[:3, :3].T + vehicle_from_points[:3, 3]
    camera_from_vehicle = model.camera_from_vehicle
    points_camera = points @ camera_from_vehicle[:3, :3].T + camera_from_vehicle[:3, 3]
    pad = ROLLING_MARGIN * max(model.width, model.height)
    # a cheap cone first (undistorted, twice the padded field of view), then the distortion
    reach = 2.0 * (max(model.width, model.height) + pad) / min(model.f_u, model.f_v)
    x = points_camera[:, 0]
    cone = np.flatnonzero((x > 0) & (np.abs(points_camera[:, 1]) < reach * x) & (np.abs(points_camera[:, 2]) < reach * x))
    pixels, valid = model.pixels_from_camera(points_camera[cone])
    with np.errstate(invalid="ignore"):
        near = (valid & (pixels[:, 0] >= -pad) & (pixels[:, 0] < model.width + pad)
                & (pixels[:, 1] >= -pad) & (pixels[:, 1] < model.height + pad))
    return cone[near]


def sparse_depth(scene: Scene, config: TrackConfig, job: DepthJob, plan: SegmentPlan | None = None) -> np.ndarray:
    """float32 [B, H, W] sparse z-depth maps of ``job`` from the LiDAR: > 0 a return, 0 none, < 0 a bound.

    Uses the returns of ``config.depth_lasers`` and ``config.depth_returns`` (default: first
    returns of every lidar). Returns are moved from the frame's vehicle frame
    to the vehicle frame at the image's pose before projection, so that the maps agree with the
    track projection (the ego vehicle moves between the LiDAR and the camera timestamps); under a
    rolling shutter (``config.rolling_shutter`` and the image's timing) each return near the image
    is projected at its capture time in its row instead (``rolling_shutter.project_world``;
    labelled objects' returns with their rigid velocity, :func:`motion_at_image_time`). With
    ``config.see_through_window_deg``, returns the camera cannot see (the LiDAR saw them past a
    nearer surface) are then removed (:func:`drivetrack.depth.see_through_returns`). With
    ``config.blind_zone_laser``, the region below that lidar's lowest scan line (its first
    returns: second returns lie behind an edge) is bounded by the line's depth
    (:func:`drivetrack.depth.bound_blind_zone`): pixels there without a return hold ``-bound``
    (:func:`complete_depth` applies it after completion). With ``config.depth_object_motion`` (and
    the trajectory time model), each labelled object's returns are first moved on its trajectory to
    the image's pose time (:func:`points_at_image_time`; ``plan``: the segment's, or one made once
    per scene and configuration).
    """
    from drivetrack.boxes import return_mask
    from drivetrack.depth import (bound_blind_zone, horizontal_depth_scale, see_through_returns,
                                  sparse_depth_from_points)
    from drivetrack.waymo.schema import LaserName

    from drivetrack.camera.rolling_shutter import project_world, shutter_state
    from drivetrack.depth import sparse_depth_from_pixels

    frames = scene.cameras[job.camera]
    model = frames.model
    lidar = scene.lidar
    out = np.zeros((job.frames.size, model.height, model.width), dtype=np.float32)
    window_px = max(1, int(round(model.f_u * np.tan(np.radians(config.see_through_window_deg or 0.5)))))
    scale = horizontal_depth_scale(model) if config.blind_zone_laser is not None else None
    motion = _labelled_motion(scene, config, plan)
    for i, t in enumerate(job.frames.tolist()):
        part = lidar.of_frame(t)
        points = lidar.points_vehicle[part]
        lasers, returns = lidar.laser[part], lidar.return_index[part]
        keep = return_mask(lasers, returns, config.depth_laser_values, config.depth_returns)
        if not keep.all():
            points, lasers, returns = points[keep], lasers[keep], returns[keep]
        velocity_world = replace = None
        rolling = config.rolling_shutter and shutter_state(frames, t).rolling
        if motion is not None and rolling:
            rows = np.arange(part.start, part.stop, dtype=np.int64)[keep]
            points, velocity_world = motion_at_image_time(scene, config, *motion[:2], job.camera, t, rows, points,
                                                          memo=motion[2], with_velocity=True)
        elif motion is not None:
            # the map takes the moved returns in place of theirs (no copy of the frame's returns)
            rows = np.arange(part.start, part.stop, dtype=np.int64)[keep]
            moves = labelled_moves(scene, config, *motion[:2], job.camera, t, rows, points, memo=motion[2])
            replace = None if moves is None else (moves[0], moves[1], moves[3])
        subset = (None if config.blind_zone_laser is None
                  else (lasers == int(LaserName[config.blind_zone_laser])) & (returns == 1))
        image_world_from_vehicle = frames.world_from_vehicle[t]
        image_vehicle_from_vehicle = None
        if np.all(np.isfinite(image_world_from_vehicle)):
            image_vehicle_from_vehicle = invert_rigid(image_world_from_vehicle) @ scene.world_from_vehicle[t]
        if rolling:
            # each return where the camera saw it: at its pixel's capture time in its row (the
            # ego's motion during the readout, and a labelled object's own), as the tracks are
            # projected (drivetrack.tracks.core, ``TrackConfig.rolling_shutter``); only returns
            # near the image at its pose are solved (the readout moves them by tens of pixels)
            near = _near_image(points, model, image_vehicle_from_vehicle)
            world_from_vehicle = scene.world_from_vehicle[t]
            seen = project_world(frames, t, points[near] @ world_from_vehicle[:3, :3].T + world_from_vehicle[:3, 3],
                                 None if velocity_world is None else velocity_world[near])
            maps = sparse_depth_from_pixels(seen.pixels, seen.points_camera[:, 0], seen.valid, model,
                                            None if subset is None else subset[near])
        else:
            maps = sparse_depth_from_points(points, model, subset=subset, vehicle_from_points=image_vehicle_from_vehicle,
                                            replace=replace)
        if config.blind_zone_laser is None:
            out[i] = maps
        else:
            out[i], reference = maps
        if config.see_through_window_deg is not None:
            out[i][see_through_returns(out[i], window_px, config.occlusion_ratio,
                                       config.see_through_min_quadrants)] = 0.0
        if config.blind_zone_laser is not None:
            out[i] = bound_blind_zone(out[i], reference, window_px, config.occlusion_ratio, scale)
    return out


def complete_depth(sparse: np.ndarray, config: TrackConfig) -> np.ndarray:
    """float32 [B, H, W] dense maps from sparse float32 [B, H, W] with ``config.depth_completer``.

    The completer sees the returns only (``max(sparse, 0)``); the blind-zone bounds that
    :func:`sparse_depth` encodes as negative values are applied to its result
    (:func:`drivetrack.depth.apply_depth_bounds`).
    """
    from drivetrack.depth import apply_depth_bounds, get_completer

    sparse = np.asarray(sparse, dtype=np.float32)
    if sparse.ndim != 3:
        raise ValueError(f"complete_depth expects sparse maps [B, H, W], got shape {sparse.shape}")
    completer = get_completer(config.depth_completer, **config.depth_completer_options)
    dense = np.require(completer(np.maximum(sparse, 0.0)), dtype=np.float32, requirements=("C", "W"))
    return apply_depth_bounds(dense, sparse, in_place=True)


@dataclass
class DepthBatch:
    """Depth maps of one camera over a batch of frames of one segment.

    Attributes:
        segment: segment name (for error messages and routing).
        camera: ``CameraName`` value.
        frames: int64 [B], frame indices.
        maps: float32 [B, H, W], z-depth in metres from the camera, 0 = unknown; sparse maps
            also hold blind-zone bounds as negative values (``drivetrack.depth.bound_blind_zone``).
        dense: False for sparse LiDAR maps, True once completed.
        method: the completer that produced dense maps ("" for sparse).
    """
    segment: str
    camera: int
    frames: np.ndarray
    maps: np.ndarray
    dense: bool = False
    method: str = ""


def sparse_depth_batches(scene: Scene, config: "AnnotateConfig", plan: SegmentPlan | None = None,
                         map_fn: Callable[[Callable, list], Iterable] | None = None) -> list[DepthBatch]:
    """Sparse LiDAR depth maps of every frame an accepted clip needs, in batches per camera.

    ``map_fn(function, jobs)`` runs the batches (default: the built-in ``map``; a thread pool's
    ``map`` runs cameras at once: the projection kernel releases the GIL), results in job order.
    """
    from drivetrack.tracks.plan import plan_segment

    plan = plan if plan is not None else plan_segment(scene, config.track)
    return list((map_fn or map)(lambda job: sparse_depth_batch(scene, config, job, plan),
                                depth_jobs(scene, config.track, plan)))


def sparse_depth_batch(scene: Scene, config: "AnnotateConfig", job: DepthJob,
                       plan: SegmentPlan | None = None) -> DepthBatch:
    """The sparse :class:`DepthBatch` of one :class:`DepthJob` (:func:`sparse_depth`; ``plan``: the
    segment's, when the caller has it, for moving labelled returns to image time)."""
    return DepthBatch(scene.segment, job.camera, job.frames, sparse_depth(scene, config.track, job, plan))


def complete_depth_batch(batch: DepthBatch, config: "AnnotateConfig", device: str | None = None) -> DepthBatch:
    """Complete a sparse batch with the configured completer: the unit of the depth (GPU) queue.

    ``device`` (e.g. ``"cuda:0"``) is passed to completers that take one (``nearest-torch``).
    """
    if batch.dense:
        raise ValueError(f"segment {batch.segment!r} camera {CameraName(batch.camera).name}: "
                         f"batch is already completed (by {batch.method!r})")
    track = config.track
    if device is not None:
        options = {**track.depth_completer_options, "device": device}
        track = type(track).from_dict({**track.to_dict(), "depth_completer_options": options})
    maps = complete_depth(batch.maps, track)
    return DepthBatch(batch.segment, batch.camera, batch.frames, maps, dense=True, method=track.depth_completer)


def _depth_by_camera(batches: Iterable[DepthBatch]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Camera value -> (int64 [F] sorted frames, float32 [F, H, W] maps) of completed batches.

    Each camera's batches are copied into one array, then let go, so that (when the caller keeps
    no reference, e.g. passes a generator) at most one camera's maps exist twice at a time."""
    grouped: dict[int, list[DepthBatch]] = {}
    for batch in batches:
        if not batch.dense:
            raise ValueError(f"segment {batch.segment!r} camera {CameraName(batch.camera).name}: "
                             f"depth batch of frames {batch.frames[:5].tolist()}... is not completed")
        grouped.setdefault(batch.camera, []).append(batch)
    out = {}
    for camera in list(grouped):
        parts = grouped.pop(camera)
        frames = np.concatenate([p.frames for p in parts])
        order = np.argsort(frames, kind="stable")
        if len(parts) == 1 and np.array_equal(order, np.arange(frames.size)):
            out[camera] = (frames, parts[0].maps)
            continue
        maps = np.empty((frames.size,) + parts[0].maps.shape[1:], dtype=parts[0].maps.dtype)
        start = 0
        for part in parts:
            maps[start:start + part.frames.size] = part.maps
            start += part.frames.size
        del parts, part
        out[camera] = (frames[order], maps if np.array_equal(order, np.arange(frames.size)) else maps[order])
    return out
