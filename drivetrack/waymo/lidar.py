"""Range images of the Waymo lidars: beam geometry (METHOD.md section 1) and points.

The beam geometry is shared by the reader (range image -> points, :func:`lidar_points`) and the
synthetic generator (rays to cast), so both follow one definition of which direction a
range-image pixel looks in.
"""
from __future__ import annotations

import numpy as np

from drivetrack.geometry import invert_rigid
from drivetrack.waymo.kernel import pack_return_keys, vehicle_from_pixel_pose

__all__ = ["beam_inclinations", "beam_azimuths", "sensor_directions", "lidar_points",
           "points_from_directions", "apply_pixel_pose", "camera_projection_at",
           "RETURN_KEY_BITS", "return_keys"]


def beam_inclinations(height: int, values: np.ndarray | None, inclination_min: float | None,
                      inclination_max: float | None) -> np.ndarray:
    """float64 [H] inclination of each range-image row, radians, row 0 = highest beam.

    ``values`` (``beam_inclination.values``, ascending as Waymo stores them) wins when present and
    non-empty; otherwise rows are spread uniformly over [min, max] at their centres:
    ``min + (i + 0.5) / H * (max - min)``. The list is then reversed, since row 0 of a range image
    is the highest beam.
    """
    if values is not None and len(values) > 0:
        values = np.asarray(values, dtype=np.float64)
        if values.shape != (height,):
            raise ValueError(
                f"beam_inclination.values has {values.shape[0]} entries but the range image has "
                f"{height} rows")
        incl = values
    else:
        if inclination_min is None or inclination_max is None:
            raise ValueError("beam_inclination has neither values nor min/max")
        i = np.arange(height, dtype=np.float64)
        incl = inclination_min + (i + 0.5) / height * (inclination_max - inclination_min)
    return incl[::-1].copy()


def beam_azimuths(width: int, vehicle_from_lidar: np.ndarray) -> np.ndarray:
    """float64 [W] azimuth of each range-image column in the lidar (sensor) frame, radians.

    ``az = (2 (W - c - 0.5) / W - 1) pi - atan2(E[1, 0], E[0, 0])``: column 0 looks backwards and
    azimuth decreases with the column; the correction makes the image centre face the vehicle's
    +x whatever the sensor's mounting yaw.
    """
    c = np.arange(width, dtype=np.float64)
    yaw = np.arctan2(vehicle_from_lidar[1, 0], vehicle_from_lidar[0, 0])
    return (2.0 * (width - c - 0.5) / width - 1.0) * np.pi - yaw


def sensor_directions(inclinations: np.ndarray, azimuths: np.ndarray) -> np.ndarray:
    """float64 [H, W, 3] unit direction of each range-image pixel in the lidar frame."""
    ci = np.cos(inclinations)[:, None]
    return np.stack([ci * np.cos(azimuths)[None, :], ci * np.sin(azimuths)[None, :],
                     np.broadcast_to(np.sin(inclinations)[:, None], (inclinations.size, azimuths.size))],
                    axis=-1)


def lidar_points(range_image: np.ndarray, vehicle_from_lidar: np.ndarray,
                 inclinations: np.ndarray, pixel_pose: np.ndarray | None = None,
                 world_from_vehicle: np.ndarray | None = None):
    """Valid returns of one range image as vehicle-frame points.

    Args:
        range_image: float [H, W, C] (channels range, intensity, elongation, no-label-zone);
            a pixel is a return where range > 0 and finite (NaN / inf ranges are no return).
        vehicle_from_lidar: float64 [4, 4], ``lidar_calibration.extrinsic``.
        inclinations: float64 [H], radians, row 0 = highest beam (:func:`beam_inclinations`).
        pixel_pose: optional float [H, W, 6] (``lidar_pose``: roll, pitch, yaw, x, y, z =
            world_from_vehicle at each pixel's capture time); needs ``world_from_vehicle``.
        world_from_vehicle: float64 [4, 4], the frame's vehicle pose.
    Returns:
        ``(points_vehicle float64 [M, 3], row int32 [M], col int32 [M], intensity float32 [M])``
        in row-major pixel order; with ``pixel_pose`` the points are in the frame's vehicle frame
        (motion during the sweep removed).
    """
    h, w, _ = range_image.shape
    azimuths = beam_azimuths(w, vehicle_from_lidar)
    directions = sensor_directions(np.asarray(inclinations, np.float64), azimuths)
    rotated = directions @ np.asarray(vehicle_from_lidar, np.float64)[:3, :3].T
    return points_from_directions(range_image, rotated, vehicle_from_lidar[:3, 3], pixel_pose,
                                   world_from_vehicle)


def points_from_directions(range_image, directions_vehicle, origin_vehicle, pixel_pose=None,
                            world_from_vehicle=None):
    rng = range_image[..., 0]
    with np.errstate(invalid="ignore"):
        rows, cols = np.nonzero(np.isfinite(rng) & (rng > 0))
    r = rng[rows, cols].astype(np.float64)
    points = r[:, None] * directions_vehicle[rows, cols] + np.asarray(origin_vehicle, np.float64)
    if range_image.shape[-1] > 1:
        intensity = range_image[rows, cols, 1].astype(np.float32)
    else:
        intensity = np.full(rows.shape, np.nan, np.float32)
    if pixel_pose is not None:
        points = apply_pixel_pose(points, pixel_pose[rows, cols], world_from_vehicle)
    return points, rows.astype(np.int32), cols.astype(np.int32), intensity


def apply_pixel_pose(points_vehicle_at_pixel: np.ndarray, pose: np.ndarray,
                      world_from_vehicle: np.ndarray) -> np.ndarray:
    """float64 [M, 3] ``inv(world_from_vehicle) @ pixel_pose @ p`` for points [M, 3] and poses
    [M, 6] (roll, pitch, yaw radians, x, y, z metres: ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` as
    :func:`drivetrack.geometry.rotation_from_rpy`), in one numba pass
    (:func:`drivetrack.waymo.kernel.vehicle_from_pixel_pose`)."""
    pose = np.asarray(pose, np.float64)
    points = np.ascontiguousarray(points_vehicle_at_pixel, np.float64)
    angles = pose[:, :3]
    out = np.empty_like(points)
    vehicle_from_pixel_pose(points, np.cos(angles), np.sin(angles), np.ascontiguousarray(pose[:, 3:6]),
                            invert_rigid(world_from_vehicle), out)
    return out


def camera_projection_at(projection: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """int16 [M, 6] ``lidar_camera_projection`` [cam1, x1, y1, cam2, x2, y2] at given pixels.

    ``projection`` is the decoded [H, W, 6] range image (integers stored as float); camera 0 means
    no projection. Coordinates follow Waymo: pixel 0 starts at the left/top image edge.
    """
    return np.rint(projection[rows, cols, :6]).astype(np.int16)




#: Bit fields of a LiDAR return key (:func:`return_keys`), most significant first; 63 bits in all,
#: so every key is a non-negative int64.
RETURN_KEY_BITS = (("frame", 28), ("laser", 3), ("return", 2), ("row", 14), ("col", 16))


def return_keys(frame, laser, return_index, row, col, where: str = "") -> np.ndarray:
    """int64 [N] key of each LiDAR return (segment frame, laser, return, range-image row, col).

    Bit layout (:data:`RETURN_KEY_BITS`), most significant first: frame 28 bits | laser 3 |
    return 2 | row 14 | col 16. Keys therefore sort like the tuples ``(frame, laser, return, row,
    col)``, and the keys of one (frame, laser, return) range image lie in
    ``[return_keys(f, l, r, 0, 0), return_keys(f, l, r + 1, 0, 0))``. The one packing for every
    place that joins returns (the reader's ordering, consistency, evaluation, show); keys are
    compared within one process only and never written.

    Args:
        frame, laser, return_index, row, col: integer arrays broadcastable to [N] (or scalars).
        where: named in the error.
    Raises:
        ValueError naming ``where``, the field and the first value outside ``[0, 2**bits)``.
    """
    columns = [np.asarray(v) for v in (frame, laser, return_index, row, col)]
    if all(c.ndim == 1 and c.shape == columns[0].shape and c.dtype.kind in "iu" for c in columns):
        # one pass over equal columns (a segment's 9.4 M returns: ~30 numpy passes otherwise)
        out = np.empty(columns[0].shape[0], np.int64)
        field, i = pack_return_keys(*columns, np.array([b for _, b in RETURN_KEY_BITS], np.int64), out)
        if field >= 0:
            name, bits = RETURN_KEY_BITS[field]
            raise ValueError(f"{where}: LiDAR {name} value {int(columns[field][i])} outside [0, {1 << bits})")
        return out
    key = np.zeros(np.broadcast(*columns).shape, np.int64)
    for (name, bits), value in zip(RETURN_KEY_BITS, (frame, laser, return_index, row, col)):
        value = np.asarray(value)
        limit = 1 << bits
        if value.size and (value.min() < 0 or value.max() >= limit):
            bad = int(value[(value < 0) | (value >= limit)].flat[0])
            raise ValueError(f"{where}: LiDAR {name} value {bad} outside [0, {limit})")
        key = (key << bits) | value.astype(np.int64, copy=False)
    return key
