"""Shared by the benchmarks that compare refinement settings on small noisy-label worlds
(``bench_slip``, ``bench_sampling``): generate the worlds, annotate each with every setting,
score the tracks against the exact truth with ``bench_visibility``'s clip selection, and write
one table (a world per row, a setting per column) to docs/benchmarks.md. Not a benchmark itself
(its name does not start with ``bench_``)."""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "benchmarks.md"

#: (label, SynthConfig options) of the worlds of one seed: movers on their box centres and on
#: their rear axles (a centre slips sideways on a turn, as a real car's does)
BOX_WORLDS = (("box centres", {}), ("rear axles", {"rear_axle_fraction": 0.3}))
#: cars shaped as a body and a cabin (their side faces show edges along the road)
CABIN_WORLDS = (("cabin cars", {"car_shape": "cabin"}),)


def score(src: str, out: str, refine_options: dict) -> dict:
    """Annotate one segment of ``src`` with ``refine_options`` and score it (``bench_visibility``)."""
    from bench.bench_visibility import CAMERAS, point_frames, summarise
    from drivetrack.annotate import AnnotateConfig, annotate_segment
    from drivetrack.evaluation import evaluate_tracks
    from drivetrack.tracks import TrackConfig

    seg = Path(src, "segment.txt").read_text().strip()
    config = AnnotateConfig(track=TrackConfig(cameras=CAMERAS, object_types=("VEHICLE", "PEDESTRIAN", "CYCLIST", "SIGN"),
                                              min_frames=8, max_camera_distance_m=75.0), refine_options=refine_options)
    result = annotate_segment(src, "training", seg, out, config, keep_tracks=True)
    if result.status != "done":
        raise RuntimeError(f"annotation of {seg} failed at {result.stage}: {result.error}")
    tracks = [t for t in result.tracks if t.rejection is None and t.num_tracks > 0]
    summary = summarise(point_frames(tracks, src), evaluate_tracks(tracks, src).clips)
    aj = np.array([c["aj"] for c in summary["per_clip_oa"]], np.float64)
    weight = np.array([c["tracks"] for c in summary["per_clip_oa"]], np.float64)
    ok = np.isfinite(aj)
    return {"weighted_aj": float(np.average(aj[ok], weights=weight[ok])), "mean_aj": float(aj[ok].mean()),
            "min_aj": float(aj[ok].min()), "wrong": int(summary["wrong"]), "point_frames": int(summary["point_frames"]),
            "p90_px": float(summary["pixel_error"]["p90"]), "refine_s": float(result.timings_s.get("refine", np.nan))}


def markdown(results: dict, settings: tuple, title: str, intro: str, machine: str, start: str, end: str) -> str:
    """The docs block: ``title``, ``intro`` (what was run), one row per world, means, refine time."""
    names = [n for n, _ in settings]
    lines = [start, f"## {title}", "", f"{intro} Machine: {machine}. Each cell: clip AJ weighted by tracks / mean "
             "clip AJ / lowest clip AJ / wrong occlusion calls / pixel error p90 of the truly visible point-frames.", "",
             "| world | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]

    def cell(r: dict, bold: bool = False) -> str:
        text = (f"{r['weighted_aj']:.3f} / {r['mean_aj']:.3f} / {r['min_aj']:.2f} / {r['wrong']:,.0f} / "
                f"{r['p90_px']:.2f}")
        return f"**{text}**" if bold else text

    for world, row in results.items():
        lines.append(f"| {world} | " + " | ".join(cell(row[n]) for n in names) + " |")
    keys = ("weighted_aj", "mean_aj", "min_aj", "wrong", "p90_px", "refine_s")
    mean = {n: {k: np.mean([row[n][k] for row in results.values()]) for k in keys} for n in names}
    lines.append("| **mean** | " + " | ".join(cell(mean[n], bold=True) for n in names) + " |")
    lines += ["", "Refine stage, mean wall seconds per world: " + ", ".join(f"{n} {mean[n]['refine_s']:.1f} s" for n in names)
              + ".", end]
    return "\n".join(lines)


def arguments(description: str, seeds: str) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--seeds", default=seeds, help=f"comma-separated world seeds (default {seeds})")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--workers", type=int, default=2, help="threads rendering the cameras")
    ap.add_argument("--json", default=None, help="also write the raw results to this file")
    ap.add_argument("--no-docs", action="store_true", help="do not rewrite the block in docs/benchmarks.md")
    return ap


def parse_seeds(ap: argparse.ArgumentParser, args: argparse.Namespace) -> list[int]:
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    except ValueError:
        ap.error(f"--seeds: expected comma-separated integers, got {args.seeds!r}")
    if not seeds or args.frames < 8:
        ap.error(f"--seeds needs at least one seed and --frames at least 8 (got {args.seeds!r}, {args.frames})")
    return seeds


def compare(seeds: list[int], worlds: tuple, settings: tuple, frames: int, workers: int) -> dict:
    """{world name: {setting name: score}} over small hard worlds (5 cm / 1 deg labels, every
    camera) of each seed and each of ``worlds`` ((label, SynthConfig options)), annotated with
    each of ``settings`` ((name, refine options))."""
    from bench.bench_visibility import CAMERAS
    from drivetrack.synth import SynthConfig, generate_segment

    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            for label, options in worlds:
                src = f"{tmp}/s{seed}_{len(results)}"
                start = time.perf_counter()
                seg = generate_segment(src, SynthConfig(seed=seed, frames=frames, preset="small", cameras=CAMERAS,
                                                        world="hard", box_noise_m=0.05, **options),
                                       0, workers=workers)["segment"]
                Path(src, "segment.txt").write_text(seg)
                world = f"seed {seed}, {label}"
                row = {}
                for k, (name, refine_options) in enumerate(settings):
                    row[name] = score(src, f"{tmp}/out{len(results)}_{k}", refine_options)
                results[world] = row
                print(world, f"{time.perf_counter() - start:.0f} s", json.dumps(row), flush=True)
    return results


def run(argv: list[str] | None, description: str, seeds: str, worlds: tuple, settings: tuple, title: str,
        intro: str, start: str, end: str) -> int:
    """A benchmark's ``main``: parse the options, compare, print and (unless --no-docs) write the block."""
    from bench.run import machine_description, replace_doc_block

    ap = arguments(description, seeds)
    args = ap.parse_args(argv if argv is not None else [])
    seed_list = parse_seeds(ap, args)
    results = compare(seed_list, worlds, settings, args.frames, args.workers)
    if args.json:
        Path(args.json).write_text(json.dumps({"seeds": seed_list, "results": results}, indent=1))
    intro = intro.format(frames=args.frames, seeds=", ".join(map(str, seed_list)))
    block = markdown(results, settings, title, intro, machine_description(), start, end)
    print(block)
    if not args.no_docs:
        replace_doc_block(DOC, start, end, block)
    return 0
