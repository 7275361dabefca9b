"""``drivetrack publish DIR --store STORE --version V``: publish an annotation output folder as a release."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from drivetrack.commands._release_common import (EXIT_CODES_HELP, EXIT_FAILED, EXIT_GATES_FAILED,
                                                 add_store_options, print_json, run_store_command,
                                                 storage_options)


def add_parser(sub) -> None:
    p = sub.add_parser("publish", help="publish an annotation output folder as an immutable, versioned release",
                       description="Stage, check and commit DIR as {STORE}/{dataset}/{version}/ "
                                   "(manifest.json written last; latest/versions updated by compare-and-swap).",
                       epilog=EXIT_CODES_HELP)
    p.add_argument("dir", help="annotation output folder (run.json, clips/{split}/*.parquet, frames/{split}/*.parquet, stats/*.parquet, ...); "
                               "links, hidden files and files outside the output contract are refused")
    p.add_argument("--store", default="./store", help="store URL: folder, s3://bucket/prefix or gs://bucket/prefix")
    p.add_argument("--version", required=True, dest="release_version", help="semantic version, e.g. 1.0.0")
    p.add_argument("--config", default=None, help="YAML/JSON file recorded in the manifest (key 'card' overrides card fields)")
    p.add_argument("--gates-config", default=None, help="gate configuration for drivetrack.gates (default infra/gates.yaml)")
    p.add_argument("--gate-report", default=None,
                   help="use this gate report JSON (DIR/validation/gates.json written by `drivetrack gates DIR`) "
                        "instead of running the gates; refused unless its binding (sha256 of the statistics "
                        "tables and of every clip file) matches DIR")
    p.add_argument("--accept-failed-gates", default=None, metavar="REASON",
                   help="publish even if gates failed; REASON is recorded in the manifest and the card")
    p.add_argument("--resume", action="store_true", help="resume an interrupted publish of this version")
    p.add_argument("--npz", action="store_true",
                   help="also publish the clips as DriveTrack and TAPVid-3D npz files, exported from the tables "
                        "into DIR first (drivetrack export); without it npz files in DIR are left out")
    p.add_argument("--workers", type=int, default=8, help="concurrent uploads/hashes")
    add_store_options(p)
    p.set_defaults(func=run)


def _load_config(path: str | None) -> dict | None:
    if path is None:
        return None
    text = Path(path).read_text()
    if path.endswith(".json"):
        return json.loads(text)
    import yaml

    cfg = yaml.safe_load(text)
    if not isinstance(cfg, dict):
        raise ValueError(f"{path}: the config must be a mapping, found {type(cfg).__name__}")
    return cfg


def _gate_report(args) -> dict | None:
    """``--gate-report FILE`` if given; None makes publish_release run the gates itself."""
    if not args.gate_report:
        return None
    report = json.loads(Path(args.gate_report).read_text())
    if not isinstance(report, dict):
        raise ValueError(f"{args.gate_report}: a gate report must be a JSON object")
    return report


def run(args) -> int:
    from drivetrack.release import GatesFailedError, ReleaseError

    def locate(cause):  # a local source file that cannot be read is the source's problem
        name = getattr(cause, "filename", None)
        src = str(Path(args.dir).resolve())
        if isinstance(name, str) and (name == src or name.startswith(src + "/")):
            return "source", args.dir
        return None

    return run_store_command(
        "publish", args.store, lambda: _run(args),
        [(GatesFailedError, EXIT_GATES_FAILED), ((ReleaseError, ValueError, OSError), EXIT_FAILED)],
        after_unreachable="nothing was published; when it is reachable, run the same command with --resume "
                          "(or `drivetrack gc` to clean up)", locate=locate)


def _run(args) -> int:
    from drivetrack.release import publish_release

    from drivetrack.commands._progress import progress_bar

    config = _load_config(args.config)
    with progress_bar("publish", enabled=not args.json) as progress:
        result = publish_release(
            args.dir, args.store, args.release_version, dataset=args.dataset,
            storage_options=storage_options(args), gate_report=_gate_report(args),
            gates_config=args.gates_config,
            accept_failed_gates=args.accept_failed_gates, config=config, resume=args.resume,
            workers=args.workers, progress=progress, publish_npz=args.npz)
    if args.json:
        print_json(result.__dict__)
    else:
        print(f"published {result.version_url}: {result.files} files, {result.bytes / 1e6:.1f} MB, "
              f"{result.mb_per_s:.1f} MB/s, manifest sha256 {result.manifest_sha256}"
              + (f", {result.reused_files} reused" if result.reused_files else "")
              + (f"; latest = {result.latest}" if result.latest else ""))
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    return 0
