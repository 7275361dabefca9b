"""Box, screen-rectangle and ray helpers shared by the camera renderer, the lidar and the truth."""
from __future__ import annotations

import numpy as np

from drivetrack.camera.model import CameraModel
from drivetrack.geometry import box_from_center_heading, transform_points

_EDGES = np.array([(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7),
                   (0, 4), (1, 5), (2, 6), (3, 7)])
_CORNER_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)


def _box_corners(size) -> np.ndarray:
    """float64 [8, 3] corners of a box of ``size`` in its own frame (index bits: x, y, z)."""
    return _CORNER_SIGNS * (np.asarray(size, np.float64) / 2.0)


def _box_edge_samples(size, n: int = 9) -> np.ndarray:
    """float64 [12 * n, 3] points on the 12 edges of a box of ``size`` (box frame)."""
    c = _box_corners(size)
    s = np.linspace(0.0, 1.0, n)[:, None]
    return np.concatenate([c[a] + s * (c[b] - c[a]) for a, b in _EDGES])


_RAY_CACHE: dict[tuple, np.ndarray] = {}


def _pixel_rays(model: CameraModel) -> np.ndarray:
    """float64 [H * W, 3] unit camera-frame rays of every pixel centre (row-major), from
    :meth:`CameraModel.rays_from_pixels` with 10 iterations (they reproject onto their pixel
    centre within 1e-8 px for these calibrations); computed in chunks, cached per intrinsics."""
    key = (model.f_u, model.f_v, model.c_u, model.c_v, model.k1, model.k2, model.p1, model.p2,
           model.k3, model.width, model.height)
    rays = _RAY_CACHE.get(key)
    if rays is None:
        H, W = model.height, model.width
        rays = np.empty((H * W, 3))
        step = max(1, 65536 // W)
        xs = np.arange(W) + 0.5
        for y0 in range(0, H, step):
            ys = np.arange(y0, min(H, y0 + step)) + 0.5
            px = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None]), -1).reshape(-1, 2)
            rays[y0 * W:y0 * W + px.shape[0]] = model.rays_from_pixels(px, iterations=10)
        if len(_RAY_CACHE) > 8:
            _RAY_CACHE.clear()
        _RAY_CACHE[key] = rays
    return rays


def _undistorted_extent(model: CameraModel, rays: np.ndarray) -> tuple[float, float, float, float]:
    """(u_min, u_max, v_min, v_max) of the image border in undistorted coordinates
    (u = -y/x, v = -z/x), grown by 2 %."""
    r = rays.reshape(model.height, model.width, 3)
    border = np.concatenate([r[0], r[-1], r[:, 0], r[:, -1]])
    u, v = -border[:, 1] / border[:, 0], -border[:, 2] / border[:, 0]
    du, dv = 0.02 * (u.max() - u.min()), 0.02 * (v.max() - v.min())
    return u.min() - du, u.max() + du, v.min() - dv, v.max() + dv


def _screen_rect(model: CameraModel, extent, camera_from_box: np.ndarray, size, pad: int = 3):
    """(x0, x1, y0, y1) pixel columns/rows (inclusive-exclusive) containing the projection of a box,
    or None when no part of it can appear in the image.

    Exact construction: the box is clipped to the plane x = 0.01 m in front of the camera; the
    bounding rectangle of the clipped vertices in undistorted coordinates contains the silhouette;
    that rectangle (cut to the image's extent) is mapped through the distortion by sampling its
    border densely, and padded by ``pad`` pixels.
    """
    eps = 0.01
    corners = transform_points(camera_from_box, _box_corners(size))
    a, b = corners[_EDGES[:, 0]], corners[_EDGES[:, 1]]
    xa, xb = a[:, 0], b[:, 0]
    pts = [corners[corners[:, 0] >= eps]]
    cross = (xa - eps) * (xb - eps) < 0
    if cross.any():
        s = (eps - xa[cross]) / (xb[cross] - xa[cross])
        pts.append(a[cross] + s[:, None] * (b[cross] - a[cross]))
    pts = np.concatenate(pts)
    if pts.shape[0] == 0:
        return None
    u, v = -pts[:, 1] / pts[:, 0], -pts[:, 2] / pts[:, 0]
    u0, u1 = max(u.min(), extent[0]), min(u.max(), extent[1])
    v0, v1 = max(v.min(), extent[2]), min(v.max(), extent[3])
    if u0 >= u1 or v0 >= v1:
        return None
    s = np.linspace(0.0, 1.0, 65)
    bu = np.concatenate([u0 + s * (u1 - u0), u0 + s * (u1 - u0), np.full(65, u0), np.full(65, u1)])
    bv = np.concatenate([np.full(65, v0), np.full(65, v1), v0 + s * (v1 - v0), v0 + s * (v1 - v0)])
    px, valid = model.pixels_from_camera(np.stack([np.ones_like(bu), -bu, -bv], -1))
    if not valid.all():
        return (0, model.width, 0, model.height)
    x0 = max(int(np.floor(px[:, 0].min())) - pad, 0)
    x1 = min(int(np.ceil(px[:, 0].max())) + pad, model.width)
    y0 = max(int(np.floor(px[:, 1].min())) - pad, 0)
    y1 = min(int(np.ceil(px[:, 1].max())) + pad, model.height)
    if x0 >= x1 or y0 >= y1:
        return None
    return (x0, x1, y0, y1)


def _apply(dst_from_src: np.ndarray, points: np.ndarray) -> np.ndarray:
    """float64 [n, 3]: one rigid transform [4, 4] applied to points [n, 3] (BLAS, no einsum)."""
    return (dst_from_src[:3, :3] @ points.T).T + dst_from_src[:3, 3]


def _yaw_transform(points_box: np.ndarray, center: np.ndarray, heading) -> np.ndarray:
    """World points float64 [n, 3] of box-frame points, box at ``center`` [n, 3] / ``heading`` [n]."""
    c, s = np.cos(heading), np.sin(heading)
    x = c * points_box[..., 0] - s * points_box[..., 1] + center[..., 0]
    y = s * points_box[..., 0] + c * points_box[..., 1] + center[..., 1]
    return np.stack([x, y, points_box[..., 2] + center[..., 2]], axis=-1)


def _rotate_rpy(vectors: np.ndarray, rpy: np.ndarray, inverse: bool = False) -> np.ndarray:
    """float64 [n, 3]: ``Rz(yaw) Ry(pitch) Rx(roll)`` (``geometry.rotation_from_rpy``) applied to
    vectors [n, 3] with angles ``rpy[:, :3]`` (radians), or its transpose when ``inverse``."""
    cr, sr = np.cos(rpy[:, 0]), np.sin(rpy[:, 0])
    cp, sp = np.cos(rpy[:, 1]), np.sin(rpy[:, 1])
    cy, sy = np.cos(rpy[:, 2]), np.sin(rpy[:, 2])
    x, y, z = vectors[:, 0], vectors[:, 1], vectors[:, 2]
    if not inverse:
        y, z = cr * y - sr * z, sr * y + cr * z
        x, z = cp * x + sp * z, -sp * x + cp * z
        x, y = cy * x - sy * y, sy * x + cy * y
    else:
        x, y = cy * x + sy * y, -sy * x + cy * y
        x, z = cp * x - sp * z, sp * x + cp * z
        y, z = cr * y + sr * z, -sr * y + cr * z
    return np.stack([x, y, z], axis=-1)


def _rect_indices(rect, width: int) -> np.ndarray:
    x0, x1, y0, y1 = rect
    return (np.arange(y0, y1)[:, None] * width + np.arange(x0, x1)[None, :]).ravel()


def _box_matrix(center, heading):
    """float64 [..., 4, 4] ``world_from_box`` of a yaw-only box (``geometry.box_from_center_heading``)."""
    return box_from_center_heading(center, heading)
