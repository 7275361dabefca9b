"""An emulation of the ORIGINAL released DriveTrack script's choices, on our Scene (bench only).

Written from the list of its choices in /work/shared/METHOD.md section 3 (no code of it is
copied; it is not used by the pipeline). Its purpose: score the original method on the same
synthetic scenes and with the same evaluation (``drivetrack.evaluation``) as ours. Choices
emulated:

- object points: TOP LiDAR, first return only, inside the labelled box (no margin, no ground
  clearance);
- depth maps: the same TOP first returns projected into the camera **without lens distortion**
  (pinhole with the calibration's f and c), each pixel keeping the nearest value of the
  **Euclidean distance from the vehicle origin** (not the camera's z-depth), completed by
  ``scipy.interpolate.NearestNDInterpolator`` over the **full pixel grid** (so depth is
  extrapolated into the sky and every other area without LiDAR);
- tracks: ``X_tau = W_tau^-1 B_tau B_t^-1 W_t X_t`` with the frame poses (no image-pose timing
  correction, **no rolling shutter**), projected without distortion; occluded when the
  depth map (maximum of the four neighbouring pixels) is below **0.95 x the point's distance from
  the vehicle origin**; a point is kept when visible in at least one frame;
- filters: in view for at least 24 continuous frames (our planner's test, which the original
  shares) and within **50 m of the vehicle origin** (not the camera) at some frame.

The result per clip is a :class:`drivetrack.evaluation.Clip` (lidar_sources = (TOP, 1, row, col)).
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from drivetrack.depth import lookup_max4
from drivetrack.evaluation import Clip
from drivetrack.geometry import box_from_center_heading, invert_rigid, transform_points
from drivetrack.scene import Scene
from drivetrack.tracks import TrackConfig, plan_segment
from drivetrack.waymo.schema import CameraName, LaserName

__all__ = ["ORIGINAL_MAX_DISTANCE_M", "ORIGINAL_OCCLUSION_FACTOR", "original_config", "pinhole_pixels",
           "original_depth_map", "original_clips"]

ORIGINAL_MAX_DISTANCE_M = 50.0
ORIGINAL_OCCLUSION_FACTOR = 0.95


def original_config(base: TrackConfig | None = None) -> TrackConfig:
    """Our planner configured like the original: TOP first return, no ground clearance, no
    camera-distance filter here (the 50 m vehicle-origin filter is applied by :func:`original_clips`)."""
    base = base or TrackConfig()
    return replace(base, lasers=("TOP",), returns=(1,), ground_clearance_m=0.0, box_margin_m=0.0,
                   max_camera_distance_m=float("inf"), rolling_shutter=False,
                   occlusion_ratio=ORIGINAL_OCCLUSION_FACTOR)


def pinhole_pixels(model, points_vehicle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels float64 [..., 2] of vehicle-frame points [..., 3] WITHOUT distortion, and bool
    [...] in front of the camera (the original's projection)."""
    points_camera = transform_points(model.camera_from_vehicle, points_vehicle)
    x = points_camera[..., 0]
    front = x > 1e-6
    safe = np.where(front, x, 1.0)
    pixels = np.stack([model.f_u * (-points_camera[..., 1] / safe) + model.c_u,
                       model.f_v * (-points_camera[..., 2] / safe) + model.c_v], axis=-1)
    return pixels, front


def _top_first(scene: Scene, t: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows of frame t's TOP first returns, and their vehicle-frame points."""
    lidar = scene.lidar
    part = lidar.of_frame(t)
    rows = np.arange(part.start, part.stop)
    rows = rows[(lidar.laser[part] == int(LaserName.TOP)) & (lidar.return_index[part] == 1)]
    return rows, lidar.points_vehicle[rows]


def original_depth_map(model, points_vehicle: np.ndarray) -> np.ndarray:
    """float32 [H, W]: vehicle-origin distance of the nearest projected point per pixel, then
    NearestNDInterpolator over the full grid (every pixel filled)."""
    from scipy.interpolate import NearestNDInterpolator

    pixels, front = pinhole_pixels(model, points_vehicle)
    inside = front & (pixels[:, 0] >= 0) & (pixels[:, 0] < model.width) & (pixels[:, 1] >= 0) \
        & (pixels[:, 1] < model.height)
    distance = np.linalg.norm(points_vehicle, axis=-1)[inside]
    cols = np.floor(pixels[inside, 0]).astype(np.int64)
    rows = np.floor(pixels[inside, 1]).astype(np.int64)
    sparse = np.full(model.height * model.width, np.inf)
    np.minimum.at(sparse, rows * model.width + cols, distance)
    known = np.flatnonzero(np.isfinite(sparse))
    if known.size == 0:
        return np.zeros((model.height, model.width), np.float32)
    interpolate = NearestNDInterpolator(np.stack([known // model.width, known % model.width], axis=-1),
                                        sparse[known])
    grid_rows, grid_cols = np.mgrid[0:model.height, 0:model.width]
    return interpolate(grid_rows, grid_cols).astype(np.float32)


def original_clips(scene: Scene, base: TrackConfig | None = None, timings: dict | None = None,
                   depth_maps: dict | None = None) -> list[Clip]:
    """Clips of every (camera, object) the original would annotate in ``scene``.

    ``timings`` (optional dict) receives ``depth_cpu_s``, ``tracks_cpu_s`` and ``num_depth_maps``
    (maps computed in this call). ``depth_maps`` (optional dict ``(camera, frame) -> map``) is
    reused and filled across calls on scenes that differ only in their box labels.
    """
    config = original_config(base)
    plan = plan_segment(scene, config)
    lidar, boxes = scene.lidar, scene.boxes
    jobs = []
    for job in plan.jobs:       # the 50 m filter, from the vehicle origin
        if np.min(np.linalg.norm(boxes.center[job.box_rows], axis=-1)) <= ORIGINAL_MAX_DISTANCE_M:
            jobs.append(job)
    depth_cpu = tracks_cpu = 0.0
    maps: dict[tuple[int, int], np.ndarray] = depth_maps if depth_maps is not None else {}
    computed = 0
    start = time.process_time()
    for job in jobs:
        model = scene.cameras[job.camera].model
        for t in job.frames.tolist():
            if (job.camera, t) not in maps:
                maps[(job.camera, t)] = original_depth_map(model, _top_first(scene, t)[1])
                computed += 1
    depth_cpu += time.process_time() - start

    start = time.process_time()
    clips = []
    for job in jobs:
        model = scene.cameras[job.camera].model
        frames, rows = job.frames, job.box_rows
        world_from_box = scene.world_from_vehicle[frames] @ box_from_center_heading(boxes.center[rows],
                                                                                   boxes.heading[rows])
        vehicle_from_world = invert_rigid(scene.world_from_vehicle[frames])
        lidar_rows, source = plan.box_points(rows)
        # X_tau = W_tau^-1 B_tau B_t^-1 W_t X_t
        box_from_vehicle = invert_rigid(world_from_box) @ scene.world_from_vehicle[frames]
        points_box = transform_points(box_from_vehicle[source], lidar.points_vehicle[lidar_rows][:, None, :])[:, 0]
        vehicle_from_box = vehicle_from_world @ world_from_box                                  # [T,4,4]
        points_tau = np.einsum("tij,nj->nti", vehicle_from_box[:, :3, :3], points_box) + vehicle_from_box[None, :, :3, 3]
        pixels, front = pinhole_pixels(model, points_tau)                                       # [N,T,2]
        inside = front & (pixels[..., 0] >= 0) & (pixels[..., 0] < model.width) & (pixels[..., 1] >= 0) \
            & (pixels[..., 1] < model.height)
        stack = np.stack([maps[(job.camera, t)] for t in frames.tolist()])                      # [T,H,W]
        surface = lookup_max4(stack, np.swapaxes(pixels, 0, 1))                                 # [T,N]
        distance = np.linalg.norm(points_tau, axis=-1)
        occluded = surface.T < ORIGINAL_OCCLUSION_FACTOR * distance
        visibles = inside & ~occluded
        keep = visibles.any(axis=1)
        sources = np.stack([lidar.laser[lidar_rows], lidar.return_index[lidar_rows], lidar.row[lidar_rows],
                            lidar.col[lidar_rows]], axis=-1)
        if keep.any():
            clips.append(Clip(segment=scene.segment, camera=CameraName(job.camera).name, object_id=job.object_id,
                              split=scene.split, timestamps_micros=scene.timestamps_micros[frames].astype(np.int64),
                              tracks=pixels[keep].astype(np.float32), visibles=visibles[keep],
                              query_frames=source[keep].astype(np.int64), lidar_sources=sources[keep].astype(np.int64),
                              file="original-emulation"))
    tracks_cpu += time.process_time() - start
    if timings is not None:
        timings.update(depth_cpu_s=depth_cpu, tracks_cpu_s=tracks_cpu, num_depth_maps=computed)
    return clips
