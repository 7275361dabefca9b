"""Pose refinement benchmark: tracks with and without refined boxes, against exact synthetic truth.

For each label-noise level (0, 2, 5, 10 cm centre sigma per axis with 0, 0.5, 1, 2 degrees of
heading sigma) one synthetic segment is generated (same world, same seed, only the written labels
differ), the standard pipeline runs on the labels (``baseline``) and on the labels replaced by
:func:`drivetrack.refine.refine_scene_boxes` (``refined``), and both are scored with
:func:`drivetrack.evaluate.evaluate_tracks`: occlusion accuracy (OA), average Jaccard (AJ),
delta_avg (query mode ``first``), median pixel error, purity and recall. CPU cost: process CPU
seconds of the refinement per object, and of the track stage (plan + object jobs, depth excluded)
per object for comparison.

    .venv/bin/python -m bench.run refine          # rewrites its block of docs/benchmarks.md
    .venv/bin/python bench/bench_refine.py --quick  # 2 noise levels, 24 frames, docs untouched

Generated segments are cached under ``$DRIVETRACK_BENCH_DIR`` (default ``/tmp/drivetrack-bench``).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DOC = ROOT / "docs" / "benchmarks.md"
DOC_START = "<!-- bench_refine:start -->"
DOC_END = "<!-- bench_refine:end -->"
LEVELS = ((0.0, 0.0), (0.02, 0.5), (0.05, 1.0), (0.10, 2.0))      # (centre sigma m, heading sigma deg)
SEED = 7


def _segment(root: Path, noise_m: float, noise_deg: float, frames: int) -> tuple[str, str]:
    """Generate (once) the segment of one noise level; returns (root url, segment name)."""
    from drivetrack.synth import SynthConfig, generate_segment, segment_name

    where = root / f"noise_{noise_m:.3f}m_{noise_deg:.2f}deg_{frames}f"
    name = segment_name(SEED, 0)
    done = where / "training" / "drivetrack_ground_truth" / name / "lidar_hits.npz"
    if not done.exists():
        generate_segment(str(where), SynthConfig(seed=SEED, frames=frames, preset="small", box_noise_m=noise_m,
                                                 heading_noise_rad=float(np.deg2rad(noise_deg))), 0)
    return str(where), name


def _run_pipeline(scene, config):
    """(results, cpu seconds of plan + object jobs, number of object jobs)."""
    from drivetrack.annotate import complete_depth_batch, sparse_depth_batches, track_segment
    from drivetrack.tracks import plan_segment

    plan = plan_segment(scene, config.track)
    dense = [complete_depth_batch(b, config) for b in sparse_depth_batches(scene, config, plan)]
    cpu0 = time.process_time()
    plan = plan_segment(scene, config.track)
    results = track_segment(scene, dense, config, plan)
    return results, time.process_time() - cpu0, len(plan.jobs), plan


def _scores(results, truth_root: str) -> dict:
    from drivetrack.evaluate import evaluate_tracks

    summary = evaluate_tracks(results, truth_root).summary
    first = summary["modes"].get("first", {})
    return {"OA": first.get("occlusion_accuracy", float("nan")), "AJ": first.get("average_jaccard", float("nan")),
            "delta_avg": first.get("average_pts_within_thresh", float("nan")),
            "px_median": summary.get("pixel_error_median", float("nan")),
            "purity": summary.get("purity", float("nan")), "recall": summary.get("recall", float("nan")),
            "tracks": summary.get("num_tracks", 0)}


def measure(levels=LEVELS, frames: int = 40, work: Path | None = None) -> list[dict]:
    from drivetrack.annotate import AnnotateConfig
    from drivetrack.refine import RefineConfig, refine_scene_boxes
    from drivetrack.waymo.reader import load_scene

    work = work or Path(os.environ.get("DRIVETRACK_BENCH_DIR", "/tmp/drivetrack-bench")) / "refine"
    config = AnnotateConfig()
    rows = []
    for noise_m, noise_deg in levels:
        root, segment = _segment(work, noise_m, noise_deg, frames)
        scene = load_scene(root, "training", segment, cameras=config.track.camera_values, with_images=True)
        base, base_cpu, jobs, plan = _run_pipeline(scene, config)
        objects = sorted({j.object_id for j in plan.jobs})
        cpu0 = time.process_time()
        boxes, refined = refine_scene_boxes(scene, RefineConfig(), object_ids=objects,
                                            lasers=config.track.laser_values, returns=config.track.returns)
        refine_cpu = time.process_time() - cpu0
        reasons = {}
        for r in refined.values():
            reasons[r.reason] = reasons.get(r.reason, 0) + 1
        scene_refined = dataclasses.replace(scene, boxes=boxes)
        ref, ref_cpu, ref_jobs, _ = _run_pipeline(scene_refined, config)
        row = {"noise_m": noise_m, "noise_deg": noise_deg, "objects": len(objects), "clips": jobs,
               "baseline": _scores(base, root), "refined": _scores(ref, root),
               "track_cpu_s_per_object": base_cpu / max(len(objects), 1),
               "refine_cpu_s_per_object": refine_cpu / max(len(objects), 1),
               "refine_over_track_cpu": refine_cpu / max(base_cpu, 1e-9),
               "reasons": reasons,
               "correction_p50_m": float(np.median([r.summary()["refine_translation_p50_m"] for r in refined.values()]))
               if refined else float("nan")}
        rows.append(row)
        print(json.dumps(row))
    return rows


def _table(rows: list[dict]) -> str:
    head = ("| label noise | boxes | OA | AJ | delta_avg | px error (median) | purity | recall | "
            "CPU s/object: track stage | refinement | refinement outcome |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|\n")
    lines = []
    for r in rows:
        for kind in ("baseline", "refined"):
            s = r[kind]
            label = f"{100 * r['noise_m']:.0f} cm / {r['noise_deg']:g} deg" if kind == "baseline" else ""
            if kind == "baseline":
                tail = f"{r['track_cpu_s_per_object']:.2f} | - | -"
            else:
                outcome = ", ".join(f"{k} {v}" for k, v in sorted(r["reasons"].items()))
                tail = (f"{r['track_cpu_s_per_object']:.2f} | {r['refine_cpu_s_per_object']:.2f} "
                        f"({r['refine_over_track_cpu']:.1f}x track) | {outcome}")
            lines.append(f"| {label} | {'labels' if kind == 'baseline' else 'refined'} | {s['OA']:.3f} | "
                         f"{s['AJ']:.3f} | {s['delta_avg']:.3f} | {s['px_median']:.2f} | "
                         f"{100 * s['purity']:.2f}% | {100 * s['recall']:.1f}% | {tail} |")
    return head + "\n".join(lines) + "\n"


def write_doc(rows: list[dict], machine: str, frames: int) -> None:
    block = (f"{DOC_START}\n## Pose refinement\n\n"
             f"`bench/bench_refine.py`: one synthetic segment per label-noise level (preset `small`, "
             f"{frames} frames, seed {SEED}; 480x320 images), default `TrackConfig`, default `RefineConfig`; "
             f"tracks scored against the exact truth (`drivetrack.evaluate`, query mode `first`). "
             f"Machine: {machine}; load average {os.getloadavg()[0]:.1f} at the end of the run (CPU "
             f"seconds, not wall time, are reported).\n\n" + _table(rows) + f"\n{DOC_END}")
    text = DOC.read_text() if DOC.exists() else "# Benchmarks\n"
    if DOC_START in text:
        text = re.sub(re.escape(DOC_START) + ".*?" + re.escape(DOC_END), lambda _: block, text, flags=re.S)
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    DOC.write_text(text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="two noise levels, 24 frames, docs untouched")
    args = parser.parse_args(argv if argv is not None else [])
    from bench.run import machine_description

    if args.quick:
        measure(levels=(LEVELS[0], LEVELS[2]), frames=24)
        return 0
    rows = measure()
    write_doc(rows, machine_description(), 40)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
