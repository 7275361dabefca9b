"""``drivetrack diff STORE V1 V2``: files added, removed and changed, and statistic deltas."""
from __future__ import annotations

import sys

from drivetrack.commands._release_common import add_store_options, print_json, storage_options


def add_parser(sub) -> None:
    p = sub.add_parser("diff", help="compare two published versions (files and statistics)")
    p.add_argument("store", help="store URL")
    p.add_argument("old", help="older version")
    p.add_argument("new", help="newer version")
    add_store_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from drivetrack.release import ReleaseError, diff_versions

    try:
        d = diff_versions(args.store, args.old, args.new, args.dataset, storage_options=storage_options(args))
    except (ReleaseError, OSError, ValueError) as e:
        print(f"drivetrack diff: {type(e).__name__}: {e}", file=sys.stderr)
        return 2
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
