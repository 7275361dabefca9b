"""Pose refinement benchmark: tracks with and without refined boxes, against exact synthetic truth.

For each label-noise level (0, 2, 5, 10 cm centre sigma per axis with 0, 0.5, 1, 2 degrees of
heading sigma) one synthetic segment is generated (same world, same seed, only the written labels
differ), the standard pipeline runs on the labels (``baseline``) and on the boxes of
:func:`drivetrack.annotate.refine_scene` (``drivetrack.refine.refine_scene_boxes``) with 4 degrees of freedom per frame (``refined_4dof``:
centre and heading, ``RefineConfig(pitch_roll_sigma_deg=None)``) and with 6 (``refined``: and
pitch, roll; the default), and all are scored with
:func:`drivetrack.evaluation.evaluate_tracks`: occlusion accuracy (OA), average Jaccard (AJ),
delta_avg (query mode ``first``), median pixel error, purity and recall. CPU cost: process CPU
seconds of the refinement as the pipeline pays it (:func:`drivetrack.annotate.refine_scene`: its
plan without point selection to pick the objects, the candidate gather and the solves) per object,
and of the track stage (plan with point selection + object jobs, depth excluded) per object for
comparison, both in the same process.

    .venv/bin/python -m bench.run refine          # all three tables; rewrites its block of docs/benchmarks.md
    .venv/bin/python bench/bench_refine.py --quick  # 2 noise levels, 24 frames, docs untouched
    .venv/bin/python bench/bench_refine.py --small-only   # the small-preset table only
    .venv/bin/python bench/bench_refine.py --full-only    # the full-size segment only, docs untouched

The small-preset segments are cached under ``$DRIVETRACK_BENCH_DIR`` (default
``/tmp/drivetrack-bench``); the full-size (1920x1280) and ``medium`` (960x640, the same lidars)
segments under ``.bench-cache/`` (several CPU-minutes each the first time).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
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
#: refined variants: name -> RefineConfig overrides
VARIANTS = {"refined_4dof": {"pitch_roll_sigma_deg": None}, "refined": {}}


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
    from drivetrack.evaluation import evaluate_tracks

    summary = evaluate_tracks(results, truth_root).summary
    first = summary["modes"].get("first", {})
    return {"OA": first.get("occlusion_accuracy", float("nan")), "AJ": first.get("average_jaccard", float("nan")),
            "delta_avg": first.get("average_pts_within_thresh", float("nan")),
            "px_median": summary.get("pixel_error_median", float("nan")),
            "purity": summary.get("purity", float("nan")), "recall": summary.get("recall", float("nan")),
            "tracks": summary.get("num_tracks", 0)}


def _refine_timed(scene, config, overrides: dict):
    """(refined scene, CPU seconds, solve CPU seconds, {reason: count}, iterations, max tilt deg):
    exactly what the pipeline runs, ``annotate.refine_scene``, with the variant's ``RefineConfig``
    overrides."""
    from drivetrack.annotate import refine_scene

    config = dataclasses.replace(config, refine_options={**config.refine_options, **overrides})
    cpu0 = time.process_time()
    refined = refine_scene(scene, config)
    cpu = time.process_time() - cpu0
    summaries = list(refined.box_refinement.values())
    reasons: dict = {}
    for r in summaries:
        reasons[r["refine_reason"]] = reasons.get(r["refine_reason"], 0) + 1
    return (refined, cpu, sum(r["refine_cpu_seconds"] for r in summaries), reasons,
            [r["refine_iterations"] for r in summaries], max([r["refine_tilt_max_deg"] for r in summaries], default=0.0))


def measure(levels=LEVELS, frames: int = 40, work: Path | None = None) -> list[dict]:
    from drivetrack.annotate import AnnotateConfig
    from drivetrack.waymo.reader import load_scene

    work = work or Path(os.environ.get("DRIVETRACK_BENCH_DIR", "/tmp/drivetrack-bench")) / "refine"
    config = AnnotateConfig()
    rows = []
    # warm-up, untimed: imports, numba kernels loaded from their cache, first-call costs of the
    # track stage; on the noisiest level, where every refinement kernel runs
    root, segment = _segment(work, *levels[-1], frames)
    scene = load_scene(root, "training", segment, cameras=config.track.camera_values, with_images=True)
    _run_pipeline(scene, config)
    for overrides in VARIANTS.values():
        _refine_timed(scene, config, overrides)
    for noise_m, noise_deg in levels:
        root, segment = _segment(work, noise_m, noise_deg, frames)
        scene = load_scene(root, "training", segment, cameras=config.track.camera_values, with_images=True)
        base, base_cpu, jobs, plan = _run_pipeline(scene, config)
        objects = sorted({j.object_id for j in plan.jobs})
        row = {"noise_m": noise_m, "noise_deg": noise_deg, "objects": len(objects), "clips": jobs,
               "baseline": _scores(base, root), "track_cpu_s_per_object": base_cpu / max(len(objects), 1)}
        for variant, overrides in VARIANTS.items():
            # the refinement as the pipeline pays it: annotate.refine_scene (its own plan without
            # point selection picks the objects, then the gather and the solves)
            scene_refined, refine_cpu, solve_cpu, reasons, iterations, tilt = _refine_timed(scene, config, overrides)
            ref, ref_cpu, ref_jobs, _ = _run_pipeline(scene_refined, config)
            row[variant] = _scores(ref, root)
            row[variant].update(
                refine_cpu_s_per_object=refine_cpu / max(len(objects), 1), refine_solve_cpu_s=solve_cpu,
                refine_over_track_cpu=refine_cpu / max(base_cpu, 1e-9), reasons=reasons, iterations=iterations,
                refined_objects=len(scene_refined.box_refinement), tilt_max_deg=tilt)
        rows.append(row)
        print(json.dumps(row))
    return rows


def measure_full(noises=(0.0, 0.05), frames: int = 30, seed: int = SEED, cache: Path | None = None,
                 preset: str = "full") -> dict:
    """The full-size segment of ``bench/bench_tracks.py`` (preset ``full``, 1920x1280, or
    ``medium``, 960x640 with the same lidars; cached by ``ensure_source``), its labels with
    ``noisy_scene``'s noise (each of ``noises``, metres; 1 deg
    per 5 cm), tracked with the labels and with the boxes of every refinement variant
    (:data:`VARIANTS`); the track stage and the refinement timed in this process.

    Track stage CPU = ``plan_segment`` + ``prepare_segment`` (maps given) + the object jobs, as in the
    small-preset table; its object jobs alone are reported too (``bench_tracks``' "track CPU s").
    Refinement CPU = ``annotate.refine_scene`` itself, timed whole (its own ``plan_segment`` without
    point selection to pick the objects + ``refine_scene_boxes``: candidate gather + per-object
    solves); the split reports the solves (their own CPU seconds) and that plan, timed once more
    on its own; the gather is the rest."""
    from bench.bench_tracks import SPLIT, depth_for, ensure_source, noisy_scene, track_stage
    from drivetrack.annotate import AnnotateConfig, load_scene_for
    from drivetrack.evaluation import evaluate_tracks
    from drivetrack.tracks import plan_segment, prepare_segment

    cache = cache or ROOT / ".bench-cache"
    root, segment = ensure_source(cache, preset, seed, frames)
    config = AnnotateConfig()
    track = config.track
    scene = load_scene_for(root, SPLIT, segment, config, refine=False)
    model = next(iter(scene.cameras.values())).model
    out = {"preset": preset, "frames": frames, "seed": seed, "lidar_returns": len(scene.lidar), "levels": [],
           "image": f"{model.width}x{model.height}"}
    truths: dict = {}
    depth = None
    for noise_m in noises:
        noisy = noisy_scene(scene, noise_m, seed)
        level = {"noise_m": noise_m}
        scenes = {"labels": noisy}
        # the plan annotate.refine_scene runs to pick the objects (no point selection), timed on its
        # own for the split below
        c0 = time.process_time()
        objects = sorted({job.object_id for job in plan_segment(noisy, track, select_points=False).jobs})
        plan_cpu = time.process_time() - c0
        level["objects"] = len(objects)
        for variant, overrides in VARIANTS.items():
            refined, total, solve, reasons, iterations, tilt = _refine_timed(noisy, config, overrides)
            scenes[variant] = dataclasses.replace(noisy, boxes=refined.boxes)
            level[variant] = dict(
                refine_plan_cpu_s=plan_cpu, refine_solve_cpu_s=solve,
                refine_gather_cpu_s=max(total - plan_cpu - solve, 0.0), refine_cpu_s=total,
                reasons=reasons, iterations=iterations, tilt_max_deg=tilt)
        if depth is None:       # maps depend on the LiDAR only: one set for every level and variant
            depth, _, _ = depth_for(scene, track, [plan_segment(s, track) for s in scenes.values()])
        for kind, s in scenes.items():
            c0 = time.process_time()
            ctx = prepare_segment(s, track, depth=depth, plan=plan_segment(s, track))
            c1 = time.process_time()
            tracks, jobs_cpu, _, annotations = track_stage(ctx)
            entry = level.setdefault(kind, {})
            entry.update(track_cpu_s=(c1 - c0) + jobs_cpu, track_jobs_cpu_s=jobs_cpu, clips=len(ctx.plan.jobs))
            summary = evaluate_tracks(tracks, root, truths=truths).summary
            first = summary["modes"].get("first", {})
            entry.update({"OA": first.get("occlusion_accuracy", float("nan")),
                          "AJ": first.get("average_jaccard", float("nan")),
                          "delta_avg": first.get("average_pts_within_thresh", float("nan")),
                          "px_median": summary.get("pixel_error_median", float("nan")),
                          "purity": summary.get("purity", float("nan")), "recall": summary.get("recall", float("nan")),
                          "tracks": summary.get("num_tracks", 0)})
            del ctx, tracks
        for variant in VARIANTS:
            level[variant]["refine_over_track_cpu"] = (level[variant]["refine_cpu_s"]
                                                       / max(level["labels"]["track_cpu_s"], 1e-9))
        out["levels"].append(level)
        print(json.dumps(level), flush=True)
    return out


def _full_table(r: dict) -> str:
    head = ("| label noise | boxes | OA | AJ | delta_avg | px error (median) | purity | recall | track stage CPU s "
            "(jobs only) | refinement CPU s: total = plan + gather + solves | refinement outcome |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|\n")
    names = {"labels": "labels", "refined_4dof": "refined, 4 DOF", "refined": "refined, 6 DOF"}
    lines = []
    for level in r["levels"]:
        n = max(level["objects"], 1)
        for kind in ("labels", *VARIANTS):
            s = level[kind]
            noise = f"{100 * level['noise_m']:.0f} cm / {level['noise_m'] / 0.05:g} deg" if kind == "labels" else ""
            if kind == "labels":
                refine, outcome = "-", "-"
            else:
                refine = (f"{s['refine_cpu_s']:.2f} = {s['refine_plan_cpu_s']:.2f} + {s['refine_gather_cpu_s']:.2f} + "
                          f"{s['refine_solve_cpu_s']:.2f} ({s['refine_cpu_s'] / n:.2f}/object; "
                          f"{s['refine_over_track_cpu']:.1f}x track stage)")
                outcome = (", ".join(f"{k} {v}" for k, v in sorted(s["reasons"].items()))
                           + f"; iterations {s['iterations']}")
            lines.append(f"| {noise} | {names[kind]} | {s['OA']:.3f} | {s['AJ']:.3f} | {s['delta_avg']:.3f} | "
                         f"{s['px_median']:.2f} | {100 * s['purity']:.2f}% | {100 * s['recall']:.1f}% | "
                         f"{s['track_cpu_s']:.2f} ({s['track_jobs_cpu_s']:.2f}) | {refine} | {outcome} |")
    return head + "\n".join(lines) + "\n"


def _table(rows: list[dict]) -> str:
    head = ("| label noise | boxes | OA | AJ | delta_avg | px error (median) | purity | recall | "
            "CPU s/object (segment): track stage | refinement | refinement outcome |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|\n")
    lines = []
    names = {"baseline": "labels", "refined_4dof": "refined, 4 DOF", "refined": "refined, 6 DOF"}
    for r in rows:
        for kind in ("baseline", *VARIANTS):
            s = r[kind]
            label = f"{100 * r['noise_m']:.0f} cm / {r['noise_deg']:g} deg" if kind == "baseline" else ""
            n = max(r["objects"], 1)
            track = f"{r['track_cpu_s_per_object']:.3f} ({r['track_cpu_s_per_object'] * n:.2f})"
            if kind == "baseline":
                tail = f"{track} | - | -"
            else:
                outcome = (", ".join(f"{k} {v}" for k, v in sorted(s["reasons"].items()))
                           + f"; iterations {s['iterations']}")
                tail = (f"{track} | {s['refine_cpu_s_per_object']:.3f} ({s['refine_cpu_s_per_object'] * n:.2f}; "
                        f"{s['refine_over_track_cpu']:.1f}x track) | {outcome}")
            lines.append(f"| {label} | {names[kind]} | {s['OA']:.3f} | "
                         f"{s['AJ']:.3f} | {s['delta_avg']:.3f} | {s['px_median']:.2f} | "
                         f"{100 * s['purity']:.2f}% | {100 * s['recall']:.1f}% | {tail} |")
    return head + "\n".join(lines) + "\n"


def write_doc(rows: list[dict], machine: str, frames: int, full: dict | None = None,
              medium: dict | None = None) -> None:
    block = (f"{DOC_START}\n## Pose refinement\n\n"
             f"`bench/bench_refine.py`: one synthetic segment per label-noise level (preset `small`, "
             f"{frames} frames, seed {SEED}; 480x320 images), default `TrackConfig`, default `RefineConfig`; "
             f"tracks scored against the exact truth (`drivetrack.evaluation`, query mode `first`). "
             f"CPU seconds (`time.process_time`) of the track stage (plan + object jobs, depth maps excluded) and "
             f"of the refinement as the pipeline runs it (`annotate.refine_scene`: its plan without point "
             f"selection, the candidate gather, the solves), in the same process. Machine: {machine}; load average {os.getloadavg()[0]:.1f} at the end of the run (CPU "
             f"seconds, not wall time, are reported).\n\n" + _table(rows))
    if full is not None:
        block += (f"\nFull-size segment (`bench_tracks`' cached preset `full`, "
                  f"{full['frames']} frames, seed {full['seed']}, 1920x1280, {full['lidar_returns'] / 1e6:.1f} M "
                  f"returns, {full['levels'][0]['objects']} annotated objects), labels exact and with noise "
                  f"(`bench_tracks.noisy_scene`), default `AnnotateConfig`; track stage = plan + prepare (maps "
                  f"given) + object jobs; refinement = `annotate.refine_scene` timed whole (split: its plan without "
                  f"point selection, timed again on its own; the gather = the rest; the solves):"
                  f"\n\n" + _full_table(full))
    if medium is not None:
        block += (f"\nThe same at 960x640 (preset `medium`, the full-size lidars with "
                  f"cameras at half Waymo's resolution, the resolution of the label-noise reference figures (released method, 5 cm / 1 deg labels: ~6 px median error, AJ 0.36); "
                  f"{medium['frames']} frames, seed {medium['seed']}, {medium['lidar_returns'] / 1e6:.1f} M returns, "
                  f"{medium['levels'][0]['objects']} annotated objects):\n\n" + _full_table(medium))
    block += f"\n{DOC_END}"
    _replace_block(block)


def _replace_block(block: str) -> None:
    """Replace this benchmark's block of docs/benchmarks.md only (bench.run.replace_doc_block)."""
    from bench.run import replace_doc_block

    replace_doc_block(DOC, DOC_START, DOC_END, block)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="two noise levels, 24 frames, docs untouched")
    parser.add_argument("--small-only", action="store_true",
                        help="only the small-preset table (the block of docs/benchmarks.md then lacks the others)")
    parser.add_argument("--full-only", action="store_true", help="only the full-size segment, docs untouched")
    args = parser.parse_args(argv if argv is not None else [])
    from bench.run import machine_description

    if args.quick:
        measure(levels=(LEVELS[0], LEVELS[2]), frames=24)
        return 0
    if args.full_only:
        measure_full()
        return 0
    rows = measure()
    full = None if args.small_only else measure_full()
    medium = None if args.small_only else measure_full(preset="medium")
    write_doc(rows, machine_description(), 40, full, medium)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
