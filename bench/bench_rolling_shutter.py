"""Does the track stage's rolling-shutter projection pay off on rolling-shutter cameras?

Generates a small synthetic segment with ``SynthConfig(rolling_shutter=True)`` (and, as a control,
the same world global-shutter), annotates each with ``TrackConfig(rolling_shutter=True)`` and
``False`` and scores the tracks against the exact truth (``drivetrack.evaluation``).

    .venv/bin/python bench/bench_rolling_shutter.py                 # 30 frames, seed 7
    .venv/bin/python bench/bench_rolling_shutter.py --frames 30 --seed 3 --no-control
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _score(root: str, segment: str, rolling: bool, refine: bool | None) -> dict:
    from drivetrack.annotate import AnnotateConfig, annotate_segment
    from drivetrack.evaluation import evaluate_tracks
    from drivetrack.tracks import TrackConfig

    kwargs = {} if refine is None else {"refine_poses": refine}
    config = AnnotateConfig(track=TrackConfig(rolling_shutter=rolling), **kwargs)
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        result = annotate_segment(root, "training", segment, out, config, keep_tracks=True)
        if result.status != "done":
            raise RuntimeError(f"annotation of {segment} failed at {result.stage}: {result.error}")
        seconds = time.perf_counter() - start
    summary = evaluate_tracks(result.tracks, root).summary
    first = summary["modes"]["first"]
    projections = sorted({t.projection for t in result.tracks if t.rejection is None})
    return {"pixel_error_median": summary["pixel_error_median"],
            "pixel_error_p95": summary["pixel_error_p95"],
            "average_jaccard": first["average_jaccard"],
            "occlusion_accuracy": first.get("occlusion_accuracy"),
            "delta_avg": first.get("average_pts_within_thresh"),
            "projection": projections, "annotate_s": round(seconds, 1)}


def main(argv=None) -> int:
    from drivetrack.synth import SynthConfig, generate_segment

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--no-control", action="store_true", help="skip the global-shutter scene")
    ap.add_argument("--refine", choices=["default", "on", "off"], default="default",
                    help="pose refinement of the annotation (default: the library default)")
    args = ap.parse_args(argv)
    refine = None if args.refine == "default" else args.refine == "on"
    rows = []
    scenes = [True] if args.no_control else [True, False]
    with tempfile.TemporaryDirectory() as tmp:
        for rolling_scene in scenes:
            root = f"{tmp}/{'rs' if rolling_scene else 'gs'}"
            start = time.perf_counter()
            seg = generate_segment(root, SynthConfig(seed=args.seed, frames=args.frames,
                                                     rolling_shutter=rolling_scene), 0)["segment"]
            gen_s = time.perf_counter() - start
            for rolling_track in (True, False):
                row = {"scene": "rolling" if rolling_scene else "global",
                       "track_rolling_shutter": rolling_track, "generate_s": round(gen_s, 1),
                       **_score(root, seg, rolling_track, refine)}
                rows.append(row)
                print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
