"""Run the benchmarks: every ``bench/bench_*.py`` module's ``main()``, or the ones named.

    python -m bench.run                 # all
    python -m bench.run depth release   # bench_depth.py and bench_release.py only

Each benchmark prints its figures and updates its own section of docs/benchmarks.md together
with the machine description, so that the recorded numbers always come from a run of the code.
"""
from __future__ import annotations

import importlib
import os
import re
import pkgutil
import sys
import time
from pathlib import Path


def replace_doc_block(doc: Path, start: str, end: str, block: str) -> None:
    """Replace the one ``start ... end`` block of ``doc`` (docs/benchmarks.md) by ``block`` (which
    holds both markers), or append it. Others edit the rest of the file concurrently: the whole text
    is read, only the block replaced, and a temporary file in the same folder ``os.replace``d, so
    the file is never seen truncated."""
    text = doc.read_text() if doc.exists() else "# Benchmarks\n"
    if start in text:
        if text.count(start) != 1 or text.find(end) < text.find(start):
            raise ValueError(f"{doc}: expected one {start} ... {end} block")
        text = re.sub(re.escape(start) + ".*?" + re.escape(end), lambda _: block, text, flags=re.S)
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    tmp = doc.with_name(f".{doc.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, doc)


def add_hard_world_arguments(parser) -> None:
    """The options of the benchmarks that generate one hard-world segment and score it
    (bench_visibility, bench_time): preset, frames, seed, render workers, --json, --no-docs."""
    parser.add_argument("--preset", default="medium", choices=["small", "medium", "full"])
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--workers", type=int, default=2, help="threads rendering the cameras")
    parser.add_argument("--json", default=None, help="also write the raw results to this file")
    parser.add_argument("--no-docs", action="store_true", help="do not rewrite the block in docs/benchmarks.md")


def machine_description() -> str:
    """One line: cores, CPU model, memory, Python; written beside every benchmark figure."""
    import os
    import platform

    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = ""
    try:
        kb = int(Path("/proc/meminfo").read_text().split()[1])
        mem = f", {kb / 2**20:.0f} GiB RAM"
    except (OSError, ValueError, IndexError):
        pass
    return f"{os.cpu_count()} cores ({cpu}){mem}, Python {platform.python_version()}, {platform.system()}"


def main(argv: list[str] | None = None) -> int:
    wanted = set(argv if argv is not None else sys.argv[1:])
    here = Path(__file__).parent
    names = sorted(m.name for m in pkgutil.iter_modules([str(here)]) if m.name.startswith("bench_"))
    if wanted:
        names = [n for n in names if n.removeprefix("bench_") in wanted or n in wanted]
    print(f"machine: {machine_description()}")
    failures = 0
    for name in names:
        print(f"\n=== {name}")
        start = time.perf_counter()
        try:
            importlib.import_module(f"bench.{name}").main()
        except Exception as exc:  # report and go on with the other benchmarks
            failures += 1
            print(f"{name} FAILED: {type(exc).__name__}: {exc}")
        print(f"=== {name}: {time.perf_counter() - start:.1f} s")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
