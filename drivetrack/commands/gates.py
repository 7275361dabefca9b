"""``drivetrack gates OUT [--config FILE]``: run the release gates on an annotation output folder.

Writes ``OUT/validation/`` (gates.json, report.html, gx_results/, data_docs/), prints one line per
failed gate (expectation, observed against expected, failing objects or segments) and exits
0 when every gate passed, 1 when a gate failed, 2 when the input or configuration is unusable.
"""
from __future__ import annotations

import argparse
import sys


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "gates", help="run the release gates (Great Expectations) on an annotation output folder",
        description="Validate OUT/stats/*.parquet against the gates of infra/gates.yaml (or "
                    "--config merged over it). Writes OUT/validation/ and exits non-zero when a "
                    "gate fails.")
    p.add_argument("out", metavar="OUT", help="annotation output folder (local path or URL)")
    p.add_argument("--config", metavar="FILE", default=None,
                   help="YAML gate overrides, merged over infra/gates.yaml")
    p.add_argument("--no-data-docs", action="store_true",
                   help="skip the Great Expectations Data Docs (faster local check)")
    p.add_argument("--card", action="store_true",
                   help="also print the dataset-card summary (markdown)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from drivetrack.gates import (GateConfigError, GateInputError, card_summary, failure_lines,
                                  run_gates)

    try:
        from drivetrack.commands._progress import progress_bar

        with progress_bar("gates", unit="steps") as progress:
            report = run_gates(args.out, args.config, data_docs=not args.no_data_docs, progress=progress)
    except (GateConfigError, GateInputError) as exc:
        print(f"drivetrack gates: {exc}", file=sys.stderr)
        return 2
    n_fail = len(report.failures)
    for level, s in report.summary().items():
        print(f"{level:8s} {s['passed']:3d} passed {s['failed']:3d} failed")
    for line in failure_lines(report):
        print(line)
    verdict = "PASSED" if report.success else f"FAILED ({n_fail} gate(s))"
    print(f"gates {verdict}; report: {args.out.rstrip('/')}/validation/report.html "
          f"({report.seconds:.1f} s)")
    if args.card:
        print()
        print(card_summary(report))
    return 0 if report.success else 1
