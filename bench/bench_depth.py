"""Depth completion benchmark: maps per CPU-second and error against exact depth.

Scene: the analytic street of ``tests/_analytic_depth.py`` (ground plane + 7 boxes) seen by
a Waymo-like FRONT camera (1920x1280, distortion), LiDAR simulated by ray casting, exact dense
depth by intersecting every pixel-centre ray. Two LiDAR patterns: ``waymo-top`` (64 beams x
2650 columns, like Waymo's TOP LiDAR, about 0.7% of the pixels) and ``dense-5pct`` (200 x 6000,
about 5%). Errors are scored where the exact depth is known and within the LiDAR's 75 m range.

    .venv/bin/python bench/bench_depth.py             # full size; rewrites its block of docs/benchmarks.md
    .venv/bin/python -m bench.run depth               # the same through the benchmark runner
    .venv/bin/python bench/bench_depth.py --quick     # 480x320 smoke run, docs untouched
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import re
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
# The analytic scene is a test fixture (tests/_analytic_depth.py), shared with tests/test_depth.py.
sys.path.insert(0, str(ROOT / "tests"))

from drivetrack.depth import get_completer, lookup_max4, sparse_depth_from_points  # noqa: E402
from _analytic_depth import default_scene, exact_depth, front_camera, lidar_points  # noqa: E402

LIDAR_RANGE_M = 75.0
PATTERNS = {"waymo-top": dict(beams=64, azimuths=2650), "dense-5pct": dict(beams=200, azimuths=6000)}
DOC_START = "<!-- bench_depth:start -->"
DOC_END = "<!-- bench_depth:end -->"


def machine_info() -> dict:
    """nproc, CPU model, RAM, load, library versions."""
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
        mem_kb = next(int(line.split()[1]) for line in Path("/proc/meminfo").read_text().splitlines()
                      if line.startswith("MemTotal"))
    except (OSError, StopIteration):
        mem_kb = 0
    import cv2
    import scipy
    info = {"nproc": os.cpu_count(), "cpu": cpu, "ram_gib": round(mem_kb / 2**20, 1),
            "load_avg_1m": os.getloadavg()[0], "python": platform.python_version(),
            "numpy": np.__version__, "opencv": cv2.__version__, "scipy": scipy.__version__}
    try:
        import torch
        info["torch"] = torch.__version__
        info["cuda"] = torch.cuda.is_available()
    except ImportError:
        info["torch"] = None
    return info


def timed(fn, repeats: int) -> dict:
    """Run ``fn`` ``repeats`` times after one warm-up; CPU (process_time, all threads) and wall
    seconds per call, median and best."""
    result = fn()
    cpu, wall = [], []
    for _ in range(repeats):
        c0, w0 = time.process_time(), time.perf_counter()
        result = fn()
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return {"cpu_s": statistics.median(cpu), "cpu_s_best": min(cpu),
            "wall_s": statistics.median(wall), "repeats": repeats, "result": result}


def depth_errors(dense: np.ndarray, truth: np.ndarray) -> dict:
    """MAE, RMSE (metres), % within 5% on pixels with known exact depth within LiDAR range and a
    filled estimate; coverage of those pixels; % of sky pixels (no surface) filled anyway."""
    evaluable = (truth > 0) & (truth <= LIDAR_RANGE_M)
    filled = evaluable & (dense > 0)
    error = np.abs(dense[filled].astype(np.float64) - truth[filled])
    sky = truth == 0
    return {"mae_m": float(error.mean()) if error.size else math.nan,
            "rmse_m": float(np.sqrt(np.mean(error ** 2))) if error.size else math.nan,
            "within_5pct": float(np.mean(error < 0.05 * truth[filled])) if error.size else math.nan,
            "coverage": float(filled.sum() / max(evaluable.sum(), 1)),
            "sky_filled": float(np.mean(dense[sky] > 0)) if sky.any() else 0.0}


def released_baseline(sparse: np.ndarray) -> np.ndarray:
    """What the released DriveTrack script did: scipy NearestNDInterpolator over the full pixel
    grid, no reach limit (re-written here from its description, for timing only)."""
    from scipy.interpolate import NearestNDInterpolator
    rows, cols = np.nonzero(sparse)
    interpolate = NearestNDInterpolator(np.stack([rows, cols], -1), sparse[rows, cols])
    grid_rows, grid_cols = np.mgrid[0:sparse.shape[0], 0:sparse.shape[1]]
    return interpolate(grid_rows, grid_cols).astype(np.float32)


def run(width: int, height: int, repeats: int, with_baseline: bool) -> dict:
    camera = front_camera(width, height)
    scene = default_scene()
    started = time.perf_counter()
    truth = exact_depth(scene, camera)
    exact_depth_s = time.perf_counter() - started
    results = {"machine": machine_info(), "width": width, "height": height,
               "exact_depth_s": exact_depth_s, "patterns": {}}
    methods = [("nearest", {}, repeats), ("nearest", {"backend": "scipy"}, max(repeats // 3, 1)),
               ("ipbasic", {}, max(repeats // 2, 1))]
    if results["machine"].get("torch"):
        methods.append(("nearest-torch", {"device": "cpu"}, 1))
        if results["machine"].get("cuda"):
            methods.append(("nearest-torch", {"device": "cuda"}, repeats))
    for pattern, lidar in PATTERNS.items():
        points = lidar_points(scene, **lidar)
        projection = timed(lambda: sparse_depth_from_points(points, camera), max(repeats // 2, 1))
        sparse = projection.pop("result")
        entry = {"points": len(points), "density": float(np.mean(sparse > 0)),
                 "projection": projection, "sparse": depth_errors(sparse, truth), "methods": []}
        for name, params, count in methods:
            completer = get_completer(name, **params)
            timing = timed(lambda: completer(sparse), count)
            dense = timing.pop("result")
            label = name + "".join(f" {k}={v}" for k, v in params.items())
            entry["methods"].append({"method": label, **timing, **depth_errors(dense, truth)})
        if results["machine"].get("torch"):  # batching: one call for 4 maps
            completer = get_completer("nearest-torch", device="cpu")
            batch = np.stack([sparse] * 4)
            timing = timed(lambda: completer(batch), 1)
            timing.pop("result")
            entry["torch_cpu_batch4_cpu_s_per_map"] = timing["cpu_s"] / 4
        if with_baseline:
            timing = timed(lambda: released_baseline(sparse), 1)
            dense = timing.pop("result")
            entry["methods"].append({"method": "released code (NearestNDInterpolator)", **timing,
                                     **depth_errors(dense, truth)})
        results["patterns"][pattern] = entry
    rng = np.random.default_rng(0)
    pixels = rng.uniform([0, 0], [width, height], (1_000_000, 2))
    dense = get_completer("nearest")(sparse)
    lookup = timed(lambda: lookup_max4(dense, pixels), max(repeats // 2, 1))
    lookup.pop("result")
    results["lookup_max4_1M"] = lookup
    return results


def to_markdown(results: dict) -> str:
    m = results["machine"]
    lines = [
        f"Machine: {m['nproc']} CPUs ({m['cpu']}), {m['ram_gib']} GiB RAM, 1-min load "
        f"{m['load_avg_1m']:.2f} at start (a shared machine: under load CPU times run up to ~1.5x "
        f"those of a quiet one); "
        f"Python {m['python']}, numpy {m['numpy']}, OpenCV {m['opencv']}, scipy {m['scipy']}, "
        f"torch {m.get('torch')} (CUDA: {m.get('cuda', False)}).",
        f"Image {results['width']}x{results['height']}, analytic street scene "
        f"(`tests/_analytic_depth.py`); exact depth of all pixels in {results['exact_depth_s']:.1f} s. "
        f"Errors on pixels whose exact depth is within the LiDAR's {LIDAR_RANGE_M:.0f} m range; "
        "coverage = share of those filled; sky filled = share of surface-less pixels given a depth.",
        "",
    ]
    for pattern, entry in results["patterns"].items():
        proj = entry["projection"]
        lines += [
            f"**{pattern}**: {entry['points']:,} LiDAR points, {100 * entry['density']:.2f}% of "
            f"pixels have a return; `sparse_depth_from_points` {proj['cpu_s'] * 1e3:.0f} ms CPU. "
            f"Sparse returns themselves: {100 * entry['sparse']['within_5pct']:.1f}% within 5% "
            "(the rest: background seen by the LiDAR through gaps the camera does not see, "
            "LiDAR-camera parallax).",
            "",
            "| method | CPU s/map (median, best) | wall s/map | maps per CPU-s | MAE m | RMSE m | within 5% | coverage | sky filled |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for row in entry["methods"]:
            lines.append(
                f"| {row['method']} | {row['cpu_s']:.3f}, {row['cpu_s_best']:.3f} | {row['wall_s']:.3f} | "
                f"{1 / row['cpu_s']:.1f} | {row['mae_m']:.2f} | {row['rmse_m']:.2f} | "
                f"{100 * row['within_5pct']:.1f}% | {100 * row['coverage']:.1f}% | "
                f"{100 * row['sky_filled']:.1f}% |")
        if "torch_cpu_batch4_cpu_s_per_map" in entry:
            lines.append(f"\n`nearest-torch` on CPU, batch of 4: "
                         f"{entry['torch_cpu_batch4_cpu_s_per_map']:.2f} CPU s per map.")
        lines.append("")
    lookup = results["lookup_max4_1M"]
    lines.append(f"`lookup_max4`: 1,000,000 positions in {lookup['cpu_s']:.3f} CPU s "
                 f"({1 / lookup['cpu_s']:.1f} M look-ups per CPU-second).")
    return "\n".join(lines) + "\n"


def update_docs(markdown: str, path: Path) -> None:
    """Replace this benchmark's block inside the "Depth completion" section of docs/benchmarks.md."""
    block = f"{DOC_START}\n{markdown}{DOC_END}"
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    if DOC_START in text and DOC_END in text:
        text = re.sub(re.escape(DOC_START) + ".*?" + re.escape(DOC_END), lambda _: block, text,
                      flags=re.S)
    else:
        text = text.rstrip("\n") + "\n\n## Depth completion\n\n" + block + "\n"
    path.write_text(text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="480x320, few repeats (smoke test)")
    parser.add_argument("--repeats", type=int, default=None, help="timed calls per method")
    parser.add_argument("--no-baseline", action="store_true",
                        help="skip the slow released-code baseline (NearestNDInterpolator)")
    parser.add_argument("--json", type=Path, help="also write the raw results here")
    parser.add_argument("--no-docs", action="store_true",
                        help="do not rewrite the depth block of docs/benchmarks.md "
                             "(never rewritten by --quick runs)")
    # bench/run.py calls main() with no arguments: a full run that records its figures
    args = parser.parse_args([] if argv is None else argv)
    width, height = (480, 320) if args.quick else (1920, 1280)
    repeats = args.repeats or (2 if args.quick else 10)
    results = run(width, height, repeats, with_baseline=not (args.no_baseline or args.quick))
    markdown = to_markdown(results)
    print(markdown)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=float))
    if not (args.quick or args.no_docs):
        update_docs(markdown, ROOT / "docs" / "benchmarks.md")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
