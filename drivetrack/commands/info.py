"""``drivetrack info ROOT``: what a Waymo v2 split holds, per segment, without decoding images."""
from __future__ import annotations

import json
import sys


def add_parser(sub) -> None:
    p = sub.add_parser(
        "info", help="summarise Waymo v2 segments: frames, cameras, lidars, objects",
        description="Per segment: frame count and time span, cameras with image sizes, lasers with "
                    "the number of valid returns per return and of NaN/inf ranges (dropped by "
                    "annotate), labelled objects by type. Reads "
                    "ROOT/SPLIT/COMPONENT/SEGMENT.parquet (local path, file://, s3://, gs://).",
        epilog="exit codes: 0 ok; 1 some segment could not be summarised; 2 bad input (no such split, "
               "bad --storage-option); 4 cannot reach ROOT (connection, credentials, permission)")
    p.add_argument("root", help="dataset root URL or path (the folder that holds the splits)")
    p.add_argument("--split", default="training", help="training, validation or testing")
    p.add_argument("--segment", action="append", default=None,
                   help="segment id (repeatable); default: every segment of the split")
    p.add_argument("--json", action="store_true", help="print JSON for machines")
    p.add_argument("--storage-option", action="append", default=[], metavar="KEY=VALUE",
                   help="fsspec storage option, e.g. endpoint_url=http://127.0.0.1:9000 or "
                        "anon=true (repeatable; values are parsed as JSON when possible)")
    p.set_defaults(func=run)


def parse_storage_options(pairs: list[str]) -> dict:
    """``["k=v", ...]`` -> dict; values parsed as JSON when they are (``true``, ``3``)."""
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise ValueError(f"storage option {pair!r} is not KEY=VALUE")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def run(args) -> int:
    from drivetrack.commands._release_common import EXIT_BAD_INPUT, run_store_command

    return run_store_command("info", args.root, lambda: _run(args), [((ValueError, OSError), EXIT_BAD_INPUT)],
                             what="dataset root")


def _run(args) -> int:
    from drivetrack.commands._release_common import unreachable_cause
    from drivetrack.names import InvalidNameError
    from drivetrack.waymo.components import WaymoFormatError, list_segments
    from drivetrack.waymo.summary import segment_summary

    try:
        options = parse_storage_options(args.storage_option)
        segments = args.segment or list_segments(args.root, args.split, storage_options=options)
    except (ValueError, OSError) as exc:
        if unreachable_cause(exc) is not None:
            raise
        print(f"drivetrack info: {exc}", file=sys.stderr)
        return 2
    summaries, failed = [], 0
    for segment in segments:
        try:
            summaries.append(segment_summary(args.root, args.split, segment, storage_options=options))
        except (WaymoFormatError, InvalidNameError, OSError) as exc:
            if unreachable_cause(exc) is not None:
                raise  # one line for the whole command, not one error per segment
            failed += 1
            summaries.append({"segment": segment, "split": args.split, "error": str(exc)})
    if args.json:
        json.dump({"root": args.root, "split": args.split, "segments": summaries}, sys.stdout,
                  indent=2)
        print()
    else:
        _print_tables(args.root, args.split, summaries)
    return 1 if failed else 0


def _print_tables(root: str, split: str, summaries: list[dict]) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console()
    console.print(f"[bold]{root}[/bold] split [bold]{split}[/bold]: {len(summaries)} segment(s)")
    for s in summaries:
        if "error" in s:
            console.print(f"[red]{s['segment']}: {s['error']}[/red]")
            continue
        console.print(f"\n[bold]{s['segment']}[/bold]: {s['num_frames']} frames, "
                      f"{s['duration_s']:.2f} s ({s['start_micros']} .. {s['end_micros']} us)")
        cams = Table("camera", "width", "height", "images", title="cameras", title_justify="left")
        for name, c in s["cameras"].items():
            cams.add_row(name, str(c["width"]), str(c["height"]), str(c["images"]))
        lasers = Table("laser", "range image", "frames", "valid return 1", "valid return 2",
                       "NaN/inf ranges", title="lasers", title_justify="left")
        for name, l in s["lasers"].items():
            shape = "x".join(str(d) for d in l["shape"]) if l["shape"] else "-"
            lasers.add_row(name, shape, str(l["frames"]), f"{l['valid_return1']:,}",
                           f"{l['valid_return2']:,}",
                           f"{l['nonfinite_return1'] + l['nonfinite_return2']:,}")
        objects = Table("type", "objects", "boxes", title="objects (lidar_box)", title_justify="left")
        for name, o in s["objects"].items():
            objects.add_row(name, str(o["objects"]), str(o["boxes"]))
        for table in (cams, lasers, objects):
            console.print(table)
