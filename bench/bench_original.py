"""The original released DriveTrack script and our annotate on one full-size segment, in one run (issue 18).

Both read the same synthetic Waymo v2 segment (bench_tracks' cached ``--preset full --frames 30
--seed 7``: 1920x1280 cameras, Waymo-size lidars). The original is run as issue 18 prescribes:

- from its own venv (this Python's version, 3.11; the SDK's pins do not resolve on 3.10 today) with ``waymo-open-dataset-tf-2-12-0==1.6.7`` and
  ``distributed==2023.3.1`` (plus tqdm, and psutil for this script's memory sampling), built on
  first use under ``.bench-cache/original-venv`` (about 1.5 GB of wheels from PyPI);
- its script is *not* part of this repository (its code is not ours to copy): give the path of
  ``generate_drivetrack.py`` from a checkout of https://github.com/arjunvb/drivetrack with
  ``--script`` or ``DRIVETRACK_ORIGINAL_SCRIPT`` (without either, e.g. in ``make bench``, this
  benchmark says so and is skipped). This bench runs a temporary copy with the edits the issue names, applied as the
  exact textual replacements in :data:`EDITS` (it refuses when a line is not found): the
  ``gcsfs`` and ``torch`` imports made optional (the nearest-neighbour path uses neither), and the
  output folder given as an absolute path. Everything else is the script's own (a pool of 32
  processes for depth completion, one process per annotation), except its Dask cluster size,
  set with its own options ``--num-workers`` (default here: the machine's cores) and
  ``--threads-per-worker 1``: its default of 8 workers gives each worker an eighth of the RAM
  (2.9 GiB on a 24 GiB machine), and its per-camera aggregation of the LiDAR table then kills
  all of them (``KilledWorker``, measured on this machine);
- measured: wall time, CPU seconds of its whole process tree (``RUSAGE_CHILDREN``), the peak RSS
  of its largest process (``RUSAGE_CHILDREN``'s ``ru_maxrss``, what GNU ``time -v`` reports), the
  peak of the tree's summed PSS (sampled every 0.2 s with psutil: shared pages counted once; its
  32 completion processes share the parent's pages), and its npz outputs (count, bytes).

Then ours, in the same run: ``bench_annotate``'s child (one process, default configuration,
``--threads`` threads, fastest of ``--repeat``). The table with both goes into
docs/benchmarks.md between the ``bench_original`` markers.

    .venv/bin/python bench/bench_original.py --script ~/src/drivetrack/generate_drivetrack.py
    DRIVETRACK_ORIGINAL_SCRIPT=~/src/drivetrack/generate_drivetrack.py make bench BENCH=original
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DOC = ROOT / "docs" / "benchmarks.md"
DOC_START, DOC_END = "<!-- bench_original:start -->", "<!-- bench_original:end -->"
VENV_PACKAGES = ("waymo-open-dataset-tf-2-12-0==1.6.7", "distributed==2023.3.1", "tqdm", "psutil")

#: (exact text in the original script, replacement): the edits issue 18 names, nothing else.
EDITS = (
    ("import gcsfs\n",
     "try:\n    import gcsfs\nexcept ImportError:  # bench edit: not needed for local input\n"
     "    class gcsfs:\n        GCSFileSystem = None\n"),
    ("import torch\nimport torch.multiprocessing as torchmp\nimport torchvision.transforms.functional as TF\n",
     "try:\n    import torch\n    import torch.multiprocessing as torchmp\n"
     "    import torchvision.transforms.functional as TF\n"
     "except ImportError:  # bench edit: the nearest-neighbour path uses none of them\n"
     "    torch = TF = None\n"
     "    class torchmp:  # its annotations name these\n        Queue = Process = None\n"),
)


def edited_script(source: str) -> str:
    """The original's text with :data:`EDITS` applied; ValueError naming an edit it cannot apply."""
    for old, new in EDITS:
        if source.count(old) != 1:
            raise ValueError(f"bench_original: expected the line(s) {old!r} once in the original script, "
                             f"found {source.count(old)} times (another version of the script?)")
        source = source.replace(old, new)
    return source


def build_venv(venv: Path) -> Path:
    python = venv / "bin" / "python"
    if not python.exists():
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)   # our Python (3.11)
        subprocess.run([str(python), "-m", "pip", "install", "-q", *VENV_PACKAGES], check=True)
    return python


def _tree_pss_sampler(pid: int, peak: dict, stop: threading.Event) -> None:
    """Keep in ``peak["bytes"]`` the largest PSS (proportional set size: shared pages split among
    their processes, so the sum over the tree counts each page once) of the process tree."""
    import psutil

    try:
        root = psutil.Process(pid)
    except psutil.Error:
        return
    while not stop.is_set():
        total = 0
        try:
            for proc in [root, *root.children(recursive=True)]:
                try:
                    total += proc.memory_full_info().pss
                except psutil.Error:
                    pass
        except psutil.Error:
            pass
        peak["bytes"] = max(peak.get("bytes", 0), total)
        stop.wait(0.2)


def run_original(python: Path, script: Path, source_root: str, timeout_s: float, workers: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench_original_") as tmp:
        copy = Path(tmp) / "generate_drivetrack.py"
        copy.write_text(edited_script(script.read_text()))
        out = (Path(tmp) / "out").resolve()          # the script needs an absolute --output-dir
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.perf_counter()
        proc = subprocess.Popen([str(python), str(copy), "--output-dir", str(out), "--local-dataset-path",
                                 str(Path(source_root).resolve()), "--num-workers", str(workers),
                                 "--threads-per-worker", "1"], cwd=tmp, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True,
                                env={**os.environ, "CUDA_VISIBLE_DEVICES": "", "PYTHONPATH": ""})
        peak, stop = {}, threading.Event()
        sampler = threading.Thread(target=_tree_pss_sampler, args=(proc.pid, peak, stop), daemon=True)
        sampler.start()
        try:
            log, _ = proc.communicate(timeout=timeout_s)
        finally:
            stop.set()
            if proc.poll() is None:
                proc.kill()
        wall = time.perf_counter() - start
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        files = sorted(out.rglob("*.npz"))
        if proc.returncode != 0 or not files:
            raise RuntimeError(f"the original script failed (exit {proc.returncode}, {len(files)} npz files); "
                             f"its output ends:\n{log[-3000:]}")
        return {"wall_s": wall, "cpu_s": (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime),
                "peak_pss_mib": peak.get("bytes", 0) / 2 ** 20,
                "largest_process_rss_mib": after.ru_maxrss / 1024,   # max over the waited-for descendants
                "files": len(files),
                "bytes": sum(f.stat().st_size for f in files)}


def to_markdown(original: dict, ours: dict, machine: str, threads: int) -> str:
    ratio = original["wall_s"] / ours["wall_s"]
    return "\n".join([
        "## Annotate against the original script, same segment, same run (issue 18)",
        "",
        f"`bench/bench_original.py`: bench_tracks' cached full-size segment (`--preset full --frames 30 --seed 7`, "
        f"1920x1280). The original (`generate_drivetrack.py` of arjunvb/drivetrack, its venv: "
        f"{', '.join(f'`{p}`' for p in VENV_PACKAGES[:2])}; only the edits the issue names; its own options "
        f"`--num-workers {original['workers']} --threads-per-worker 1`, the rest its defaults); ours: "
        f"`annotate` with the default configuration and {threads} threads (fastest of the repeats; ours is one "
        f"process). Machine: {machine}.",
        "",
        "| run | wall s | CPU s | peak RSS of the largest process GiB | peak PSS of the process tree GiB | npz files | output bytes |",
        "|---|---|---|---|---|---|---|",
        f"| original script | {original['wall_s']:.1f} | {original['cpu_s']:.0f} | "
        f"{original['largest_process_rss_mib'] / 1024:.2f} | {original['peak_pss_mib'] / 1024:.2f} | "
        f"{original['files']} | {original['bytes']:,} |",
        f"| drivetrack annotate ({threads} threads) | {ours['wall_s']:.1f} | {ours['cpu_s']:.1f} | "
        f"{ours['peak_rss_mib'] / 1024:.2f} | {ours['peak_rss_mib'] / 1024:.2f} | (tables) | {ours['bytes']:,} |",
        "",
        f"Wall-time ratio: **{ratio:.0f}x** (issue 18 asks >= 40x).",
        ""])


def main(argv: list[str] | None = None) -> int:
    from bench.bench_annotate import run_one
    from bench.bench_tracks import ensure_source
    from bench.run import machine_description, replace_doc_block
    from drivetrack.annotate import available_cores

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--script", type=Path, default=os.environ.get("DRIVETRACK_ORIGINAL_SCRIPT") or None,
                    help="generate_drivetrack.py from a checkout of https://github.com/arjunvb/drivetrack "
                         "(default: $DRIVETRACK_ORIGINAL_SCRIPT)")
    ap.add_argument("--venv", type=Path, default=ROOT / ".bench-cache" / "original-venv",
                    help="the original's venv (default .bench-cache/original-venv)")
    ap.add_argument("--threads", type=int, default=None, help="our threads (default: all cores)")
    ap.add_argument("--repeat", type=int, default=2, help="runs of ours (the original runs once)")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds the original may take")
    ap.add_argument("--original-workers", type=int, default=None,
                    help="the original's --num-workers (Dask workers of 1 thread; default: all cores)")
    ap.add_argument("--cache", default=str(ROOT / ".bench-cache"))
    ap.add_argument("--no-docs", action="store_true")
    args = ap.parse_args(argv if argv is not None else [])
    if args.script is None:
        print("bench_original: skipped: give the original script's path (--script or "
              "DRIVETRACK_ORIGINAL_SCRIPT; see the module docstring)")
        return 0
    if not Path(args.script).is_file():
        raise FileNotFoundError(f"bench_original: --script {args.script}: no such file")
    python = build_venv(args.venv)
    root, segment = ensure_source(Path(args.cache), "full", 7, 30)
    threads = args.threads or available_cores()
    workers = args.original_workers or available_cores()
    original = run_original(python, Path(args.script), root, args.timeout, workers)
    original["workers"] = workers
    print(json.dumps({"original": original}), flush=True)
    tries = [run_one(root, segment, threads) for _ in range(max(1, args.repeat))]
    ours = min(tries, key=lambda r: r["wall_s"])
    ours["peak_rss_mib"] = max(r["peak_rss_mib"] for r in tries)
    print(json.dumps({"ours": ours}), flush=True)
    markdown = to_markdown(original, ours, machine_description(), threads)
    print(markdown)
    if not args.no_docs:
        replace_doc_block(DOC, DOC_START, DOC_END, f"{DOC_START}\n{markdown}{DOC_END}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
