"""``drivetrack annotate``: ingestion, depth and point tracks for the chosen segments."""
from __future__ import annotations

import argparse


def add_parser(sub) -> None:
    p = sub.add_parser(
        "annotate", help="annotate Waymo v2 segments with point tracks",
        description="Ingest Waymo Open Dataset v2 segments, complete depth maps, compute per-object "
                    "point tracks with occlusion, and write DriveTrack/TAPVid-3D files plus statistics "
                    "tables (stats/*.parquet) and run.json under OUT. A failing segment is reported "
                    "and does not stop the others; the exit code is 0 only if every segment succeeded. "
                    "With --workers N each segment runs in its own process; a segment whose process "
                    "dies (crash, OOM killer, kill -9) is retried once in a fresh process, then "
                    "recorded failed. At the end of a run OUT holds no temporary .partial-* files "
                    "and no clip files of failed segments. Run one annotate per OUT at a time.")
    p.add_argument("input", help="source root: local folder, file://, s3:// or gs:// URL "
                                 "holding {split}/{component}/{segment}.parquet")
    p.add_argument("--split", default="training", help="split to read (default: training)")
    p.add_argument("--out", required=True, help="output folder or URL")
    p.add_argument("--segment", action="append", default=None, metavar="ID",
                   help="segment to annotate (repeatable; default: every segment of the split)")
    p.add_argument("--depth", default=None, metavar="METHOD",
                   help="depth completer (default: nearest; see the drivetrack.depth registry)")
    p.add_argument("--workers", type=int, default=1,
                   help="segments annotated in parallel, each in its own process (default 1: in "
                        "this process, no retry)")
    p.add_argument("--threads", type=int, default=None,
                   help="threads per segment for its depth maps, object jobs and per-frame loops (default: the "
                        "available cores divided among the workers, at least 1; output is the same)")
    p.add_argument("--config", default=None, metavar="FILE",
                   help="YAML/JSON annotation config ({track: {...}, refine_poses: bool, refine_options: {...}})")
    p.add_argument("--refine-poses", dest="refine_poses", action="store_true", default=None,
                   help="refine each object's per-frame pose from its own LiDAR before tracking (default: on)")
    p.add_argument("--no-refine-poses", dest="refine_poses", action="store_false",
                   help="turn pose refinement off: use the labelled boxes as they are")
    p.set_defaults(func=run)


def load_config(path: str | None, depth: str | None = None, refine: bool | None = None):
    """An AnnotateConfig from an optional YAML/JSON file plus command-line overrides."""
    import fsspec
    import yaml

    from drivetrack.annotate import AnnotateConfig

    values = {}
    if path:
        with fsspec.open(path, "r") as handle:
            values = yaml.safe_load(handle) or {}
        if not isinstance(values, dict):
            raise ValueError(f"{path}: the annotation config must be a mapping, found {type(values).__name__}")
    values = dict(values)
    track = dict(values.get("track") or {})
    if depth:
        track["depth_completer"] = depth
    values["track"] = track
    if refine is not None:
        values["refine_poses"] = refine
    return AnnotateConfig.from_dict(values)


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from drivetrack.annotate import annotate
    from drivetrack.depth import list_completers
    from drivetrack.names import check_name
    from drivetrack.waymo.reader import list_segments

    console = Console(stderr=True)
    try:
        config = load_config(args.config, args.depth, args.refine_poses)
        if config.depth_method not in list_completers():
            raise ValueError(f"unknown depth completer {config.depth_method!r}; known: {list_completers()}")
        check_name("split", args.split, "--split")
        for segment in args.segment or ():
            check_name("segment", segment, "--segment")
        segments = args.segment or list_segments(args.input, args.split)
    except Exception as error:
        console.print(f"[red]error:[/red] {error}")
        return 2
    if not segments:
        console.print(f"[red]error:[/red] no segments found in {args.input} split {args.split!r}")
        return 2
    failed = []
    with Progress(TextColumn("[bold]annotate"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TextColumn("{task.description}"), console=console) as progress:
        task = progress.add_task("", total=len(segments))

        def on_result(r):
            notes = "".join(
                [f", {r.source_stats['lidar_nonfinite_ranges']:,} NaN/inf lidar ranges dropped"
                 if r.source_stats.get("lidar_nonfinite_ranges") else ""]
                + [f", worker {death} (retried)" for death in (r.worker_deaths if r.status == "done" else ())])
            if r.status == "done":
                progress.console.print(f"[green]done[/green]   {r.segment}: {len(r.files)} files, "
                                       f"{r.num_tracks} tracks{notes}")
            else:
                failed.append(r)
                progress.console.print(f"[red]failed[/red] {r.segment} ({r.stage}): {r.error}")
            progress.advance(task)

        annotate(args.input, args.split, segments, args.out, config, workers=args.workers,
                 on_result=on_result, threads=args.threads)
    console.print(f"{len(segments) - len(failed)}/{len(segments)} segments annotated into {args.out} "
                  f"(tables in {args.out.rstrip('/')}/stats/, provenance in run.json)")
    return 1 if failed else 0
