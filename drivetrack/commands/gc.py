"""``drivetrack gc STORE``: clean up interrupted publishes and repair the versions index / latest pointer."""
from __future__ import annotations

from drivetrack.commands._release_common import (EXIT_BAD_INPUT, EXIT_CODES_HELP, EXIT_FAILED,
                                                 check_dataset_arg, print_json, run_store_command,
                                                 storage_options)


def add_parser(sub) -> None:
    p = sub.add_parser("gc", help="remove interrupted publishes (claims, staging, uncommitted files); repair pointers",
                       description="Never touches committed versions. Claims younger than --older-than seconds "
                                   "are kept (a publish may still be running).", epilog=EXIT_CODES_HELP)
    p.add_argument("store", help="store URL")
    p.add_argument("--dataset", default=None, help="only this dataset (default: every dataset in the store)")
    p.add_argument("--older-than", type=float, default=3600.0, help="seconds; 0 collects every claim")
    p.add_argument("--dry-run", action="store_true", help="only print what would be done")
    p.add_argument("--endpoint-url", default=None, help="S3-compatible endpoint")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=run)


def run(args) -> int:
    from drivetrack.release import ReleaseError

    return run_store_command("gc", args.store, lambda: _run(args),
                             [(ValueError, EXIT_BAD_INPUT), ((ReleaseError, OSError), EXIT_FAILED)])


def _run(args) -> int:
    from drivetrack.release import gc

    check_dataset_arg(args)
    report = gc(args.store, args.dataset, older_than_s=args.older_than, dry_run=args.dry_run,
                storage_options=storage_options(args))
    if args.json:
        print_json(report.__dict__)
        return 0
    for line in report.actions:
        print(line)
    for line in report.skipped_recent:
        print(f"kept (recent): {line}")
    if not report.actions:
        print("nothing to collect")
    return 0
