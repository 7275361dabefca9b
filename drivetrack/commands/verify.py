"""``drivetrack verify STORE --version V``: re-hash a release against its manifest."""
from __future__ import annotations

from drivetrack.commands._release_common import (EXIT_BAD_INPUT, EXIT_CODES_HELP, EXIT_FAILED, EXIT_OK,
                                                 add_store_options, check_dataset_arg, print_json,
                                                 run_store_command, storage_options)


def add_parser(sub) -> None:
    p = sub.add_parser("verify", help="re-hash every file of a release against its manifest",
                       description="Streams and hashes every file concurrently; reports missing, extra and "
                                   "corrupt files.", epilog=EXIT_CODES_HELP)
    p.add_argument("store", help="store URL")
    p.add_argument("--version", required=True, dest="release_version", help="version to verify, or 'latest'")
    p.add_argument("--workers", type=int, default=8)
    add_store_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from drivetrack.release import ReleaseError

    return run_store_command("verify", args.store, lambda: _run(args),
                             [((ReleaseError, OSError, ValueError), EXIT_BAD_INPUT)])


def _run(args) -> int:
    from drivetrack.release import verify_release

    check_dataset_arg(args)
    from drivetrack.commands._progress import progress_bar

    with progress_bar("verify", enabled=not args.json) as progress:
        report = verify_release(args.store, args.release_version, args.dataset,
                                storage_options=storage_options(args), workers=args.workers,
                                progress=progress)
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
    return EXIT_OK if report.ok else EXIT_FAILED
