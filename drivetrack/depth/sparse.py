"""Sparse depth maps from LiDAR points: project, keep the nearest return per pixel."""
from __future__ import annotations

import numpy as np

from drivetrack.geometry import CameraModel, transform_points

__all__ = ["sparse_depth_from_points"]


def sparse_depth_from_points(points_vehicle: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Project LiDAR points into a camera and keep the minimum z-depth per pixel.

    Args:
        points_vehicle: float [M, 3], metres, vehicle frame (x forward, y left, z up).
        camera: the camera; its distortion is applied (:meth:`CameraModel.pixels_from_camera`),
            points behind it, with untrusted distortion, or outside the image are dropped.
    Returns:
        float32 [camera.height, camera.width], metres of z-depth (camera-frame x, distance along
        the optical axis from the camera centre), ``0`` where no point projects. A point at pixel
        position (x, y) lands in pixel (floor(x), floor(y)) (pixel ``i`` covers ``[i, i + 1)``).
        Where several points share a pixel the nearest wins (it occludes the others).
    """
    points_vehicle = np.asarray(points_vehicle)
    if points_vehicle.ndim != 2 or points_vehicle.shape[-1] != 3:
        raise ValueError(f"points_vehicle: expected float [M, 3], found shape {points_vehicle.shape}")
    if not np.issubdtype(points_vehicle.dtype, np.floating):
        raise TypeError(f"points_vehicle: expected a float dtype, found {points_vehicle.dtype}")
    height, width = int(camera.height), int(camera.width)
    if height <= 0 or width <= 0:
        raise ValueError(f"camera: expected a positive image size, found {width}x{height}")
    flat = np.full(height * width, np.inf, dtype=np.float64)
    if len(points_vehicle):
        points_camera = transform_points(camera.camera_from_vehicle, points_vehicle)
        pixels, valid = camera.pixels_from_camera(points_camera)
        keep = valid & camera.inside_image(pixels)
        cols = np.floor(pixels[keep, 0]).astype(np.int64)
        rows = np.floor(pixels[keep, 1]).astype(np.int64)
        np.minimum.at(flat, rows * width + cols, points_camera[keep, 0])
    flat[np.isinf(flat)] = 0.0
    return flat.astype(np.float32).reshape(height, width)
