"""Sparse depth maps from LiDAR points: project, keep the nearest return per pixel."""
from __future__ import annotations

import numpy as np

from drivetrack.camera.kernel import camera_parameters
from drivetrack.camera.model import CameraModel
from drivetrack.depth.kernel import NUMBA_AVAILABLE, blind_zone_in_place, bound_in_place, project_nearest
from drivetrack.geometry import transform_points

__all__ = ["sparse_depth_from_points", "sparse_depth_from_pixels", "see_through_returns", "bound_blind_zone", "apply_depth_bounds",
           "horizontal_depth_scale"]


def sparse_depth_from_points(points_vehicle: np.ndarray, camera: CameraModel,
                             subset: np.ndarray | None = None, *, vehicle_from_points: np.ndarray | None = None,
                             kernel: str = "numba",
                             replace: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None
                             ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Project LiDAR points into a camera and keep the minimum z-depth per pixel.

    Args:
        points_vehicle: float [M, 3], metres, vehicle frame (x forward, y left, z up).
        camera: the camera; its distortion is applied (:meth:`CameraModel.pixels_from_camera`),
            points behind it, with untrusted distortion, or outside the image are dropped.
        subset: optional bool [M]: also return the map of these points alone (e.g. one lidar's
            returns, for :func:`bound_blind_zone`), from the same projection.
        vehicle_from_points: optional float64 [4, 4]: the points are in another frame (e.g. the
            vehicle frame of the LiDAR's timestamp); this moves them into the vehicle frame first.
        kernel: ``numba`` (default: one fused pass, :func:`drivetrack.depth.kernel.project_nearest`)
            or ``numpy`` (the reference: [M, 3] temporaries and ``np.minimum.at``); the maps are
            bit-identical.
        replace: optional ``(rows int64 [k], points float [k, 3], skip bool [M] or None)``: the
            returns ``rows`` are at ``points`` instead (the labelled objects' returns moved to the
            image's time, :func:`drivetrack.depth.stage.motion_at_image_time`), without a copy of
            ``points_vehicle``: the numba pass leaves them out (``skip``: ``rows`` as a mask, kept
            with the caller's memo) and a second pass over ``points`` adds them; the same maps.
    Returns:
        float32 [camera.height, camera.width], metres of z-depth (camera-frame x, distance along
        the optical axis from the camera centre), ``0`` where no point projects. A point at pixel
        position (x, y) lands in pixel (floor(x), floor(y)) (pixel ``i`` covers ``[i, i + 1)``).
        Where several points share a pixel the nearest wins (it occludes the others).
        With ``subset``, a pair (map of all points, map of the subset).
    """
    points_vehicle = np.asarray(points_vehicle)
    if points_vehicle.ndim != 2 or points_vehicle.shape[-1] != 3:
        raise ValueError(f"points_vehicle: expected float [M, 3], found shape {points_vehicle.shape}")
    if not np.issubdtype(points_vehicle.dtype, np.floating):
        raise TypeError(f"points_vehicle: expected a float dtype, found {points_vehicle.dtype}")
    height, width = int(camera.height), int(camera.width)
    if height <= 0 or width <= 0:
        raise ValueError(f"camera: expected a positive image size, found {width}x{height}")
    if subset is not None:
        subset = np.asarray(subset, dtype=bool)
        if subset.shape != points_vehicle.shape[:1]:
            raise ValueError(f"subset: expected bool [{points_vehicle.shape[0]}], found shape {subset.shape}")
    if kernel not in ("numba", "numpy"):
        raise ValueError(f"sparse_depth_from_points: kernel must be 'numba' or 'numpy', found {kernel!r}")
    if vehicle_from_points is not None:
        vehicle_from_points = np.asarray(vehicle_from_points, dtype=np.float64)
        if vehicle_from_points.shape != (4, 4):
            raise ValueError(f"vehicle_from_points: expected float [4, 4], found shape {vehicle_from_points.shape}")
    if replace is not None and not (len(points_vehicle) and kernel == "numba" and NUMBA_AVAILABLE):
        rows, moved = replace[:2]
        points_vehicle = np.array(points_vehicle, dtype=np.float64)
        points_vehicle[rows] = moved
        replace = None
    if len(points_vehicle) and kernel == "numba" and NUMBA_AVAILABLE:
        depth = np.zeros(height * width, dtype=np.float32)
        depth_subset = np.zeros(height * width if subset is not None else 0, dtype=np.float32)
        first = vehicle_from_points if vehicle_from_points is not None else np.zeros((0, 0))
        camera_from_vehicle, params = np.ascontiguousarray(camera.camera_from_vehicle), camera_parameters(camera)
        skip = np.zeros(0, dtype=bool)
        if replace is not None:
            rows, moved, skip = replace
            if skip is None:
                skip = np.zeros(len(points_vehicle), dtype=bool)
                skip[rows] = True
            # min is order-free: the moved returns in a second pass over the same maps
            project_nearest(np.ascontiguousarray(moved, dtype=np.float64), first, camera_from_vehicle, params,
                            subset[rows] if subset is not None else np.zeros(0, dtype=bool), depth, depth_subset,
                            np.zeros(0, dtype=bool))
        project_nearest(np.ascontiguousarray(points_vehicle, dtype=np.float64), first, camera_from_vehicle, params,
                        subset if subset is not None else np.zeros(0, dtype=bool), depth, depth_subset,
                        np.ascontiguousarray(skip, dtype=bool))
        depth = depth.reshape(height, width)
        return depth if subset is None else (depth, depth_subset.reshape(height, width))
    if not len(points_vehicle):
        return sparse_depth_from_pixels(np.zeros((0, 2)), np.zeros(0), np.zeros(0, dtype=bool), camera,
                                        None if subset is None else subset)
    if vehicle_from_points is not None:
        points_vehicle = transform_points(vehicle_from_points, points_vehicle)
    points_camera = transform_points(camera.camera_from_vehicle, points_vehicle)
    pixels, valid = camera.pixels_from_camera(points_camera)
    return sparse_depth_from_pixels(pixels, points_camera[:, 0], valid, camera, subset)


def sparse_depth_from_pixels(pixels: np.ndarray, depth: np.ndarray, valid: np.ndarray, camera: CameraModel,
                             subset: np.ndarray | None = None) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """The nearest z-depth per pixel of points already projected: ``pixels`` float [M, 2] (x, y),
    ``depth`` float [M] metres of z-depth, ``valid`` bool [M] (e.g. a rolling-shutter projection,
    :func:`drivetrack.camera.rolling_shutter.project_world`, each point at its capture time).
    Points outside ``camera``'s image or not valid are dropped; the map and ``subset`` exactly as
    :func:`sparse_depth_from_points` returns them (its numpy reference path is this function).
    """
    height, width = int(camera.height), int(camera.width)
    flat = np.full(height * width, np.inf, dtype=np.float64)
    # the subset's map in float32 directly: the minimum of float32-rounded depths equals the
    # float32-rounded minimum, so its values match the full map's where the same return wins
    flat_subset = np.full(height * width, np.inf, dtype=np.float32) if subset is not None else None
    if len(pixels):
        keep = np.asarray(valid, dtype=bool) & np.isfinite(pixels).all(axis=-1)
        keep[keep] = camera.inside_image(pixels[keep])
        cols = np.floor(pixels[keep, 0]).astype(np.int64)
        rows = np.floor(pixels[keep, 1]).astype(np.int64)
        np.minimum.at(flat, rows * width + cols, np.asarray(depth, np.float64)[keep])
        if subset is not None:
            chosen = np.asarray(subset, dtype=bool)[keep]
            np.minimum.at(flat_subset, rows[chosen] * width + cols[chosen],
                          np.asarray(depth, np.float64)[keep][chosen].astype(np.float32))

    def as_map(values: np.ndarray) -> np.ndarray:
        values[np.isinf(values)] = 0.0
        return values.astype(np.float32).reshape(height, width)

    return as_map(flat) if subset is None else (as_map(flat), as_map(flat_subset))


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


#: :func:`horizontal_depth_scale` results by camera parameters (a segment's few cameras; bounded)
_SCALE_CACHE: dict[tuple, np.ndarray] = {}
_SCALE_CACHE_SIZE = 32


def horizontal_depth_scale(camera: CameraModel, step_px: int = 8) -> np.ndarray:
    """float32 [H, W]: z-depth per metre of horizontal distance along each pixel's viewing ray
    (read-only; kept per camera calibration, since every depth map of a camera needs it).

    A point seen at pixel p at horizontal distance ``d`` (metres in the vehicle's x-y plane, from
    the camera centre) has z-depth ``d * scale[p]``. For a level camera ``scale`` is the cosine of
    the ray's azimuth off the optical axis; a camera pitched down sees lower points at larger
    z-depth for the same horizontal distance, which this accounts for. Computed on a grid of
    ``step_px`` and interpolated bilinearly (it varies smoothly over the image).
    """
    key = (camera.f_u, camera.f_v, camera.c_u, camera.c_v, camera.k1, camera.k2, camera.p1, camera.p2,
           camera.k3, int(camera.width), int(camera.height),
           np.asarray(camera.vehicle_from_camera, np.float64).tobytes(), max(1, int(step_px)))
    scale = _SCALE_CACHE.get(key)
    if scale is None:
        scale = _horizontal_depth_scale(camera, step_px)
        scale.flags.writeable = False
        if len(_SCALE_CACHE) >= _SCALE_CACHE_SIZE:
            _SCALE_CACHE.clear()
        _SCALE_CACHE[key] = scale
    return scale


def _horizontal_depth_scale(camera: CameraModel, step_px: int) -> np.ndarray:
    import cv2

    height, width = int(camera.height), int(camera.width)
    step = max(1, int(step_px))
    xs = np.append(np.arange(0.5, width, step), width - 0.5)
    ys = np.append(np.arange(0.5, height, step), height - 0.5)
    grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    rays = camera.rays_from_pixels(grid)                                          # camera frame
    horizontal = np.linalg.norm((rays @ camera.vehicle_from_camera[:3, :3].T)[:, :2], axis=-1)
    coarse = (rays[:, 0] / np.maximum(horizontal, 1e-9)).reshape(ys.size, xs.size)
    # grid nodes at pixel centres 0.5, 0.5 + step, ..., last centre: resample onto every centre
    map_x = np.interp(np.arange(width) + 0.5, xs, np.arange(xs.size)).astype(np.float32)
    map_y = np.interp(np.arange(height) + 0.5, ys, np.arange(ys.size)).astype(np.float32)
    grid_x, grid_y = np.meshgrid(map_x, map_y)
    return cv2.remap(coarse.astype(np.float32), grid_x, grid_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def bound_blind_zone(sparse: np.ndarray, reference: np.ndarray, cell_px: int, ratio: float = 0.95,
                     scale: np.ndarray | None = None) -> np.ndarray:
    """float32 [H, W]: ``sparse`` with the image region below the reference lidar's field of view bounded.

    A roof LiDAR next to the cameras (Waymo's TOP: beams down to about -17.6 degrees) leaves a
    blind zone round the vehicle that the bottom rows of a camera image often look into: the
    lowest scan line of that LiDAR in a camera image is the edge of what it can see. Below it,
    a camera ray points further down than any of the reference's beams, so it meets the ground
    nearer than that scan line, or a surface standing in front of it: its horizontal distance is
    at most about that of the lowest scan line there (the prior used here). Two things go wrong
    there without it: a car right beside the camera below the reference's beams has no return at
    all, so the map is unknown (completion does not reach that far) and points behind the car
    look visible; and lidars mounted elsewhere (bumpers, sides) see *under or round* that car and
    put far returns into the image region it covers.

    Per column cell of ``cell_px`` pixels, the lowest reference return (row ``r``) and the
    farthest reference return of that lowest scan line (within ``cell_px`` rows above ``r``, in
    horizontal distance) give the bound ``b``; at a pixel below row ``r`` it is the z-depth
    ``b * scale``. There, returns deeper than ``bound / ratio`` are dropped (seen past a nearer
    surface, by the occlusion test's own ``ratio``), returns nearer than that (an object in the
    blind zone seen by a bumper lidar) are kept, and every pixel without a return gets the bound
    encoded as a **negative** value ``-bound``: "no return here; the surface is at most this
    deep". :func:`apply_depth_bounds` applies it to the completed map (``min(completed, bound)``,
    the bound where completion left the pixel unknown), so that completion still spreads nearer
    returns into the region and completers only ever see returns (``max(sparse, 0)``). Column
    cells without any reference return are left as they are.

    Args:
        sparse: float32 [H, W] sparse z-depth of every lidar used for the map, 0 = no return
            (returns already removed, e.g. by :func:`see_through_returns`, are 0).
        reference: float32 [H, W] sparse z-depth of the reference lidar alone (a subset of
            ``sparse``'s returns), 0 = no return. A reference return counts only where it is the
            return ``sparse`` kept at its pixel (not removed, not behind another lidar's).
        cell_px: width of a column cell and height of the lowest scan line, pixels (about twice
            the reference's column spacing in the image).
        ratio: a return is deeper than the bound when ``ratio * depth > bound``.
        scale: float32 [H, W], :func:`horizontal_depth_scale` of the camera; None takes z-depth
            as the horizontal distance (a level camera, pixels near the optical axis).
    Returns:
        float32 [H, W], a new map: returns > 0, no return 0, bounded pixel without a return < 0.
    """
    sparse = np.asarray(sparse, dtype=np.float32)
    reference = np.asarray(reference, dtype=np.float32)
    if sparse.ndim != 2 or reference.shape != sparse.shape:
        raise ValueError(f"bound_blind_zone: expected sparse and reference float32 [H, W] of one shape, "
                         f"found {sparse.shape} and {reference.shape}")
    if scale is not None and np.shape(scale) != sparse.shape:
        raise ValueError(f"bound_blind_zone: scale must be float32 {sparse.shape}, found {np.shape(scale)}")
    if int(cell_px) < 1 or not 0 < ratio <= 1:
        raise ValueError(f"bound_blind_zone: cell_px must be >= 1 (got {cell_px}), ratio in (0, 1] (got {ratio})")
    cell = int(cell_px)
    if NUMBA_AVAILABLE:                     # one kernel, three passes (the numpy form below is its reference)
        out = sparse.copy()
        blind_zone_in_place(out, reference, cell, np.float32(ratio),
                            np.zeros((1, 1), np.float32) if scale is None else np.asarray(scale, dtype=np.float32),
                            scale is not None)
        return out
    return _bound_blind_zone_numpy(sparse, reference, cell, ratio, scale)


def _bound_blind_zone_numpy(sparse: np.ndarray, reference: np.ndarray, cell: int, ratio: float,
                            scale: np.ndarray | None) -> np.ndarray:
    """The numpy form of :func:`bound_blind_zone` (validated arguments)."""
    height, width = sparse.shape
    cells = -(-width // cell)
    out = sparse.copy()
    ys, xs = np.nonzero(reference > 0)
    depth = reference[ys, xs]
    seen = depth <= sparse[ys, xs]                        # the visible return of its pixel
    ys, xs, depth = ys[seen], xs[seen], depth[seen]
    if ys.size == 0:
        return out
    horizontal = depth / (scale[ys, xs] if scale is not None else 1.0)   # metres
    cx = xs // cell
    lowest = np.full(cells, -1, dtype=np.int64)
    np.maximum.at(lowest, cx, ys)                                       # lowest reference row per cell
    line = ys >= lowest[cx] - cell                                      # the lowest scan line
    bound = np.zeros(cells, dtype=np.float32)
    np.maximum.at(bound, cx[line], horizontal[line])
    row_of = np.repeat(lowest, cell)[:width]                           # [W]
    bound_of = np.repeat(bound, cell)[:width]
    has = row_of >= 0
    top = int(row_of[has].min()) + 1                                    # first row that can be below
    if top >= height:
        return out
    band = out[top:]                                                    # a view: rows top..H-1
    below = (np.arange(top, height)[:, None] > row_of[None, :]) & has[None, :]
    region = band[below]
    bounded = np.broadcast_to(bound_of[None, :], band.shape)[below]
    if scale is not None:
        bounded = bounded * np.asarray(scale, dtype=np.float32)[top:][below]
    band[below] = np.where((region <= 0) | (ratio * region > bounded), -bounded, region)
    return out


def apply_depth_bounds(dense: np.ndarray, sparse: np.ndarray, in_place: bool = False) -> np.ndarray:
    """float32 [..., H, W]: completed maps with the bounds of :func:`bound_blind_zone` applied.

    Args:
        dense: float32 [..., H, W] completed z-depth, 0 = unknown (completed from
            ``max(sparse, 0)``).
        sparse: float32 [..., H, W] the sparse maps it was completed from; a negative value
            ``-b`` bounds the depth of that pixel to at most ``b`` (and sets it where unknown).
        in_place: write into ``dense`` (float32, C-contiguous, writeable) in one pass
            (:func:`drivetrack.depth.kernel.bound_in_place`) and return it.
    Returns:
        float32 [..., H, W]; without ``in_place``, ``dense`` itself when ``sparse`` holds no bound,
        else a new array.
    """
    sparse = np.asarray(sparse)
    if np.shape(dense) != sparse.shape:
        raise ValueError(f"apply_depth_bounds: completed maps {np.shape(dense)} and sparse maps {sparse.shape} "
                         f"differ in shape")
    if in_place:
        if not (isinstance(dense, np.ndarray) and dense.dtype == np.float32 and dense.flags.c_contiguous
                and dense.flags.writeable):
            raise ValueError("apply_depth_bounds(in_place=True): dense must be a writeable C-contiguous "
                             "float32 array")
        bound_in_place(dense.reshape(-1), np.ascontiguousarray(sparse, dtype=np.float32).reshape(-1))
        return dense
    bounded = sparse < 0
    if not bounded.any():
        return dense
    out = np.array(dense, dtype=np.float32, copy=True)
    bound_in_place(out.reshape(-1), np.ascontiguousarray(sparse, dtype=np.float32).reshape(-1))
    return out
