"""What to generate: :class:`SynthConfig`, segment names and the timing constants."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivetrack.synth.sensors import DEFAULT_CAMERAS

__all__ = ["SynthConfig", "segment_name", "FRAME_PERIOD_S", "SWEEP_S", "LABEL_RANGE_M", "T0_MICROS",
           "sweep_offset"]

FRAME_PERIOD_S = 0.1
SWEEP_S = 0.1
LABEL_RANGE_M = 75.0
T0_MICROS = 1_557_000_000_000_000



def sweep_offset(azimuth_vehicle: np.ndarray) -> np.ndarray:
    """float64 [...] seconds after the frame time at which the TOP sweep points along
    ``azimuth_vehicle`` (radians about the vehicle's z, 0 = forward, positive = left).

    The TOP columns (``drivetrack.waymo.lidar.beam_azimuths``, mount yaw corrected) run from
    azimuth +pi at the sweep start (frame time - 0.05 s) down to -pi at its end, so
    ``offset = -wrap(azimuth) / (2 pi) * SWEEP_S``: left-facing cameras fire before the frame time,
    right-facing ones after it."""
    a = np.angle(np.exp(1j * np.asarray(azimuth_vehicle, np.float64)))
    return -a / (2.0 * np.pi) * SWEEP_S


@dataclass(frozen=True)
class SynthConfig:
    """What to generate. ``box_noise_m`` is the sigma (metres, per axis) of Gaussian noise added
    to the *written* box centres; ``heading_noise_rad`` defaults to 1 degree per 5 cm of it.
    ``rolling_shutter`` renders rolling-shutter cameras (module docstring); off by default, which
    keeps the global-shutter output byte-identical to earlier versions.

    ``world``: "default", or "hard" (adds the cases of issues 15 and 16, see
    :func:`drivetrack.synth.world._hard_objects`). ``camera_trigger``: "frame" (every camera image
    at the frame time) or "sweep" (each camera fires when the TOP sweep crosses its optical axis,
    as Waymo's do: ``pose_timestamp`` = frame time - yaw / (2 pi) * 0.1 s); None means "sweep"
    in the hard world, "frame" otherwise. ``label_time``: "frame" (``lidar_box`` = the box at the
    frame time) or "sweep" (the box where the object was when the TOP sweep passed its centre,
    still expressed in the vehicle frame of the frame time). ``car_shape``: "box" (every vehicle is
    its label box), "cabin" (a body and a cabin inside the label box, see
    :func:`drivetrack.synth.world.cabin_parts`) or "rounded" (the cabin car with the body's corners
    rounded in plan view, :func:`drivetrack.synth.world.rounded_parts`). ``pedestrian_shape``: "box" (every pedestrian is its
    label box) or "body" (legs, torso, arms and head inside it, see
    :func:`drivetrack.synth.world.body_parts`). ``speed_changes_mps2``: 0 (every mover keeps its
    speed, the worlds before) or the largest along-track acceleration (m/s^2) with which moving
    vehicles and cyclists brake and speed up (:func:`drivetrack.synth.world.make_world`); the
    world is otherwise the same. ``range_noise_m``: 0 (exact ranges) or the sigma (metres) of
    Gaussian noise on every written lidar range, as real returns carry (each return moves along
    its ray; the ground truth keeps the point where the ray hit the surface). ``rear_axle_fraction``:
    0 (the box centre of every mover follows its path, heading its tangent: no slip at the centre)
    or where the point without lateral slip lies behind the centre of each moving vehicle and
    cyclist, as a fraction of its length (about 0.3 for a car's rear axle): on a turn the centre
    then moves sideways, as real cars' do (:attr:`drivetrack.synth.world.SynthObject.axle_offset_m`).
    ``box_slack_m``: 0 (every written box is its object's extent) or how much wider than its object
    every written box is drawn on each side (metres), as hand-drawn labels are: the written sizes
    (``lidar_box``, ``lidar_camera_synced_box``, ``projected_lidar_box``) grow by twice this, the
    centres stay; the ground truth keeps the objects' own sizes."""
    seed: int = 7
    frames: int = 40
    preset: str = "small"
    cameras: tuple[str, ...] = DEFAULT_CAMERAS
    split: str = "training"
    box_noise_m: float = 0.0
    heading_noise_rad: float | None = None
    rolling_shutter: bool = False
    world: str = "default"
    camera_trigger: str | None = None
    label_time: str = "frame"
    car_shape: str = "box"
    pedestrian_shape: str = "box"
    speed_changes_mps2: float = 0.0
    range_noise_m: float = 0.0
    rear_axle_fraction: float = 0.0
    box_slack_m: float = 0.0

    def __post_init__(self):
        from drivetrack.synth.world import CAR_SHAPES, PEDESTRIAN_SHAPES, WORLDS

        for name, value, allowed in (("world", self.world, WORLDS),
                                     ("camera_trigger", self.camera_trigger, (None, "frame", "sweep")),
                                     ("label_time", self.label_time, ("frame", "sweep")),
                                     ("car_shape", self.car_shape, CAR_SHAPES),
                                     ("pedestrian_shape", self.pedestrian_shape, PEDESTRIAN_SHAPES)):
            if value not in allowed:
                raise ValueError(f"SynthConfig.{name}: expected one of {allowed}, found {value!r}")
        from drivetrack.synth.sensors import _CAMERAS

        unknown = [c for c in self.cameras if c not in _CAMERAS]
        if isinstance(self.cameras, str) or not self.cameras or unknown:
            raise ValueError(f"SynthConfig.cameras: expected a non-empty tuple of camera names from "
                             f"{', '.join(_CAMERAS)}, found {self.cameras!r}")
        if not (isinstance(self.range_noise_m, (int, float)) and 0 <= self.range_noise_m <= 0.5):
            raise ValueError(f"SynthConfig.range_noise_m: expected a sigma in metres in [0, 0.5], "
                             f"found {self.range_noise_m!r}")
        if not (isinstance(self.rear_axle_fraction, (int, float)) and 0 <= self.rear_axle_fraction < 0.5):
            raise ValueError(f"SynthConfig.rear_axle_fraction: expected a fraction of the length in [0, 0.5), "
                             f"found {self.rear_axle_fraction!r}")
        if not (isinstance(self.box_slack_m, (int, float)) and 0 <= self.box_slack_m <= 0.5):
            raise ValueError(f"SynthConfig.box_slack_m: expected metres in [0, 0.5], found {self.box_slack_m!r}")
        if not (isinstance(self.speed_changes_mps2, (int, float)) and 0 <= self.speed_changes_mps2 < 20):
            raise ValueError(f"SynthConfig.speed_changes_mps2: expected a number of m/s^2 in [0, 20), "
                             f"found {self.speed_changes_mps2!r}")

    @property
    def trigger(self) -> str:
        """The camera trigger convention in effect ("frame" or "sweep")."""
        if self.camera_trigger is not None:
            return self.camera_trigger
        return "sweep" if self.world == "hard" else "frame"

    @property
    def extended_truth(self) -> bool:
        """True when anything beyond the original scene is on: the truth then also records roles
        and time offsets (kept out of the default output so its bytes stay the same)."""
        return (self.world != "default" or self.trigger != "frame" or self.label_time != "frame"
                or self.speed_changes_mps2 > 0 or self.rear_axle_fraction > 0)

    @property
    def heading_sigma(self) -> float:
        if self.heading_noise_rad is not None:
            return float(self.heading_noise_rad)
        return float(np.deg2rad(1.0) * self.box_noise_m / 0.05)


def segment_name(seed: int, index: int) -> str:
    """Deterministic ``key.segment_context_name`` of synthetic segment ``index`` of ``seed``."""
    return f"drivetrack_synth_s{seed}_{index:04d}"
