"""Range-image beam geometry of the Waymo lidars (METHOD.md section 1).

Shared by the reader (range image -> points) and the synthetic generator (rays to cast), so both
follow one definition of which direction a range-image pixel looks in.
"""
from __future__ import annotations

import numpy as np

__all__ = ["beam_inclinations", "beam_azimuths", "sensor_directions"]


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
