"""Evaluation: annotations against exact synthetic truth, and trackers against a release.

docs/evaluation.md describes what is measured. The modules, by job:

- :mod:`.metrics`: TAP-Vid metrics (``compute_tapvid_metrics``, query building, rescaling).
- :mod:`.clips`: :class:`Clip` (shared with :mod:`drivetrack.show`), finding and reading clip files.
- :mod:`.truth`: :class:`TruthIndex`, the ground truth of a synthetic segment indexed by LiDAR return.
- :mod:`.scoring`: :func:`score_clip`, :func:`evaluate_clips` / ``_tracks`` / ``_annotations``, tables.
- :mod:`.predictions`: :func:`score_predictions`, a tracker's npz files against a release.
"""
from drivetrack.evaluation.clips import AnnotationFile, Clip, clip_from_tracks, find_annotation_files, iter_clips, \
    read_clip
from drivetrack.evaluation.predictions import score_predictions
from drivetrack.evaluation.scoring import (DEFAULT_MAX_QUERIES, METRIC_KEYS, Evaluation, evaluate_annotations,
                                           evaluate_clips, evaluate_tracks, pixel_error_stats, score_clip,
                                           tapvid_scores)
from drivetrack.evaluation.truth import TruthIndex

__all__ = ["METRIC_KEYS", "DEFAULT_MAX_QUERIES", "Clip", "Evaluation", "AnnotationFile", "TruthIndex",
           "find_annotation_files", "read_clip", "iter_clips", "clip_from_tracks", "score_clip",
           "evaluate_clips", "evaluate_tracks", "evaluate_annotations", "score_predictions", "tapvid_scores",
           "pixel_error_stats"]
