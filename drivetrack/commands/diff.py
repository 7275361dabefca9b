"""``drivetrack diff STORE V1 V2``: files added, removed and changed, and statistic deltas."""
from __future__ import annotations

from drivetrack.commands._release_common import (EXIT_BAD_INPUT, EXIT_CODES_HELP, add_store_options,
                                                 check_dataset_arg, print_json, run_store_command,
                                                 storage_options)


def add_parser(sub) -> None:
    p = sub.add_parser("diff", help="compare two published versions (files and statistics)",
                       epilog=EXIT_CODES_HELP)
    p.add_argument("store", help="store URL")
    p.add_argument("old", help="older version")
    p.add_argument("new", help="newer version")
    add_store_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from drivetrack.release import ReleaseError

    return run_store_command("diff", args.store, lambda: _run(args),
                             [((ReleaseError, OSError, ValueError), EXIT_BAD_INPUT)])


def _run(args) -> int:
    from drivetrack.release import diff_versions

    check_dataset_arg(args)
    d = diff_versions(args.store, args.old, args.new, args.dataset, storage_options=storage_options(args))
    if args.json:
        print_json(d.to_json())
        return 0
    print(f"{args.dataset} {d.old} -> {d.new}: {len(d.added)} added, {len(d.removed)} removed, "
          f"{len(d.changed)} changed, {d.unchanged} unchanged")
    for tag, paths in (("+", d.added), ("-", d.removed), ("~", d.changed)):
        for p in paths:
            print(f"{tag} {p}")
    for k, v in d.deltas.items():
        delta = "" if v["delta"] is None else f" ({v['delta']:+g})"
        print(f"  {k}: {v['old']} -> {v['new']}{delta}")
    return 0
