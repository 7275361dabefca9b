"""``drivetrack evaluate``: score annotations against synthetic truth, or a tracker against a release."""
from __future__ import annotations

import argparse
import json
import sys


def add_parser(sub) -> None:
    p = sub.add_parser(
        "evaluate", help="score annotations vs synthetic truth, or tracker predictions vs a release",
        description="With --truth SRC: score the annotation folder OUT against the exact ground truth "
                    "that `drivetrack synth` wrote beside SRC (TAP-Vid metrics in query modes first and "
                    "strided, pixel error, track purity, recall). With --predictions DIR: score a "
                    "tracker's npz files (same names as the clips; tracks [N,T,2] and visibles or "
                    "occluded [N,T], bool or 0/1) against the release or annotation folder as ground truth; "
                    "headers are checked before data is read, and NaN/inf positions count as misses "
                    "(+inf px) and are reported. "
                    "See docs/evaluation.md.")
    p.add_argument("input", metavar="OUT_OR_RELEASE", help="annotation output or release folder (path or URL)")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--truth", metavar="SRC", help="synthetic source root holding {split}/drivetrack_ground_truth/")
    what.add_argument("--predictions", metavar="DIR", help="folder of a tracker's predictions, one npz per clip")
    p.add_argument("--split", default=None, help="only clips of this split (default: every split found)")
    p.add_argument("--stride", type=int, default=5, help="query stride of the strided mode (default 5)")
    p.add_argument("--resize", default=None, metavar="WxH",
                   help="with --predictions: rescale pixels to WxH before scoring (TAP-Vid uses 256x256)")
    p.add_argument("--allow-missing", action="store_true",
                   help="with --predictions: skip clips that have no prediction instead of failing")
    p.add_argument("--json", action="store_true", help="print the summary and tables as JSON")
    p.add_argument("--out", default=None, metavar="FILE",
                   help="also write the result: .json (summary + tables), .csv or .parquet (per-clip table)")
    p.set_defaults(func=run)


def _parse_size(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--resize {text!r} is not WxH, e.g. 256x256") from None
    if width < 1 or height < 1:
        raise ValueError(f"--resize {text!r}: width and height must be positive")
    return width, height


def write_result(result, path: str) -> None:
    """Write an Evaluation to ``path`` by extension (.json, .csv, .parquet), through fsspec."""
    import fsspec

    if path.endswith(".json"):
        with fsspec.open(path, "w") as handle:
            json.dump(result.to_json(), handle, indent=2)
    elif path.endswith(".csv"):
        with fsspec.open(path, "w") as handle:
            result.clips.to_csv(handle, index=False)
    elif path.endswith(".parquet"):
        with fsspec.open(path, "wb") as handle:
            result.clips.to_parquet(handle, index=False)
    else:
        raise ValueError(f"--out {path}: unknown extension; use .json, .csv or .parquet")


def _fmt(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and value != value):
        return "-"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def print_tables(result, console) -> None:
    from rich.table import Table

    summary = result.summary
    truth_mode = summary["kind"] == "annotations_vs_truth"
    title = ("annotations vs exact synthetic truth" if truth_mode else "predictions vs release") + \
        f": {summary['num_clips']} clips, {summary['num_objects']} objects, {summary['num_tracks']:,} tracks"
    table = Table(title=title)
    for column in ("mode", "queries", "OA", "<1", "<2", "<4", "<8", "<16", "AJ", "δ_avg"):
        table.add_column(column, justify="right")
    for mode, m in summary["modes"].items():
        table.add_row(mode, f"{m['num_queries']:,}", _fmt(m["occlusion_accuracy"]),
                      *(_fmt(m[f"pts_within_{d}"]) for d in (1, 2, 4, 8, 16)),
                      _fmt(m["average_jaccard"]), _fmt(m["average_pts_within_thresh"]))
    console.print(table)
    line = (f"pixel error at truth-visible frames: median {_fmt(summary['pixel_error_median'])} px, "
            f"mean {_fmt(summary['pixel_error_mean'])} px, p95 {_fmt(summary['pixel_error_p95'])} px")
    nonfinite = summary.get("num_nonfinite_at_visible", 0)
    if nonfinite:
        what = "track positions" if truth_mode else "predictions"
        line += (f"\n[bold red]non-finite {what}: {nonfinite:,} point-frames in {summary['num_clips_nonfinite']:,} "
                 f"clips[/] (of {summary['num_gt_visible_points']:,} truth-visible; NaN/inf counted as misses and "
                 f"as +inf px above)")
    if truth_mode:
        line += (f"\npurity {_fmt(summary['purity'], 4)} ({summary['num_unmatched']:,} tracks from ground/background, "
                 f"{summary['num_other_object']:,} from other objects); recall {_fmt(summary['recall'])} of the "
                 f"objects' LiDAR hits ({_fmt(summary['recall_visible'])} of those visible in the camera)")
    console.print(line)
    first = result.clips[result.clips["query_mode"] == result.clips["query_mode"].iloc[0]] \
        if not result.clips.empty else result.clips
    clips = Table(title=f"per clip ({first['query_mode'].iloc[0] if len(first) else '-'} mode)")
    columns = ["segment", "camera", "object", "tracks", "OA", "AJ", "δ_avg", "px med"]
    if nonfinite:
        columns.append("non-finite")
    if truth_mode:
        columns += ["purity", "recall"]
    for column in columns:
        clips.add_column(column, justify="left" if column in ("segment", "camera", "object") else "right")
    for row in first.to_dict("records"):
        cells = [row["segment"], row["camera"], row["object_id"], f"{row['num_tracks']:,}",
                 _fmt(row["occlusion_accuracy"]), _fmt(row["average_jaccard"]),
                 _fmt(row["average_pts_within_thresh"]), _fmt(row["pixel_error_median"], 2)]
        if nonfinite:
            cells.append(f"{row['num_nonfinite_at_visible']:,}")
        if truth_mode:
            cells += [_fmt(row["purity"], 4), _fmt(row["recall"])]
        clips.add_row(*cells)
    console.print(clips)


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from drivetrack.evaluation import evaluate_annotations, score_predictions

    try:
        if args.stride < 1:
            raise ValueError(f"--stride must be >= 1, got {args.stride}")
        if args.truth is not None:
            if args.resize or args.allow_missing:
                raise ValueError("--resize and --allow-missing apply to --predictions only")
            result = evaluate_annotations(args.input, args.truth, split=args.split, stride=args.stride)
        else:
            result = score_predictions(args.input, args.predictions, split=args.split, stride=args.stride,
                                       resize_to=_parse_size(args.resize), allow_missing=args.allow_missing)
        if args.out:
            write_result(result, args.out)
    except (ValueError, OSError, KeyError) as error:
        print(f"drivetrack evaluate: error: {error}", file=sys.stderr)   # unwrapped: paths stay whole
        return 2
    if args.json:
        json.dump(result.to_json(), sys.stdout, indent=2)
        print()
    else:
        print_tables(result, Console())
    return 0
