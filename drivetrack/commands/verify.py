"""``drivetrack verify STORE --version V``: re-hash a release against its manifest."""
from __future__ import annotations

import sys

from drivetrack.commands._release_common import add_store_options, print_json, storage_options


def add_parser(sub) -> None:
    p = sub.add_parser("verify", help="re-hash every file of a release against its manifest",
                       description="Streams and hashes every file concurrently; reports missing, extra and "
                                   "corrupt files; exits 1 on any mismatch, 2 if the version is not published.")
    p.add_argument("store", help="store URL")
    p.add_argument("--version", required=True, dest="release_version", help="version to verify, or 'latest'")
    p.add_argument("--workers", type=int, default=8)
    add_store_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from drivetrack.release import ManifestError, ReleaseError, VersionNotFoundError, verify_release

    try:
        report = verify_release(args.store, args.release_version, args.dataset,
                                storage_options=storage_options(args), workers=args.workers)
    except (VersionNotFoundError, ManifestError) as e:
        print(f"drivetrack verify: {type(e).__name__}: {e}", file=sys.stderr)
        return 2
    except (ReleaseError, OSError, ValueError) as e:
        print(f"drivetrack verify: {type(e).__name__}: {e}", file=sys.stderr)
        return 2
    if args.json:
        print_json(report.to_json())
    else:
        for p in report.missing:
            print(f"MISSING  {p}")
        for p in report.extra:
            print(f"EXTRA    {p}")
        for c in report.corrupt:
            print(f"CORRUPT  {c['path']}: {c['problem']} expected {c['expected']}, found {c['found']}")
        verdict = "OK" if report.ok else "FAILED"
        print(f"{verdict}: {report.url}: {report.files_checked} files, {report.bytes / 1e6:.1f} MB in "
              f"{report.seconds:.2f} s ({report.mb_per_s:.0f} MB/s); {len(report.missing)} missing, "
              f"{len(report.extra)} extra, {len(report.corrupt)} corrupt")
    return 0 if report.ok else 1
