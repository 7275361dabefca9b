"""Sensor rig of the synthetic vehicle: presets, Waymo-like camera and lidar calibrations."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivetrack.camera.model import CameraModel
from drivetrack.geometry import rigid_from_rotation_translation, rotation_from_rpy
from drivetrack.waymo.schema import CameraName, LaserName

__all__ = ["Preset", "PRESETS", "LidarSpec", "camera_models", "lidar_specs", "DEFAULT_CAMERAS",
           "GLOBAL_SHUTTER", "LEFT_TO_RIGHT", "TOP_TO_BOTTOM", "RIGHT_TO_LEFT",
           "ROLLING_SHUTTER_DIRECTIONS", "READOUT_S", "SHUTTER_S"]

#: ``rolling_shutter_direction`` values (``dataset.proto`` CameraCalibration.RollingShutterReadOutDirection).
TOP_TO_BOTTOM = 1
LEFT_TO_RIGHT = 2
RIGHT_TO_LEFT = 4
GLOBAL_SHUTTER = 5

#: Readout direction per camera when ``SynthConfig.rolling_shutter`` is on: the front camera
#: reads rows top to bottom, the angled and side cameras read columns, sweeping from the side
#: nearer the vehicle's front towards the back (three different directions are exercised).
ROLLING_SHUTTER_DIRECTIONS = {"FRONT": TOP_TO_BOTTOM, "FRONT_LEFT": RIGHT_TO_LEFT,
                              "FRONT_RIGHT": LEFT_TO_RIGHT, "SIDE_LEFT": RIGHT_TO_LEFT,
                              "SIDE_RIGHT": LEFT_TO_RIGHT}
#: Exposure (``rolling_shutter_params.shutter``) and readout durations written per image, seconds.
SHUTTER_S = 0.004
READOUT_S = 0.033

DEFAULT_CAMERAS = ("FRONT", "FRONT_LEFT", "FRONT_RIGHT")


@dataclass(frozen=True)
class Preset:
    """Sensor resolutions. ``camera_scale`` multiplies Waymo's image sizes and focal lengths."""
    name: str
    camera_scale: float
    top_shape: tuple[int, int]
    short_shape: tuple[int, int]
    jpeg_quality: int = 90


PRESETS: dict[str, Preset] = {
    "full": Preset("full", 1.0, (64, 2650), (200, 600)),
    "medium": Preset("medium", 0.5, (64, 2650), (200, 600)),
    "small": Preset("small", 0.25, (32, 650), (40, 120)),
}

# name -> (width, height, f, yaw deg, mount x, y, z, k1, k2, p1, p2, k3) at Waymo's full resolution
_CAMERAS = {
    "FRONT": (1920, 1280, 2055.0, 0.0, 1.54, -0.02, 2.12, 0.044, -0.32, 0.0011, -0.0006, 0.012),
    "FRONT_LEFT": (1920, 1280, 2050.0, 45.0, 1.50, 0.10, 2.11, 0.041, -0.31, -0.0008, 0.0009, 0.010),
    "FRONT_RIGHT": (1920, 1280, 2048.0, -45.0, 1.49, -0.13, 2.11, 0.046, -0.33, 0.0007, 0.0004, 0.014),
    "SIDE_LEFT": (1920, 886, 2040.0, 90.0, 1.05, 0.95, 2.05, 0.040, -0.30, 0.0005, -0.0007, 0.011),
    "SIDE_RIGHT": (1920, 886, 2042.0, -90.0, 1.05, -0.95, 2.05, 0.043, -0.31, -0.0006, 0.0005, 0.012),
}


def camera_models(preset: Preset, names: tuple[str, ...] = DEFAULT_CAMERAS,
                  rolling_shutter_direction: int | None = GLOBAL_SHUTTER) -> dict[int, CameraModel]:
    """``CameraName`` value -> :class:`CameraModel` for the requested cameras.

    ``rolling_shutter_direction`` None gives each camera its direction from
    :data:`ROLLING_SHUTTER_DIRECTIONS`; an int gives every camera that value.

    Extrinsics (``vehicle_from_camera``) mount the cameras about 2.1 m high, looking forward or
    +-45 / +-90 degrees, pitched down 1 degree; principal points sit a few pixels off centre.
    """
    out = {}
    for name in names:
        if name not in _CAMERAS:
            raise ValueError(f"unknown camera {name!r}; choose from {sorted(_CAMERAS)}")
        w, h, f, yaw, x, y, z, k1, k2, p1, p2, k3 = _CAMERAS[name]
        s = preset.camera_scale
        rotation = rotation_from_rpy(0.002, np.deg2rad(1.0), np.deg2rad(yaw))
        out[int(CameraName[name])] = CameraModel(
            f_u=f * s, f_v=f * s * 1.0003, c_u=(w / 2 + 3.7) * s, c_v=(h / 2 - 2.9) * s,
            k1=k1, k2=k2, p1=p1, p2=p2, k3=k3, width=int(round(w * s)), height=int(round(h * s)),
            vehicle_from_camera=rigid_from_rotation_translation(rotation, np.array([x, y, z])),
            rolling_shutter_direction=(ROLLING_SHUTTER_DIRECTIONS[name] if rolling_shutter_direction
                                       is None else rolling_shutter_direction))
    return out


@dataclass(frozen=True)
class LidarSpec:
    """One lidar: range-image shape, mounting, beam inclinations and sensing limits.

    ``inclination_values`` (ascending, radians) is written for TOP only, as Waymo does; the short
    lidars publish min/max only. ``half_fov`` (radians) limits the azimuths a short lidar sees
    around its forward axis; ``max_range`` in metres.
    """
    laser: int
    height: int
    width: int
    vehicle_from_lidar: np.ndarray
    inclination_min: float
    inclination_max: float
    inclination_values: np.ndarray | None
    max_range: float
    half_fov: float


def lidar_specs(preset: Preset) -> dict[int, LidarSpec]:
    """``LaserName`` value -> :class:`LidarSpec` (TOP + FRONT, SIDE_LEFT, SIDE_RIGHT, REAR)."""
    th, tw = preset.top_shape
    # TOP: denser beams near the horizon (non-uniform, so readers must use the values list)
    s = np.linspace(0.0, 1.0, th)
    lo, hi = np.deg2rad(-17.6), np.deg2rad(2.4)
    top_values = lo + (hi - lo) * (1.0 - (1.0 - s) ** 1.35)
    specs = {int(LaserName.TOP): LidarSpec(
        int(LaserName.TOP), th, tw,
        rigid_from_rotation_translation(rotation_from_rpy(0.001, -0.002, 0.0213), np.array([1.43, 0.0, 2.18])),
        float(top_values[0]), float(top_values[-1]), top_values, 75.0, np.pi)}
    sh, sw = preset.short_shape
    for name, (x, y, z, yaw) in {"FRONT": (4.07, 0.0, 0.69, 0.0), "SIDE_LEFT": (3.25, 1.02, 0.98, 90.0),
                                 "SIDE_RIGHT": (3.25, -1.02, 0.98, -90.0),
                                 "REAR": (-1.15, 0.0, 0.47, 180.0)}.items():
        specs[int(LaserName[name])] = LidarSpec(
            int(LaserName[name]), sh, sw,
            rigid_from_rotation_translation(rotation_from_rpy(0.0, 0.0, np.deg2rad(yaw)), np.array([x, y, z])),
            np.deg2rad(-90.0), np.deg2rad(30.0), None, 20.0, np.deg2rad(95.0))
    return specs
