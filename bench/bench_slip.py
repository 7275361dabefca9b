"""The refinement's no-side-slip prior (``RefineConfig.slip_sigma_mps``) on noisy labels, before and after.

Generates small hard-world segments (``SynthConfig(world="hard")``, 5 cm / 1 deg label noise,
every camera) for several seeds, each with movers driving on their box centres and on their rear
axles (``rear_axle_fraction`` 0.3: a centre slips sideways on a turn, as a real car's does),
annotates each with the prior off and at the default, and scores the tracks against the exact
truth with ``bench_visibility``'s clip selection (five cameras, every object type, ``min_frames``
8, ``max_camera_distance_m`` 75): clip AJ weighted by tracks, mean clip AJ, wrong occlusion
calls, pixel error of the truly visible point-frames. Writes the ``bench_slip`` block of
docs/benchmarks.md.

    .venv/bin/python bench/bench_slip.py                          # seeds 7-11, ~12 min
    .venv/bin/python bench/bench_slip.py --seeds 7 --no-docs       # ~2 min
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DOC = ROOT / "docs" / "benchmarks.md"
DOC_START, DOC_END = "<!-- bench_slip:start -->", "<!-- bench_slip:end -->"
#: (name, refine options) compared on every world
SETTINGS = (("prior off", {"slip_sigma_mps": None}), ("0.02 m/s (default)", {}))


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
            "wrong": int(summary["wrong"]), "point_frames": int(summary["point_frames"]),
            "p90_px": float(summary["pixel_error"]["p90"]), "refine_s": float(result.timings_s.get("refine", np.nan))}


def markdown(results: dict, setup: dict, machine: str) -> str:
    names = [n for n, _ in SETTINGS]
    lines = [DOC_START, "## The refinement's no-side-slip prior on noisy labels", "",
             f"`bench/bench_slip.py` (small hard world, {setup['frames']} frames, 5 cm / 1 deg labels, seeds "
             f"{', '.join(map(str, setup['seeds']))}, each with movers on their box centres and on their rear axles "
             "(`rear_axle_fraction` 0.3); `bench_visibility`'s clip selection and scoring; docs/refinement.md, "
             f"\"No side slip\"). Machine: {machine}. Each cell: clip AJ weighted by tracks / mean clip AJ / wrong "
             "occlusion calls / pixel error p90 of the truly visible point-frames.", "",
             "| world | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for world, row in results.items():
        lines.append(f"| {world} | " + " | ".join(
            f"{row[n]['weighted_aj']:.3f} / {row[n]['mean_aj']:.3f} / {row[n]['wrong']:,} / {row[n]['p90_px']:.2f}"
            for n in names) + " |")
    mean = {n: {k: np.mean([row[n][k] for row in results.values()]) for k in ("weighted_aj", "mean_aj", "wrong",
                                                                             "p90_px", "refine_s")} for n in names}
    lines.append("| **mean** | " + " | ".join(
        f"**{mean[n]['weighted_aj']:.3f} / {mean[n]['mean_aj']:.3f} / {mean[n]['wrong']:,.0f} / {mean[n]['p90_px']:.2f}**"
        for n in names) + " |")
    lines += ["", "Refine stage, mean wall seconds per world: " + ", ".join(f"{n} {mean[n]['refine_s']:.1f} s" for n in names)
              + ".", DOC_END]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from bench.run import machine_description, replace_doc_block
    from drivetrack.synth import SynthConfig, generate_segment

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="7,8,9,10,11", help="comma-separated world seeds (default 7-11)")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--workers", type=int, default=2, help="threads rendering the cameras")
    ap.add_argument("--json", default=None, help="also write the raw results to this file")
    ap.add_argument("--no-docs", action="store_true", help="do not rewrite the block in docs/benchmarks.md")
    args = ap.parse_args(argv if argv is not None else [])
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    except ValueError:
        ap.error(f"--seeds: expected comma-separated integers, got {args.seeds!r}")
    if not seeds or args.frames < 8:
        ap.error(f"--seeds needs at least one seed and --frames at least 8 (got {args.seeds!r}, {args.frames})")
    from bench.bench_visibility import CAMERAS

    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            for axle in (0.0, 0.3):
                src = f"{tmp}/s{seed}_{axle:g}"
                start = time.perf_counter()
                seg = generate_segment(src, SynthConfig(seed=seed, frames=args.frames, preset="small", cameras=CAMERAS,
                                                        world="hard", box_noise_m=0.05, rear_axle_fraction=axle),
                                       0, workers=args.workers)["segment"]
                Path(src, "segment.txt").write_text(seg)
                world = f"seed {seed}, " + ("rear axles" if axle else "box centres")
                row = {}
                for k, (name, options) in enumerate(SETTINGS):
                    row[name] = score(src, f"{tmp}/out{k}", options)
                results[world] = row
                print(world, f"{time.perf_counter() - start:.0f} s", json.dumps(row), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"seeds": seeds, "results": results}, indent=1))
    block = markdown(results, {"seeds": seeds, "frames": args.frames}, machine_description())
    print(block)
    if not args.no_docs:
        replace_doc_block(DOC, DOC_START, DOC_END, block)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
