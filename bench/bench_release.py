"""Benchmark: publish and verify throughput (MB/s) on a local store, against `sha256sum` on the same files.

    .venv/bin/python bench/bench_release.py [--files 32] [--mib 16] [--workers 4] [--s3]

Writes random files into a temporary folder, hashes them once with `sha256sum` (one process, all
files; the reference), publishes them with `publish_release` and verifies with `verify_release`.
Page cache is warm for all three (the files were just written), so the numbers compare hashing
and I/O paths, not disks. `--s3` also publishes to a moto server on loopback.
Target (issue 4): verify >= 80% of sha256sum's throughput on a local store.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--files", type=int, default=32)
    ap.add_argument("--mib", type=int, default=16, help="size of each file, MiB")
    ap.add_argument("--workers", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=3, help="best of N for sha256sum and verify")
    ap.add_argument("--s3", action="store_true")
    args = ap.parse_args()

    from drivetrack.release import publish_release, verify_release

    with tempfile.TemporaryDirectory(prefix="bench-release-") as tmp:
        src = Path(tmp) / "src"
        for i in range(args.files):
            d = src / ("training" if i % 2 else "validation")
            d.mkdir(parents=True, exist_ok=True)
            (d / f"clip_{i:04d}.bin").write_bytes(os.urandom(args.mib * 2**20))
        total_mb = args.files * args.mib * 2**20 / 1e6
        files = sorted(str(p) for p in src.rglob("*.bin"))

        ref = []
        for _ in range(args.repeat):
            t = time.perf_counter()
            subprocess.run(["sha256sum", *files], check=True, capture_output=True)
            ref.append(time.perf_counter() - t)
        ref_mbs = total_mb / min(ref)

        t = time.perf_counter()
        publish_release(src, Path(tmp) / "store", "1.0.0", workers=args.workers)
        pub_mbs = total_mb / (time.perf_counter() - t)

        ver = []
        for _ in range(args.repeat):
            report = verify_release(Path(tmp) / "store", "1.0.0", workers=args.workers)
            assert report.ok
            ver.append(report.seconds)
        ver_mbs = report.bytes / 1e6 / min(ver)

        print(f"data: {args.files} files x {args.mib} MiB = {total_mb:.0f} MB, workers={args.workers}, "
              f"cpus={os.cpu_count()}, load={os.getloadavg()[0]:.1f}")
        print(f"sha256sum (1 process):      {ref_mbs:8.0f} MB/s")
        print(f"drivetrack verify (local):  {ver_mbs:8.0f} MB/s  = {ver_mbs / ref_mbs:.0%} of sha256sum")
        print(f"drivetrack publish (local): {pub_mbs:8.0f} MB/s  (copy + hash + re-hash check + rename)")
        if args.s3:
            from s3server import S3Server

            server = S3Server().start()
            try:
                url = f"s3://{server.new_bucket()}/bench"
                opts = server.storage_options()
                t = time.perf_counter()
                publish_release(src, url, "1.0.0", storage_options=opts, workers=args.workers)
                s3_pub = total_mb / (time.perf_counter() - t)
                r = verify_release(url, "1.0.0", storage_options=opts, workers=args.workers)
                print(f"drivetrack publish (moto S3): {s3_pub:6.0f} MB/s")
                print(f"drivetrack verify (moto S3):  {r.mb_per_s:6.0f} MB/s")
            finally:
                server.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
