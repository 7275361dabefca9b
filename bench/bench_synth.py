"""Synthetic scene generation benchmark: one ``full`` segment (Waymo sizes) and one ``small``.

Generates with :func:`drivetrack.synth.generate_segment` in a child process, so that wall time,
CPU time (user + system, all threads) and peak RSS are those of the generation alone, and
records bytes written (parquet components and ground truth).

    .venv/bin/python bench/bench_synth.py                  # full (40 frames) + small, updates docs
    .venv/bin/python bench/bench_synth.py --quick          # small only, prints, docs untouched
    .venv/bin/python bench/bench_synth.py --frames 10 --no-docs
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DOC_START = "<!-- bench_synth:start -->"
DOC_END = "<!-- bench_synth:end -->"


def _child(out: str, preset: str, frames: int, workers: int) -> None:
    from drivetrack.synth import SynthConfig, generate_segment

    stages: dict[str, float] = {}
    start = time.perf_counter()

    def progress(stage, done, total):
        stages[stage] = time.perf_counter() - start

    summary = generate_segment(out, SynthConfig(seed=7, frames=frames, preset=preset), 0,
                               progress=progress, workers=workers)
    summary["stage_end_s"] = stages
    summary["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps(summary))


def _dir_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def run_one(preset: str, frames: int, workers: int) -> dict:
    with tempfile.TemporaryDirectory(prefix=f"bench_synth_{preset}_") as out:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, __file__, "--child", out, preset, str(frames), str(workers)],
                              check=True, capture_output=True, text=True, cwd=ROOT)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        summary = json.loads(proc.stdout.strip().splitlines()[-1])
        split = Path(out) / "training"
        components = {p.name: _dir_bytes(p) for p in split.iterdir() if p.name != "drivetrack_ground_truth"}
    return {"preset": preset, "frames": frames, "workers": workers, "wall_s": wall,
            "cpu_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
            "peak_rss_mib": summary["peak_rss_mib"], "stage_end_s": summary["stage_end_s"],
            "component_bytes": components, "ground_truth_bytes": summary["ground_truth_bytes"],
            "object_returns": summary["num_object_returns"], "objects": summary["num_objects"]}


def to_markdown(results: list[dict], machine: str, load: float) -> str:
    lines = ["## Synthetic scene generation", "",
             "`bench/bench_synth.py`: `generate_segment` (seed 7, cameras FRONT, FRONT_LEFT, "
             "FRONT_RIGHT, all five lidars, both returns, exact ground truth) in a child process. "
             f"Machine: {machine}; 1-minute load average at start {load:.1f} (the machine is shared, "
             "so wall time can exceed CPU time).", "",
             "| preset | frames | camera threads | wall s | CPU s | peak RSS MiB | parquet MB | ground truth MB | object returns |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        lines.append(f"| {r['preset']} | {r['frames']} | {r['workers']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | "
                     f"{r['peak_rss_mib']:.0f} | {sum(r['component_bytes'].values()) / 1e6:.1f} | "
                     f"{sum(r['ground_truth_bytes'].values()) / 1e6:.1f} | {r['object_returns']} |")
    lines.append("")
    for r in results:
        st = r["stage_end_s"]
        order = [s for s in ("cameras", "lidar", "write", "truth") if s in st]
        prev, parts = 0.0, []
        for s in order:
            parts.append(f"{s} {st[s] - prev:.1f} s")
            prev = st[s]
        big = sorted(r["component_bytes"].items(), key=lambda kv: -kv[1])[:4]
        lines.append(f"- `{r['preset']}` stages (wall): {', '.join(parts)}; largest components: "
                     + ", ".join(f"{k} {v / 1e6:.1f} MB" for k, v in big)
                     + "; ground truth: " + ", ".join(f"{k} {v / 1e6:.1f} MB" for k, v in r["ground_truth_bytes"].items()))
    lines.append("")
    return "\n".join(lines) + "\n"


def update_docs(markdown: str, path: Path) -> None:
    block = f"{DOC_START}\n{markdown}{DOC_END}"
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    if DOC_START in text and DOC_END in text:
        text = re.sub(re.escape(DOC_START) + ".*?" + re.escape(DOC_END), lambda _: block, text, flags=re.S)
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    path.write_text(text)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:
        _child(argv[1], argv[2], int(argv[3]), int(argv[4]))
        return 0
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--workers", type=int, default=2, help="camera render threads")
    parser.add_argument("--quick", action="store_true", help="small preset only, docs untouched")
    parser.add_argument("--no-docs", action="store_true")
    args = parser.parse_args(argv)
    from bench.run import machine_description

    load = os.getloadavg()[0]
    presets = ["small"] if args.quick else ["full", "small"]
    results = []
    for preset in presets:
        r = run_one(preset, args.frames, args.workers)
        print(json.dumps(r))
        results.append(r)
    md = to_markdown(results, machine_description(), load)
    print(md)
    if not (args.quick or args.no_docs):
        update_docs(md, ROOT / "docs" / "benchmarks.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
