"""Procedural driving scenes in the official Waymo v2 schema, with exact ground truth.

``generate_segment(root, SynthConfig(...), index)`` writes one segment's components to
``{root}/{split}/{component}/{segment}.parquet`` and its exact truth to
``{root}/{split}/drivetrack_ground_truth/{segment}/`` (see :mod:`drivetrack.synth.ground_truth`
and docs/synthetic.md). Everything derives from the explicit seed: same config, same bytes.
"""
from drivetrack.synth.generate import SynthConfig, generate_segment, segment_name
from drivetrack.synth.ground_truth import GroundTruth, load_ground_truth
from drivetrack.synth.sensors import PRESETS

__all__ = ["SynthConfig", "generate_segment", "segment_name", "GroundTruth", "load_ground_truth",
           "PRESETS"]
