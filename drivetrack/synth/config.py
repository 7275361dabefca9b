"""What to generate: :class:`SynthConfig`, segment names and the timing constants."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivetrack.synth.sensors import DEFAULT_CAMERAS

__all__ = ["SynthConfig", "segment_name", "FRAME_PERIOD_S", "SWEEP_S", "LABEL_RANGE_M", "T0_MICROS"]

FRAME_PERIOD_S = 0.1
SWEEP_S = 0.1
LABEL_RANGE_M = 75.0
T0_MICROS = 1_557_000_000_000_000


@dataclass(frozen=True)
class SynthConfig:
    """What to generate. ``box_noise_m`` is the sigma (metres, per axis) of Gaussian noise added
    to the *written* box centres; ``heading_noise_rad`` defaults to 1 degree per 5 cm of it.
    ``rolling_shutter`` renders rolling-shutter cameras (module docstring); off by default, which
    keeps the global-shutter output byte-identical to earlier versions."""
    seed: int = 7
    frames: int = 40
    preset: str = "small"
    cameras: tuple[str, ...] = DEFAULT_CAMERAS
    split: str = "training"
    box_noise_m: float = 0.0
    heading_noise_rad: float | None = None
    rolling_shutter: bool = False

    @property
    def heading_sigma(self) -> float:
        if self.heading_noise_rad is not None:
            return float(self.heading_noise_rad)
        return float(np.deg2rad(1.0) * self.box_noise_m / 0.05)


def segment_name(seed: int, index: int) -> str:
    """Deterministic ``key.segment_context_name`` of synthetic segment ``index`` of ``seed``."""
    return f"drivetrack_synth_s{seed}_{index:04d}"
