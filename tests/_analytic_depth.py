"""An analytic scene (ground plane + boxes) with exact dense depth and a simulated spinning LiDAR.

Used by the depth benchmarks and tests to score completers against exact depth. Everything is
in the vehicle frame (x forward, y left, z up, metres). Rays are intersected analytically, so
the "ground truth" depth of every pixel centre is exact up to float64 rounding.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from drivetrack.camera.model import CameraModel
from drivetrack.geometry import rigid_from_rotation_translation, rotation_from_rpy

__all__ = ["AnalyticScene", "default_scene", "front_camera", "ray_hit_distance", "exact_depth",
           "lidar_points"]


@dataclass(frozen=True)
class AnalyticScene:
    """Ground plane ``z = ground_z`` plus axis-aligned boxes ``boxes`` float [K, 2, 3] (min, max
    corner, vehicle frame, metres)."""
    ground_z: float = 0.0
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))


def default_scene() -> AnalyticScene:
    """A street: cars at 7-45 m, a truck, a pedestrian-sized box, a building front at 60 m."""
    boxes = np.array([
        [[8.0, -3.2, 0.0], [12.5, -1.3, 1.6]],    # car ahead right
        [[15.0, 1.0, 0.0], [19.5, 2.9, 1.5]],     # car ahead left
        [[25.0, -1.3, 0.0], [33.0, 1.3, 3.2]],    # truck ahead
        [[40.0, 3.0, 0.0], [44.5, 4.9, 1.5]],     # far car
        [[6.0, 2.0, 0.0], [6.6, 2.6, 1.8]],       # pedestrian
        [[60.0, -40.0, 0.0], [62.0, -6.0, 12.0]],  # building front right
        [[55.0, 8.0, 0.0], [57.0, 40.0, 9.0]],     # building front left
    ], dtype=np.float64)
    return AnalyticScene(ground_z=0.0, boxes=boxes)


def front_camera(width: int = 1920, height: int = 1280) -> CameraModel:
    """A Waymo-like FRONT camera (f about 2055 px at 1920 wide, mild barrel distortion), 1.5 m
    ahead of the vehicle origin at 2.1 m height, pitched 2 degrees down; intrinsics scale with
    ``width``."""
    scale = width / 1920.0
    vehicle_from_camera = rigid_from_rotation_translation(
        rotation_from_rpy(0.0, np.radians(2.0), 0.0), np.array([1.5, 0.0, 2.1]))
    return CameraModel(f_u=2055.0 * scale, f_v=2055.0 * scale, c_u=width / 2.0, c_v=height / 2.0,
                       k1=0.04, k2=-0.02, p1=0.0005, p2=-0.0003, k3=0.0, width=width,
                       height=height, vehicle_from_camera=vehicle_from_camera)


def ray_hit_distance(origin: np.ndarray, directions: np.ndarray, scene: AnalyticScene) -> np.ndarray:
    """Distance along unit rays to the first surface.

    Args:
        origin: float [3], vehicle frame, metres (outside every box).
        directions: float [N, 3] unit vectors, vehicle frame.
    Returns:
        float64 [N], metres; ``inf`` where the ray hits nothing.
    """
    origin = np.asarray(origin, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    hit = np.full(directions.shape[0], np.inf)
    dz = directions[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = (scene.ground_z - origin[2]) / dz
        hit = np.where((dz < 0) & (t_ground > 0), t_ground, hit)
        inverse = 1.0 / directions
        for lower, upper in np.asarray(scene.boxes, dtype=np.float64):  # slab method, K boxes
            t1 = (lower - origin) * inverse
            t2 = (upper - origin) * inverse
            t_near = np.nanmax(np.minimum(t1, t2), axis=1)
            t_far = np.nanmin(np.maximum(t1, t2), axis=1)
            enters = (t_near <= t_far) & (t_near > 0)
            hit = np.where(enters & (t_near < hit), t_near, hit)
    return hit


def exact_depth(scene: AnalyticScene, camera: CameraModel) -> np.ndarray:
    """float32 [H, W] exact z-depth (metres) at every pixel centre, 0 where the ray hits nothing
    (sky) or the pixel's distortion is untrusted."""
    rows, cols = np.mgrid[0:camera.height, 0:camera.width]
    pixels = np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5], axis=-1)
    rays_camera = camera.rays_from_pixels(pixels)
    _, trusted = camera.pixels_from_camera(rays_camera)
    rotation = camera.vehicle_from_camera[:3, :3]
    distance = ray_hit_distance(camera.vehicle_from_camera[:3, 3], rays_camera @ rotation.T, scene)
    depth = np.where(np.isfinite(distance) & trusted, distance * rays_camera[:, 0], 0.0)
    return depth.astype(np.float32).reshape(camera.height, camera.width)


def lidar_points(scene: AnalyticScene, origin=(0.0, 0.0, 2.2), beams: int = 64,
                 azimuths: int = 2650, inclination_deg=(-17.6, 2.4), max_range: float = 75.0,
                 ) -> np.ndarray:
    """Returns of a spinning LiDAR (Waymo TOP-like by default: 64 beams x 2650 columns).

    Returns:
        float64 [M, 3] vehicle-frame points (first return, range <= ``max_range``).
    """
    inclination = np.radians(np.linspace(inclination_deg[1], inclination_deg[0], beams))
    azimuth = np.linspace(-np.pi, np.pi, azimuths, endpoint=False)
    incl, az = np.meshgrid(inclination, azimuth, indexing="ij")
    directions = np.stack([np.cos(incl) * np.cos(az), np.cos(incl) * np.sin(az), np.sin(incl)],
                          axis=-1).reshape(-1, 3)
    origin = np.asarray(origin, dtype=np.float64)
    distance = ray_hit_distance(origin, directions, scene)
    keep = distance <= max_range
    return origin + directions[keep] * distance[keep, None]
