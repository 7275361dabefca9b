"""The depth stage: per (camera, frame) occlusion depth maps, computed once per segment.

Split so an orchestrator can stage it: :func:`depth_jobs` lists the (camera, frame batch) units,
:func:`sparse_depth` projects a batch's LiDAR (CPU), :func:`complete_depth` densifies it with the
configured completer (the GPU-queue unit), and :func:`prepare_segment` assembles the results into
the :class:`SegmentContext` shared read-only by every object job of the segment (or runs the whole
stage in-process when no depth is given).

Only frames that an accepted clip of that camera needs get a depth map.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivetrack.geometry import invert_rigid, transform_points
from drivetrack.scene import Scene
from drivetrack.tracks.config import TrackConfig
from drivetrack.tracks.plan import ObjectJob, SegmentPlan, plan_segment
from drivetrack.waymo.schema import CameraName

__all__ = ["DepthJob", "DepthStack", "SegmentContext", "depth_jobs", "sparse_depth",
           "complete_depth", "prepare_segment", "object_jobs"]


@dataclass(frozen=True)
class DepthJob:
    """A batch of frames of one camera whose depth maps are computed together.

    Attributes:
        camera: ``CameraName`` value.
        frames: int64 [B], frame indices (sorted).
    """
    camera: int
    frames: np.ndarray


@dataclass
class DepthStack:
    """Completed depth maps of one camera.

    Attributes:
        frames: int64 [F], frame indices with a map (sorted).
        maps: float32 [F, H, W], z-depth from the camera in metres, 0 = unknown.
        slot: int64 [T], position of frame t in ``maps`` (-1 = no map).
    """
    frames: np.ndarray
    maps: np.ndarray
    slot: np.ndarray

    def of_frame(self, t: int) -> np.ndarray:
        s = int(self.slot[t])
        if s < 0:
            raise KeyError(f"no depth map for frame {t}")
        return self.maps[s]


@dataclass
class SegmentContext:
    """Everything the object jobs of one segment share (read-only, never copied per job).

    Attributes:
        plan: the segment plan (scene, config, camera poses, box points, jobs, rejections).
        depth: camera value -> :class:`DepthStack`.
    """
    plan: SegmentPlan
    depth: dict[int, DepthStack]

    @property
    def scene(self) -> Scene:
        return self.plan.scene

    @property
    def config(self) -> TrackConfig:
        return self.plan.config


def _needed_frames(plan: SegmentPlan) -> dict[int, np.ndarray]:
    needed: dict[int, set] = {}
    for job in plan.jobs:
        needed.setdefault(job.camera, set()).update(job.frames.tolist())
    return {c: np.array(sorted(f), dtype=np.int64) for c, f in sorted(needed.items())}


def depth_jobs(scene: Scene, config: TrackConfig, plan: SegmentPlan | None = None) -> list[DepthJob]:
    """The depth units of a segment: per camera, its needed frames in batches of ``depth_batch``."""
    plan = plan if plan is not None else plan_segment(scene, config)
    jobs = []
    for camera, frames in _needed_frames(plan).items():
        for start in range(0, frames.size, config.depth_batch):
            jobs.append(DepthJob(camera, frames[start:start + config.depth_batch]))
    return jobs


def sparse_depth(scene: Scene, config: TrackConfig, job: DepthJob) -> np.ndarray:
    """float32 [B, H, W] sparse z-depth maps of ``job`` from the LiDAR: > 0 a return, 0 none, < 0 a bound.

    Uses the returns of ``config.depth_lasers`` and ``config.depth_returns`` (default: first
    returns of every lidar). Returns are moved from the frame's vehicle frame
    to the vehicle frame at the image's pose before projection, so that the maps agree with the
    track projection (the ego vehicle moves between the LiDAR and the camera timestamps). With
    ``config.see_through_window_deg``, returns the camera cannot see (the LiDAR saw them past a
    nearer surface) are then removed (:func:`drivetrack.depth.see_through_returns`). With
    ``config.blind_zone_laser``, the region below that lidar's lowest scan line (its first
    returns: second returns lie behind an edge) is bounded by the line's depth
    (:func:`drivetrack.depth.bound_blind_zone`): pixels there without a return hold ``-bound``
    (:func:`complete_depth` applies it after completion).
    """
    from drivetrack.depth import (bound_blind_zone, horizontal_depth_scale, see_through_returns,
                                  sparse_depth_from_points)
    from drivetrack.waymo.schema import LaserName

    frames = scene.cameras[job.camera]
    model = frames.model
    lidar = scene.lidar
    out = np.zeros((job.frames.size, model.height, model.width), dtype=np.float32)
    window_px = max(1, int(round(model.f_u * np.tan(np.radians(config.see_through_window_deg or 0.5)))))
    scale = horizontal_depth_scale(model) if config.blind_zone_laser is not None else None
    for i, t in enumerate(job.frames.tolist()):
        part = lidar.of_frame(t)
        points = lidar.points_vehicle[part]
        lasers, returns = lidar.laser[part], lidar.return_index[part]
        keep = np.isin(lasers, config.depth_laser_values) & np.isin(returns, config.depth_returns)
        if not keep.all():
            points, lasers, returns = points[keep], lasers[keep], returns[keep]
        image_world_from_vehicle = frames.world_from_vehicle[t]
        if np.all(np.isfinite(image_world_from_vehicle)):
            image_vehicle_from_vehicle = invert_rigid(image_world_from_vehicle) @ scene.world_from_vehicle[t]
            points = transform_points(image_vehicle_from_vehicle, points)
        if config.blind_zone_laser is None:
            out[i] = sparse_depth_from_points(points, model)
        else:
            out[i], reference = sparse_depth_from_points(
                points, model, subset=(lasers == int(LaserName[config.blind_zone_laser])) & (returns == 1))
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
    dense = np.asarray(completer(np.maximum(sparse, 0.0)), dtype=np.float32)
    return apply_depth_bounds(dense, sparse)


def _stack(scene: Scene, camera: int, frames: np.ndarray, maps: np.ndarray) -> DepthStack:
    model = scene.cameras[camera].model
    if maps.shape != (frames.size, model.height, model.width):
        raise ValueError(f"segment {scene.segment!r} camera {CameraName(camera).name}: depth maps have "
                         f"shape {maps.shape}, expected {(frames.size, model.height, model.width)}")
    slot = np.full(scene.num_frames, -1, dtype=np.int64)
    slot[frames] = np.arange(frames.size)
    return DepthStack(frames, maps, slot)


def prepare_segment(scene: Scene, config: TrackConfig, depth: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
                    plan: SegmentPlan | None = None) -> SegmentContext:
    """Plan the segment and attach its depth maps (one stack per camera, shared by all jobs).

    Args:
        depth: optional precomputed maps from a staged depth run: camera value ->
            ``(frames int [F], maps float32 [F, H, W])``; they must cover every frame that
            :func:`depth_jobs` lists. When None the depth stage runs here, batch by batch.
        plan: optional result of :func:`plan_segment` (recomputed when None).
    """
    plan = plan if plan is not None else plan_segment(scene, config)
    needed = _needed_frames(plan)
    stacks: dict[int, DepthStack] = {}
    if depth is None:
        for camera, frames in needed.items():
            model = scene.cameras[camera].model
            maps = np.zeros((frames.size, model.height, model.width), dtype=np.float32)
            for start in range(0, frames.size, config.depth_batch):
                job = DepthJob(camera, frames[start:start + config.depth_batch])
                maps[start:start + job.frames.size] = complete_depth(sparse_depth(scene, config, job), config)
            stacks[camera] = _stack(scene, camera, frames, maps)
    else:
        for camera, frames in needed.items():
            if camera not in depth:
                raise ValueError(f"segment {scene.segment!r}: no depth maps given for camera "
                                 f"{CameraName(camera).name}")
            given_frames, maps = depth[camera]
            given_frames = np.asarray(given_frames, dtype=np.int64)
            missing = np.setdiff1d(frames, given_frames)
            if missing.size:
                raise ValueError(f"segment {scene.segment!r} camera {CameraName(camera).name}: depth maps "
                                 f"missing for frames {missing[:10].tolist()}")
            stacks[camera] = _stack(scene, camera, given_frames, np.asarray(maps, dtype=np.float32))
    return SegmentContext(plan, stacks)


def object_jobs(ctx: SegmentContext) -> list[ObjectJob]:
    """The clips to annotate (after the planning filters; rejections are in ``ctx.plan``)."""
    return list(ctx.plan.jobs)
