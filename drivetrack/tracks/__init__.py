"""Per (segment, camera, object) point tracks with occlusion, filters, consistency metrics, writers.

Two stages, separable by an orchestrator:

1. depth stage (per frame, batchable, GPU-queue friendly; :mod:`drivetrack.depth.stage`):
   ``plan = plan_segment(scene, config)``; ``depth_jobs(scene, config, plan)`` ->
   ``sparse_depth(scene, config, job)`` -> ``complete_depth(sparse, config)``;
2. track stage (per object clip): ``ctx = prepare_segment(scene, config, depth, plan)``;
   ``for job in object_jobs(ctx): result = run_object_job(ctx, job)``;
   ``write_object_outputs(out_url, split, result)``; tables from ``object_stats``,
   ``segment_stats``, ``rejection_stats``.

The numeric core never imports Prefect.
"""
from drivetrack.outputs import REJECTION_REASONS
from drivetrack.tracks.config import FOV_RUN_POLICIES, TrackConfig
from drivetrack.tracks.core import ObjectTracks, run_object_job, track_speeds
from drivetrack.tracks.context import DepthStack, SegmentContext, object_jobs, prepare_segment
from drivetrack.tracks.plan import ObjectJob, SegmentPlan, continuous_runs, plan_segment
from drivetrack.tracks.stats import object_stats, rejection_stats, segment_stats, write_table
from drivetrack.tracks.writers import WRITERS, write_object_outputs

__all__ = [
    "TrackConfig", "FOV_RUN_POLICIES", "REJECTION_REASONS", "ObjectJob", "SegmentPlan", "plan_segment",
    "continuous_runs", "DepthStack", "SegmentContext", "prepare_segment", "object_jobs", "ObjectTracks", "run_object_job", "track_speeds",
    "object_stats", "segment_stats", "rejection_stats", "write_table", "WRITERS", "write_object_outputs",
]
