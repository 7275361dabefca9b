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


def see_through_returns(sparse: np.ndarray, window_px: int, ratio: float = 0.95, min_quadrants: int = 3,
                        cell_px: int | None = None) -> np.ndarray:
    """bool [..., H, W]: returns of a sparse map that the camera cannot see (seen *through* a nearer surface).

    The LiDAR looks from elsewhere than the camera (higher, or from a bumper), so it sees surfaces
    the camera cannot: over the roof of a car beside the camera, under a trailer, round a pole.
    Projected into the image, such a return lands among the returns of the nearer surface that
    hides it, and a completed map that keeps it marks points behind that surface as visible. A
    return of depth ``d`` is flagged when, in at least ``min_quadrants`` of the four quadrant
    windows around it (up-left, up-right, down-left, down-right, each ``window_px`` on a side), a
    return is nearer than ``ratio * d``. At a true depth edge the nearer surface lies on one side
    only (two quadrants), and on a slanted surface (the ground) only the quadrants towards the
    near side hold nearer returns, so both keep their returns.

    Args:
        sparse: float32 [..., H, W] sparse z-depth maps, 0 = no return.
        window_px: side of each quadrant window, pixels (about twice the vertical spacing of the
            LiDAR's scan lines in the image keeps far, sparse surfaces covered).
        ratio: a return is nearer when its depth is below ``ratio`` times the tested one.
        min_quadrants: 1 to 4 quadrants that must hold a nearer return.
        cell_px: the minima are taken on a grid of ``cell_px`` x ``cell_px`` cells (min-pooled),
            so the quadrant borders are exact to one cell; default ``max(1, window_px // 8)``.
    Returns:
        bool [..., H, W], True at the flagged returns (never where ``sparse`` is 0).
    """
    import cv2

    sparse = np.asarray(sparse, dtype=np.float32)
    if sparse.ndim < 2:
        raise ValueError(f"sparse: expected float32 [..., H, W], found shape {sparse.shape}")
    if int(window_px) < 1 or not 0 < ratio <= 1 or not 1 <= int(min_quadrants) <= 4:
        raise ValueError(f"see_through_returns: window_px must be >= 1 (got {window_px}), ratio in (0, 1] "
                         f"(got {ratio}), min_quadrants in 1..4 (got {min_quadrants})")
    if sparse.ndim > 2:
        return np.stack([see_through_returns(m, window_px, ratio, min_quadrants, cell_px)
                         for m in sparse.reshape(-1, *sparse.shape[-2:])]).reshape(sparse.shape)
    height, width = sparse.shape
    cell = max(1, int(cell_px) if cell_px else int(window_px) // 8)
    span = max(1, -(-int(window_px) // cell))                     # quadrant side in cells
    rows, cols = -(-height // cell), -(-width // cell)
    flat = np.flatnonzero(sparse.reshape(-1) > 0)
    ys, xs = np.divmod(flat, width)
    depth = sparse.reshape(-1)[flat]
    cy, cx = ys // cell, xs // cell
    cells = np.full(rows * cols, np.inf, dtype=np.float32)
    np.minimum.at(cells, cy * cols + cx, depth)                    # min-pooled cells
    cells = cells.reshape(rows, cols)
    nearer = np.zeros(depth.shape, dtype=np.int8)
    border = dict(borderType=cv2.BORDER_CONSTANT, borderValue=float("inf"))
    # quadrant minima: a row pass towards the left / right, then a column pass up / down
    for ax in (span - 1, 0):                                       # anchor: window left / right of x
        across = cv2.erode(cells, np.ones((1, span), np.uint8), anchor=(ax, 0), **border)
        for ay in (span - 1, 0):                                   # window above / below y
            quadrant = cv2.erode(across, np.ones((span, 1), np.uint8), anchor=(0, ay), **border)
            nearer += quadrant[cy, cx] < ratio * depth
    out = np.zeros(sparse.size, dtype=bool)
    out[flat] = nearer >= int(min_quadrants)
    return out.reshape(sparse.shape)
