"""``drivetrack versions STORE``: list the published versions of a dataset."""
from __future__ import annotations

from drivetrack.commands._release_common import (EXIT_BAD_INPUT, EXIT_CODES_HELP, EXIT_FAILED,
                                                 add_store_options, check_dataset_arg, print_json,
                                                 run_store_command, storage_options)


def add_parser(sub) -> None:
    p = sub.add_parser("versions", help="list the published versions of a dataset in a store",
                       epilog=EXIT_CODES_HELP)
    p.add_argument("store", help="store URL")
    add_store_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from drivetrack.release import ReleaseError

    return run_store_command("versions", args.store, lambda: _run(args),
                             [(ValueError, EXIT_BAD_INPUT), ((ReleaseError, OSError), EXIT_FAILED)])


def _run(args) -> int:
    from drivetrack.release import list_versions

    check_dataset_arg(args)
    versions = list_versions(args.store, args.dataset, storage_options=storage_options(args))
    if args.json:
        print_json(versions)
        return 0
    if not versions:
        print(f"no published versions of {args.dataset} in {args.store}")
    for v in versions:
        flags = " (latest)" if v["latest"] else ""
        flags += "" if v["indexed"] else " (not in versions.json: run drivetrack gc)"
        print(f"{v['version']:<16} {v['created']}  {v['files']:>7} files  {v['bytes'] / 1e6:>10.1f} MB  "
              f"{v['manifest_sha256'][:16]}{flags}")
    return 0
