"""``drivetrack export``: write a release's clips (or an output folder's) as npz files of the field's formats."""
from __future__ import annotations

import argparse


def add_parser(sub) -> None:
    p = sub.add_parser(
        "export", help="write clips as DriveTrack or TAPVid-3D npz files from the v2 tables",
        description="Read the clips tables (clips/{split}/*.parquet) and frames tables of RELEASE_OR_OUT "
                    "(a published release version STORE/NAME/VERSION or an annotation output folder) clip "
                    "by clip and write each clip as an npz file: drivetrack-npz -> "
                    "DIR/tracks/{split}/waymo_{segment}_{CAMERA}_{object_id}.npz (video, tracks, visibles, "
                    "points3d, ...), tapvid3d -> DIR/tapvid3d/{split}/... (TAPVid-3D layout). The files are "
                    "byte for byte those the pipeline's npz writers produce for the same clip "
                    "(docs/formats.md).")
    p.add_argument("source", metavar="RELEASE_OR_OUT", help="release version folder or annotation output folder")
    p.add_argument("--format", dest="formats", action="append", required=True,
                   choices=["drivetrack-npz", "tapvid3d"], help="npz format (repeatable)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder the npz files go under (local path or URL)")
    p.add_argument("--clip", action="append", default=None, metavar="CLIP",
                   help="export only this clip id waymo_{segment}_{CAMERA}_{object_id} (repeatable)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from drivetrack.compact.export import export_clips
    from drivetrack.compact.read import CompactFormatError

    console = Console(stderr=True)
    count = 0

    def on_clip(clip, urls):
        nonlocal count
        count += 1

    try:
        written = export_clips(args.source, args.formats, args.out, set(args.clip) if args.clip else None,
                               on_clip=on_clip)
    except (CompactFormatError, FileNotFoundError, ValueError, OSError) as error:
        console.print(f"[red]error:[/] {error}")
        return 1
    console.print(f"exported {count} clip(s) as {len(written)} file(s) under {args.out}")
    return 0
