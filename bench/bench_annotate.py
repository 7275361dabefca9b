"""Annotate speed and memory on one full-size segment (issue 18): stage times, bytes, peak RSS.

One child process per run annotates bench_tracks' cached full-size synthetic segment
(``--preset full --frames 30 --seed 7``: 1920x1280 cameras, Waymo-size lidars; generated under
``.bench-cache/`` on first use) with the default configuration, so that wall time, CPU time (all
threads) and peak RSS are those of the annotation alone. Each thread count given is run
``--repeat`` times; the table reports the fastest run of each (its stage times) and the largest
peak RSS. The first run of the process tree also loads numba's cached kernels.

    .venv/bin/python bench/bench_annotate.py                    # threads 1 and all cores, docs updated
    .venv/bin/python bench/bench_annotate.py --threads 2 --no-docs
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DOC = ROOT / "docs" / "benchmarks.md"
DOC_START, DOC_END = "<!-- bench_annotate:start -->", "<!-- bench_annotate:end -->"
STAGES = ("ingest", "refine", "plan", "depth", "tracks", "write")


def _child(root: str, segment: str, out: str, threads: int) -> None:
    from drivetrack.annotate import AnnotateConfig, annotate_segment

    start = time.perf_counter()
    result = annotate_segment(root, "training", segment, out, AnnotateConfig(), threads=threads)
    wall = time.perf_counter() - start
    if result.status != "done":
        raise SystemExit(f"annotation failed at {result.stage}: {result.error}")
    objects = result.objects
    annotations = int((objects["num_tracks"] * objects["num_frames"]).sum()) if len(objects) else 0
    print(json.dumps({"wall_s": wall, "stages_s": {str(k): v for k, v in result.timings_s.items()},
                      "annotations": annotations,
                      "peak_rss_mib": _peak_rss_mib()}))


def _peak_rss_mib() -> float:
    """This process's peak RSS (VmHWM: reset by exec, unlike getrusage's ru_maxrss, which may
    carry the forking parent's peak), MiB."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _bytes(out: Path) -> int:
    return sum(p.stat().st_size for p in out.rglob("*") if p.is_file())


def run_one(root: str, segment: str, threads: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench_annotate_") as tmp:
        out = Path(tmp) / "out"
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, __file__, "--child", root, segment, str(out), str(threads)],
                              check=True, capture_output=True, text=True, cwd=ROOT,
                              env={**os.environ, "PYTHONPATH": str(ROOT)})
        wall = time.perf_counter() - start
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        run = json.loads(proc.stdout.strip().splitlines()[-1])
        run.update(threads=threads, process_wall_s=wall,
                   cpu_s=(after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime),
                   bytes=_bytes(out))
        return run


def to_markdown(runs: list[dict], machine: str, scene: str) -> str:
    lines = ["## Annotate: stage times and memory on one full-size segment (issue 18)", "",
             f"`bench/bench_annotate.py`: the default configuration on {scene}, each run in its own "
             f"process (fastest of the repeats; peak RSS the largest). Machine: {machine}.", "",
             "| threads | wall s | CPU s | " + " | ".join(f"{s} s" for s in STAGES) + " | peak RSS GiB | annotations | "
             "output bytes / annotation |",
             "|---|---|---|" + "---|" * len(STAGES) + "---|---|---|"]
    for r in runs:
        stages = " | ".join(f"{r['stages_s'].get(s, float('nan')):.2f}" for s in STAGES)
        lines.append(f"| {r['threads']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {stages} | "
                     f"{r['peak_rss_mib'] / 1024:.2f} | {r['annotations']:,} | "
                     f"{r['bytes'] / max(r['annotations'], 1):.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    from bench.bench_tracks import ensure_source
    from bench.run import machine_description, replace_doc_block
    from drivetrack.annotate import available_cores

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", default=None, help="comma-separated thread counts (default: 1 and all cores)")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--cache", default=str(ROOT / ".bench-cache"))
    ap.add_argument("--no-docs", action="store_true")
    args = ap.parse_args(argv if argv is not None else [])
    root, segment = ensure_source(Path(args.cache), "full", 7, args.frames)
    counts = [int(t) for t in args.threads.split(",")] if args.threads else sorted({1, available_cores()})
    runs = []
    for threads in counts:
        tries = [run_one(root, segment, threads) for _ in range(max(1, args.repeat))]
        best = min(tries, key=lambda r: r["wall_s"])
        best["peak_rss_mib"] = max(r["peak_rss_mib"] for r in tries)
        runs.append(best)
        print(json.dumps(best), flush=True)
    markdown = to_markdown(runs, machine_description(),
                           f"bench_tracks' cached segment (`--preset full --frames {args.frames} --seed 7`)")
    print(markdown)
    if not args.no_docs:
        replace_doc_block(DOC, DOC_START, DOC_END, f"{DOC_START}\n{markdown}{DOC_END}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        _child(sys.argv[2], sys.argv[3], sys.argv[4], int(sys.argv[5]))
    else:
        sys.exit(main(sys.argv[1:]))
