"""Ours vs the original's emulation on the clips BOTH annotate (like for like), full-size segment.

bench_tracks compares each method on its own clip set (the original's 50 m filter admits a sixth,
farther clip); this script scores both on the common (camera, object) clips only, against the
exact synthetic truth, TAP-Vid query mode ``first``, for one or more settings of the depth maps'
see-through filter (``TrackConfig.see_through_window_deg`` / ``see_through_min_quadrants``):

    .venv/bin/python bench/common_clips.py                 # the default TrackConfig
    .venv/bin/python bench/common_clips.py none,3 0.5,3 1.0,3 0.5,3,top

Each argument is ``WINDOW_DEG|none,MIN_QUADRANTS[,top][,noblind]`` (``top``: depth maps from the
TOP LiDAR only; ``noblind``: no blind-zone bound, ``TrackConfig.blind_zone_laser=None``). Uses
bench_tracks' cached full-size segment (``.bench-cache/``; generated on first use).
Pose refinement is off (exact labels).
"""
from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def main(argv: list[str]) -> int:
    from bench.baseline_original import original_clips
    from bench.bench_tracks import SPLIT, ensure_source
    from drivetrack.annotate import (AnnotateConfig, complete_depth_batch, load_scene_for, sparse_depth_batches,
                                     track_segment)
    from drivetrack.evaluation import evaluate_clips, evaluate_tracks
    from drivetrack.tracks import TrackConfig, plan_segment

    root, segment = ensure_source(ROOT / ".bench-cache", "full", 7, 30)
    base = AnnotateConfig(refine_poses=False)
    scene = load_scene_for(root, SPLIT, segment, base, refine=False)
    truths: dict = {}
    original = evaluate_clips(original_clips(scene), root, truths=truths).clips
    key = ["segment", "camera", "object_id", "query_mode"]

    def line(name, clips):
        first = clips[clips.query_mode == "first"]
        per_clip = " ".join(f"{o[:6]}:{a:.3f}" for o, a in zip(first.object_id, first.occlusion_accuracy))
        return (f"{name:34s} clips {len(first)} OA {first.occlusion_accuracy.mean():.4f} "
                f"AJ {first.average_jaccard.mean():.4f} delta_avg {first.average_pts_within_thresh.mean():.4f} | {per_clip}")

    for setting in (argv or ["default"]):
        if setting == "default":
            track = TrackConfig()
        else:
            window, quadrants, *rest = setting.split(",")
            track = TrackConfig(see_through_window_deg=None if window == "none" else float(window),
                                see_through_min_quadrants=int(quadrants),
                                **({"depth_lasers": ("TOP",)} if "top" in rest else {}),
                                **({"blind_zone_laser": None} if "noblind" in rest else {}))
        config = replace(base, track=track)
        plan = plan_segment(scene, track)
        dense = [complete_depth_batch(b, config) for b in sparse_depth_batches(scene, config, plan)]
        ours = evaluate_tracks([t for t in track_segment(scene, dense, config, plan) if t.rejection is None],
                               root, truths=truths).clips
        common = ours.merge(original[key], on=key)[key]
        print(line(f"ours ({setting})", ours.merge(common, on=key)), flush=True)
        print(line("original (emulated)", original.merge(common, on=key)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
