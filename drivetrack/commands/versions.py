"""``drivetrack versions STORE``: list the published versions of a dataset."""
from __future__ import annotations

import sys

from drivetrack.commands._release_common import add_store_options, print_json, storage_options


def add_parser(sub) -> None:
    p = sub.add_parser("versions", help="list the published versions of a dataset in a store")
    p.add_argument("store", help="store URL")
    add_store_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from drivetrack.release import ReleaseError, list_versions

    try:
        versions = list_versions(args.store, args.dataset, storage_options=storage_options(args))
    except (ReleaseError, OSError) as e:
        print(f"drivetrack versions: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
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
