"""Benchmark: release layout v2 size (bytes per annotation) and the write stage's share of annotate.

    .venv/bin/python bench/bench_compact.py [--preset medium] [--frames 30] [--seed 7]

Synthesises one segment (``drivetrack synth``), annotates it (default configuration, one
process), then measures:

- bytes per annotation of the v2 layout: (clips tables + frames tables) / sum over clips of
  N x T (one annotation = one track in one frame; the frames' JPEG bytes are amortised over the
  annotations of every clip that uses them);
- the same for the npz files ``drivetrack export`` writes (DriveTrack + TAPVid-3D), the layout
  before v2;
- the share of annotate's wall time spent writing the files (``write_segment_outputs`` on the
  segment's tracked clips, timed alone), the stage times (``SegmentResult.timings_s``; its
  ``write`` stage also computes the statistics rows, e.g. the speed consistency under the
  labelled poses), and the export's time.

Target (issue 18): <= 30 bytes per annotation, frames included; writing < 10 % of annotate.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path


def _bytes(root: Path, pattern: str) -> int:
    return sum(p.stat().st_size for p in root.glob(pattern))


def main(argv: list[str] | None = None) -> int:
    """``argv`` None (as ``bench.run`` calls it): the defaults."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="medium", choices=["small", "medium", "full"])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args(argv or [])

    import pyarrow.parquet as pq

    from drivetrack.annotate import AnnotateConfig, annotate, annotate_segment, write_segment_outputs
    from drivetrack.compact.export import FORMATS, export_clips
    from drivetrack.synth import SynthConfig, generate_segment, segment_name

    with tempfile.TemporaryDirectory(prefix="bench-compact-") as tmp:
        src, out, exp = Path(tmp) / "src", Path(tmp) / "out", Path(tmp) / "exp"
        generate_segment(str(src), SynthConfig(seed=args.seed, frames=args.frames, preset=args.preset), 0)
        segment = segment_name(args.seed, 0)
        annotate(str(src), "training", [segment], str(out), AnnotateConfig())   # warm numba caches
        out_warm = Path(tmp) / "out2"
        t = time.perf_counter()
        result = annotate(str(src), "training", [segment], str(out_warm), AnnotateConfig())[0]
        wall = time.perf_counter() - t
        assert result.status == "done", result.error
        clips = pq.read_table(next(out_warm.glob("clips/training/*.parquet")), columns=["num_tracks", "num_frames"])
        annotations = sum(n * f for n, f in zip(clips.column("num_tracks").to_pylist(),
                                                clips.column("num_frames").to_pylist()))
        clips_b, frames_b = _bytes(out_warm, "clips/*/*.parquet"), _bytes(out_warm, "frames/*/*.parquet")
        t = time.perf_counter()
        export_clips(str(out_warm), list(FORMATS), str(exp))
        export_s = time.perf_counter() - t
        npz_dt, npz_tv = _bytes(exp, "tracks/*/*.npz"), _bytes(exp, "tapvid3d/*/*.npz")
        timings = result.timings_s
        total = sum(timings.values())
        kept = annotate_segment(str(src), "training", segment, str(Path(tmp) / "out3"), AnnotateConfig(),
                                keep_tracks=True)
        t = time.perf_counter()
        write_segment_outputs(str(Path(tmp) / "out4"), "training", kept.tracks)
        write_s = time.perf_counter() - t

    print(f"preset {args.preset}, {args.frames} frames, seed {args.seed}: {clips.num_rows} clips, "
          f"{annotations:,} annotations (track x frame)")
    print("| layout | bytes | bytes / annotation |")
    print("|---|---|---|")
    print(f"| v2 clips tables | {clips_b:,} | {clips_b / annotations:.1f} |")
    print(f"| v2 frames tables (JPEG once) | {frames_b:,} | {frames_b / annotations:.1f} |")
    print(f"| **v2 total** | {clips_b + frames_b:,} | **{(clips_b + frames_b) / annotations:.1f}** |")
    print(f"| npz DriveTrack (export) | {npz_dt:,} | {npz_dt / annotations:.1f} |")
    print(f"| npz TAPVid-3D (export) | {npz_tv:,} | {npz_tv / annotations:.1f} |")
    print(f"| npz both (the layout before v2) | {npz_dt + npz_tv:,} | {(npz_dt + npz_tv) / annotations:.1f} |")
    print()
    print("| stage | seconds | share |")
    print("|---|---|---|")
    for stage, seconds in timings.items():
        print(f"| {stage} | {seconds:.2f} | {100 * seconds / total:.1f} % |")
    print(f"| annotate wall (one segment, warm) | {wall:.2f} | |")
    print(f"| of which writing the tables (write_segment_outputs alone) | {write_s:.2f} | "
          f"{100 * write_s / wall:.1f} % of the wall |")
    print(f"| export, both formats (not part of annotate) | {export_s:.2f} | |")
    return 0


if __name__ == "__main__":
    import sys

    raise SystemExit(main(sys.argv[1:]))
