"""What the object jobs of one segment share: its plan and its completed depth maps.

:func:`prepare_segment` assembles the depth stage's results (:mod:`drivetrack.depth.stage`) into
the :class:`SegmentContext` shared read-only by every object job of the segment, or runs the
whole depth stage in-process when no depth is given.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivetrack.depth.stage import DepthJob, complete_depth, needed_frames, sparse_depth
from drivetrack.scene import Scene
from drivetrack.tracks.config import TrackConfig
from drivetrack.tracks.plan import ObjectJob, SegmentPlan, plan_segment
from drivetrack.waymo.schema import CameraName

__all__ = ["DepthStack", "SegmentContext", "prepare_segment", "object_jobs"]


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
    needed = needed_frames(plan)
    stacks: dict[int, DepthStack] = {}
    if depth is None:
        for camera, frames in needed.items():
            model = scene.cameras[camera].model
            maps = np.zeros((frames.size, model.height, model.width), dtype=np.float32)
            for start in range(0, frames.size, config.depth_batch):
                job = DepthJob(camera, frames[start:start + config.depth_batch])
                maps[start:start + job.frames.size] = complete_depth(sparse_depth(scene, config, job, plan), config)
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
