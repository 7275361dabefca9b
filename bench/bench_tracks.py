"""Track stage benchmark: annotations per CPU-second, object-job memory, accuracy vs exact truth.

On a synthetic segment (``--preset full``: 1920x1280 cameras, Waymo-size LiDAR; generating one
takes many CPU-minutes, so it is cached under ``.bench-cache/``; ``--frames`` keeps it short):

- speed: annotations (one track point in one frame, occlusion included) per CPU-second of the
  track stage (``run_object_job`` over every accepted clip; planning and depth excluded), target
  >= 10 million; if missed, a cProfile of the largest job names the hot spots;
- memory: tracemalloc peak of the largest object job beyond the shared segment context (scene,
  depth maps), measured at this clip length and extrapolated to a 200-frame clip (target < 1 GiB);
- accuracy against the exact truth (``drivetrack.evaluate``): OA, AJ, delta_avg (query mode
  ``first`` and ``strided``), pixel error, purity, recall, for each depth completer, without and
  with box noise (sigma ``--box-noise`` m on centres, 1 degree per 5 cm on headings, applied to the
  loaded labels exactly as ``drivetrack synth --box-noise`` applies it to the written ones: the
  world, LiDAR and truth are unchanged), and for ``bench/baseline_original.py`` (the original
  script's choices) on the same scenes.

Depth maps per CPU-second at 1920x1280 are measured by ``bench/bench_depth.py`` (not repeated).

    .venv/bin/python -m bench.run tracks                      # full preset, 30 frames, updates docs
    .venv/bin/python bench/bench_tracks.py --quick --no-docs  # small preset smoke run
"""
from __future__ import annotations

import argparse
import cProfile
import io
import json
import math
import pstats
import re
import sys
import time
import tracemalloc
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.baseline_original import original_clips  # noqa: E402
from bench.run import machine_description  # noqa: E402
from drivetrack.annotate import AnnotateConfig, load_scene_for, refine_scene  # noqa: E402
from drivetrack.evaluate import evaluate_clips, evaluate_tracks  # noqa: E402
from drivetrack.tracks import (TrackConfig, complete_depth, depth_jobs, plan_segment, prepare_segment,  # noqa: E402
                               run_object_job, sparse_depth)

DOC = ROOT / "docs" / "benchmarks.md"
DOC_START, DOC_END = "<!-- bench_tracks:start -->", "<!-- bench_tracks:end -->"
TARGET_ANNOTATIONS_PER_CPU_S = 10e6
TARGET_JOB_BYTES = 1 << 30
SPLIT = "training"


def ensure_source(cache: Path, preset: str, seed: int, frames: int) -> tuple[str, str]:
    """(root, segment) of a cached synthetic segment, generated when absent."""
    from drivetrack.synth import SynthConfig, generate_segment, segment_name

    root = cache / f"synth_{preset}_s{seed}_f{frames}"
    segment = segment_name(seed, 0)
    done = root / SPLIT / "drivetrack_ground_truth" / segment / "lidar_hits.npz"
    if not done.exists():
        print(f"generating {preset} segment ({frames} frames) into {root} (cached for later runs) ...", flush=True)
        start = time.process_time()
        generate_segment(str(root), SynthConfig(seed=seed, frames=frames, preset=preset), 0)
        print(f"  generated in {time.process_time() - start:.0f} CPU s", flush=True)
    return str(root), segment


def noisy_scene(scene, sigma_m: float, seed: int):
    """The scene with Gaussian noise on its box labels (centre sigma_m per axis, heading 1 deg per 5 cm)."""
    if sigma_m <= 0:
        return scene
    rng = np.random.default_rng([seed, 5005])
    boxes = scene.boxes
    center = boxes.center + rng.normal(0.0, sigma_m, size=boxes.center.shape)
    heading = boxes.heading + rng.normal(0.0, np.deg2rad(1.0) * sigma_m / 0.05, size=boxes.heading.shape)
    return replace(scene, boxes=replace(boxes, center=center, heading=heading))


def depth_for(scene, config: TrackConfig, plans) -> tuple[dict, float, int]:
    """Completed maps for every frame any of ``plans`` needs: camera -> (frames, maps); CPU s; count."""
    needed: dict[int, set] = {}
    for plan in plans:
        for job in depth_jobs(scene, config, plan):
            needed.setdefault(job.camera, set()).update(job.frames.tolist())
    out, cpu, count = {}, 0.0, 0
    from drivetrack.tracks.depth_stage import DepthJob
    for camera, frames in sorted(needed.items()):
        frames = np.array(sorted(frames), dtype=np.int64)
        parts = []
        for start in range(0, frames.size, config.depth_batch):
            job = DepthJob(camera, frames[start:start + config.depth_batch])
            sparse = sparse_depth(scene, config, job)
            c0 = time.process_time()
            parts.append(complete_depth(sparse, config))
            cpu += time.process_time() - c0
        out[camera] = (frames, np.concatenate(parts))
        count += frames.size
    return out, cpu, count


def track_stage(ctx) -> tuple[list, float, float, int]:
    """Run every job: (results, CPU s, wall s, annotations = sum of N x T)."""
    c0, w0 = time.process_time(), time.perf_counter()
    results = [run_object_job(ctx, job) for job in ctx.plan.jobs]
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    return results, cpu, wall, int(sum(r.num_tracks * r.num_frames for r in results))


def _job_peak(ctx, job, max_tracks: int | None) -> tuple[int, int]:
    """(tracemalloc peak bytes beyond what exists before the job, tracks kept) of one job."""
    from drivetrack.tracks.depth_stage import SegmentContext

    plan = replace(ctx.plan, config=replace(ctx.plan.config, max_tracks_per_object=max_tracks))
    sub = SegmentContext(plan, ctx.depth)
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    tracemalloc.reset_peak()
    result = run_object_job(sub, job)
    peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    return int(peak), result.num_tracks


def job_memory(ctx) -> dict:
    """Peak memory of the largest job (by candidate points x frames), beyond the shared context.

    Measured with tracemalloc (numpy reports its buffers to it) at all N candidate points and at
    N/2 (a seeded subset): peak = fixed(T) + per_point_frame * N * T, solved from the two runs.
    Extrapolated to a 200-frame clip of the same object with N growing in proportion to T.
    """
    job = max(ctx.plan.jobs, key=lambda j: j.num_points * j.frames.size)
    n, t = job.num_points, int(job.frames.size)
    peak_full, kept = _job_peak(ctx, job, None)
    peak_half, _ = _job_peak(ctx, job, max(n // 2, 1))
    per_point_frame = (peak_full - peak_half) / max((n - max(n // 2, 1)) * t, 1)
    fixed = max(peak_full - per_point_frame * n * t, 0.0)
    points_per_frame = n / t
    n200 = points_per_frame * 200
    return {"camera": job.camera_name, "object_id": job.object_id, "frames": t, "candidates": n,
            "tracks": kept, "peak_bytes": peak_full, "peak_bytes_half": peak_half,
            "bytes_per_point_frame": per_point_frame, "fixed_bytes": fixed,
            "extrapolated_200_frames_bytes": int(fixed * 200 / t + per_point_frame * n200 * 200),
            "points_per_frame": points_per_frame}


def profile_job(ctx, top: int = 8) -> list[str]:
    job = max(ctx.plan.jobs, key=lambda j: j.num_points * j.frames.size)
    profiler = cProfile.Profile()
    profiler.enable()
    run_object_job(ctx, job)
    profiler.disable()
    stream = io.StringIO()
    stats = pstats.Stats(profiler, stream=stream).sort_stats("tottime")
    total = sum(v[2] for v in stats.stats.values())
    lines = []
    for (file, line, name), (_, calls, tottime, _, _) in sorted(stats.stats.items(), key=lambda kv: -kv[1][2])[:top]:
        lines.append(f"{name} ({Path(file).name}:{line}) {tottime:.2f} s = {100 * tottime / total:.0f}%, {calls} calls")
    return lines


def accuracy_row(label: str, evaluation, extra: dict) -> dict:
    s = evaluation.summary
    row = {"label": label, **extra, "clips": s["num_clips"], "tracks": s["num_tracks"], "purity": s.get("purity"),
           "recall": s.get("recall"), "px_median": s["pixel_error_median"], "px_mean": s["pixel_error_mean"]}
    for mode in ("first", "strided"):
        m = s["modes"].get(mode, {})
        row[f"{mode}_oa"] = m.get("occlusion_accuracy")
        row[f"{mode}_aj"] = m.get("average_jaccard")
        row[f"{mode}_delta"] = m.get("average_pts_within_thresh")
    return row


def run(preset: str, frames: int, seed: int, cache: Path, methods: list[str], box_noise: float,
        baseline: bool, top_first_variant: bool = True) -> dict:
    root, segment = ensure_source(cache, preset, seed, frames)
    base_config = AnnotateConfig()
    # labels as read (refinement is measured separately below, on exact and on noisy labels)
    scene = load_scene_for(root, SPLIT, segment, base_config, refine=False)
    model = scene.cameras[min(scene.cameras)].model
    results = {"machine": machine_description(), "preset": preset, "frames": frames, "seed": seed,
               "segment": segment, "image": f"{model.width}x{model.height}", "box_noise_m": box_noise,
               "lidar_returns": len(scene.lidar), "speed": [], "accuracy": []}
    truths: dict = {}      # the exact truth, loaded once (about 1 GiB for a full-size 30-frame segment)
    scenes = {0.0: scene, box_noise: noisy_scene(scene, box_noise, seed)} if box_noise > 0 else {0.0: scene}
    for method in methods:
        options = {"device": "cpu"} if method == "nearest-torch" else {}
        track = TrackConfig(depth_completer=method, depth_completer_options=options)
        plans = {noise: plan_segment(s, track) for noise, s in scenes.items()}
        depth, depth_cpu, maps = depth_for(scene, track, plans.values())
        print(f"{method}: {maps} depth maps in {depth_cpu:.1f} CPU s", flush=True)
        for noise, s in scenes.items():
            ctx = prepare_segment(s, track, depth=depth, plan=plans[noise])
            tracks, cpu, wall, annotations = track_stage(ctx)
            rate = annotations / cpu if cpu > 0 else math.nan
            results["speed"].append({"method": method, "box_noise_m": noise, "jobs": len(ctx.plan.jobs),
                                     "annotations": annotations, "track_cpu_s": cpu, "track_wall_s": wall,
                                     "annotations_per_cpu_s": rate, "depth_maps": maps,
                                     "depth_cpu_s_per_map": depth_cpu / max(maps, 1)})
            print(f"  noise {noise}: {len(tracks)} clips, {annotations:,} annotations in {cpu:.1f} CPU s "
                  f"({rate / 1e6:.2f} M/CPU-s)", flush=True)
            evaluation = evaluate_tracks(tracks, root, truths=truths)
            results["accuracy"].append(accuracy_row(f"ours, {method}", evaluation, {"box_noise_m": noise}))
            print("   ", {k: (round(v, 4) if isinstance(v, float) else v)
                          for k, v in results["accuracy"][-1].items()}, flush=True)
            if method == methods[0] and noise == 0.0:
                results["memory"] = job_memory(ctx)
                print("  memory:", results["memory"], flush=True)
                if rate < TARGET_ANNOTATIONS_PER_CPU_S:
                    results["profile"] = profile_job(ctx)
                    print("  profile:", *results["profile"], sep="\n    ", flush=True)
            del ctx, tracks
        if top_first_variant and method == methods[0]:
            # like for like with the original: the same track stage on TOP first returns only; and
            # occlusion depth maps without second returns (they sit at object edges and carry the
            # surface behind them into the completed map)
            for noise, s in scenes.items():
                start = time.process_time()
                refined = refine_scene(s, replace(base_config, track=track))
                refine_cpu = time.process_time() - start
                ctx = prepare_segment(refined, track, depth=None, plan=plan_segment(refined, track))
                tracks, cpu, _, annotations = track_stage(ctx)
                results["accuracy"].append(accuracy_row(
                    f"ours, {method}, refined poses", evaluate_tracks(tracks, root, truths=truths),
                    {"box_noise_m": noise, "refine_cpu_s": refine_cpu, "track_cpu_s": cpu}))
                print("   ", results["accuracy"][-1], flush=True)
                del ctx, tracks
            variants = ((f"ours, {method}, TOP first return only", replace(track, lasers=("TOP",), returns=(1,)), True),
                        (f"ours, {method}, both returns in the depth maps",
                         replace(track, depth_returns=(1, 2)), False))
            for label, variant, shared_depth in variants:
                for noise, s in scenes.items():
                    plan = plan_segment(s, variant)
                    ctx = prepare_segment(s, variant, depth=depth if shared_depth else None, plan=plan)
                    tracks, *_ = track_stage(ctx)
                    results["accuracy"].append(accuracy_row(label, evaluate_tracks(tracks, root, truths=truths),
                                                            {"box_noise_m": noise}))
                    print("   ", results["accuracy"][-1], flush=True)
                    del ctx, tracks
        del depth
    if baseline:
        maps: dict = {}
        for noise, s in scenes.items():
            timings: dict = {}
            clips = original_clips(s, timings=timings, depth_maps=maps)
            evaluation = evaluate_clips(clips, root, truths=truths)
            results["accuracy"].append(accuracy_row("original (emulated)", evaluation,
                                                    {"box_noise_m": noise, **timings}))
            print("   ", results["accuracy"][-1], flush=True)
    return results


def _f(value, digits=3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}f}"


def markdown(r: dict) -> str:
    lines = [f"Machine: {r['machine']}; load average at start {r.get('load', '?')}.",
             f"Scene: `--preset {r['preset']} --frames {r['frames']} --seed {r['seed']}` ({r['image']} cameras, "
             f"{r['lidar_returns']:,} LiDAR returns), segment `{r['segment']}`.", "",
             "| depth | box noise | clips | annotations | track CPU s | annotations / CPU-s | depth CPU s / map |",
             "|---|---|---|---|---|---|---|"]
    for s in r["speed"]:
        lines.append(f"| {s['method']} | {s['box_noise_m']} m | {s['jobs']} | {s['annotations']:,} | "
                     f"{s['track_cpu_s']:.1f} | {s['annotations_per_cpu_s'] / 1e6:.2f} M | {s['depth_cpu_s_per_map']:.2f} |")
    m = r.get("memory")
    if m:
        lines += ["", f"Largest object job ({m['camera']}, {m['candidates']:,} candidate points x {m['frames']} frames, "
                      f"{m['tracks']:,} tracks kept): tracemalloc peak **{m['peak_bytes'] / 2**20:.0f} MiB** beyond the "
                      f"shared segment context (measured; {m['peak_bytes_half'] / 2**20:.0f} MiB with half the points), "
                      f"i.e. {m['fixed_bytes'] / 2**20:.0f} MiB of chunk temporaries + {m['bytes_per_point_frame']:.0f} "
                      f"bytes per candidate point and frame. Extrapolated to a 200-frame clip of the same object ({m['points_per_frame']:.0f} "
                      f"points per frame, so N x T grows with T^2): **{m['extrapolated_200_frames_bytes'] / 2**30:.1f} GiB** "
                      f"(extrapolation, not a measurement)."]
    if r.get("profile"):
        lines += ["", "Hot spots of the largest job (cProfile, self time):", ""]
        lines += [f"- {p}" for p in r["profile"]]
    lines += ["", "Accuracy against the exact truth (TAP-Vid at the native resolution; OA / AJ / delta_avg averaged "
                  "over clips; purity, recall and pixel error pooled over tracks):", "",
              "| method | box noise | clips | tracks | OA first | AJ first | δ_avg first | OA strided | AJ strided | "
              "δ_avg strided | px median | px mean | purity | recall |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for a in r["accuracy"]:
        lines.append(f"| {a['label']} | {a['box_noise_m']} m | {a['clips']} | {a['tracks']:,} | {_f(a['first_oa'])} | "
                     f"{_f(a['first_aj'])} | {_f(a['first_delta'])} | {_f(a['strided_oa'])} | {_f(a['strided_aj'])} | "
                     f"{_f(a['strided_delta'])} | {_f(a['px_median'], 2)} | {_f(a['px_mean'], 2)} | "
                     f"{_f(a['purity'], 4)} | {_f(a['recall'])} |")
    return "\n".join(lines)


def update_docs(text: str) -> None:
    doc = DOC.read_text()
    block = f"{DOC_START}\n{text}\n{DOC_END}"
    if DOC_START in doc and DOC_END in doc:
        doc = re.sub(re.escape(DOC_START) + r".*?" + re.escape(DOC_END), lambda _: block, doc, flags=re.S)
    else:
        doc = doc.rstrip("\n") + "\n\n## Track stage and accuracy\n\n" + block + "\n"
    DOC.write_text(doc)


def main(argv: list[str] | None = None) -> int:
    import os

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="full", choices=["small", "full"])
    parser.add_argument("--frames", type=int, default=30,
                        help="segment length (>= 24 for a clip to pass the paper's filter; default 30: "
                             "a full-size segment of 200 frames takes hours to generate on 2 cores)")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--cache", default=str(ROOT / ".bench-cache"))
    parser.add_argument("--methods", default="nearest,ipbasic,nearest-torch")
    parser.add_argument("--box-noise", type=float, default=0.05)
    parser.add_argument("--no-baseline", action="store_true")
    parser.add_argument("--quick", action="store_true", help="small preset (smoke run)")
    parser.add_argument("--no-docs", action="store_true", help="do not rewrite docs/benchmarks.md")
    parser.add_argument("--json", default=None, help="also write the raw results to this file")
    parser.add_argument("--render", nargs="+", default=None, metavar="JSON",
                        help="no run: merge the --json results of runs (e.g. one per depth method, run in "
                             "parallel) and print / write the section")
    args = parser.parse_args(argv if argv is not None else [])
    if args.render:
        parts = [json.loads(Path(p).read_text()) for p in args.render]
        results = parts[0]
        for part in parts[1:]:       # first occurrence of a (method, noise) row wins
            seen = {(r["method"], r["box_noise_m"]) for r in results["speed"]}
            results["speed"] += [r for r in part["speed"] if (r["method"], r["box_noise_m"]) not in seen]
            seen = {(r["label"], r["box_noise_m"]) for r in results["accuracy"]}
            results["accuracy"] += [r for r in part["accuracy"] if (r["label"], r["box_noise_m"]) not in seen]
            results.setdefault("memory", part.get("memory"))
            results.setdefault("profile", part.get("profile"))
        text = markdown(results)
        print(text)
        if not args.no_docs:
            update_docs(text)
        return 0
    preset = "small" if args.quick else args.preset
    load = os.getloadavg()[0]
    results = run(preset, args.frames, args.seed, Path(args.cache), [m for m in args.methods.split(",") if m],
                  args.box_noise, not args.no_baseline)
    results["load"] = f"{load:.1f}"
    text = markdown(results)
    print(text)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=float))
    if not args.no_docs and not args.quick:
        update_docs(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
