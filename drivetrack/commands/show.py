"""``drivetrack show``: draw a clip's point tracks as a contact sheet (PNG) or a short clip (MP4/GIF)."""
from __future__ import annotations

import argparse


def add_parser(sub) -> None:
    p = sub.add_parser(
        "show", help="draw point tracks over a clip: contact sheet PNG or MP4/GIF clip",
        description="Draw K sampled tracks of one clip over its frames: visible points as filled dots, "
                    "occluded points as crosses, trails of the last frames, one colour per track. "
                    "FILE_OR_RELEASE is a DriveTrack clip (.npz) or a folder (annotation output or "
                    "release version) whose clips tables (clips/*/*.parquet) are searched (folders without "
                    "them: waymo_*.npz files); without --object the clip with the most tracks is shown. With --source SRC (the Waymo v2 source root), --depth-panel adds "
                    "the recomputed depth map beside each frame and --errors (synthetic sources) colours "
                    "each point by its pixel error against the exact ground truth and rings wrong "
                    "occlusion flags.")
    p.add_argument("source_file", metavar="FILE_OR_RELEASE", help="clip .npz file or folder (local path or URL)")
    p.add_argument("--out", action="append", required=True, metavar="OUT",
                   help="output: .png/.jpg contact sheet, .mp4/.gif clip (repeatable)")
    p.add_argument("--object", dest="object_id", default=None, metavar="ID",
                   help="laser object id (use --object=ID when the id starts with '-')")
    p.add_argument("--camera", default=None, help="camera name (FRONT, FRONT_LEFT, ...) when the object has several")
    p.add_argument("--frames", default=None, metavar="A:B", help="clip frames, Python slice (default all)")
    p.add_argument("--points", type=int, default=32, metavar="K", help="tracks drawn (default 32)")
    p.add_argument("--trail", type=int, default=8, help="trail length in frames (default 8, 0 = none)")
    p.add_argument("--sheet-frames", type=int, default=6, metavar="N",
                   help="frames on a contact sheet, spread over --frames (default 6)")
    p.add_argument("--columns", type=int, default=None, help="contact sheet columns (default 3, 2 with depth)")
    p.add_argument("--fps", type=float, default=10.0, help="clip frame rate (default 10, Waymo's rate)")
    p.add_argument("--seed", type=int, default=0, help="seed of the track sampling (default 0)")
    p.add_argument("--source", default=None, metavar="SRC",
                   help="Waymo v2 source root the clip was annotated from (for --depth-panel, --errors)")
    p.add_argument("--depth-panel", action="store_true", help="add the recomputed depth map beside each frame")
    p.add_argument("--depth", default="nearest", metavar="METHOD", help="depth completer for the panel (default nearest)")
    p.add_argument("--errors", action="store_true",
                   help="error view against the synthetic ground truth under --source")
    p.add_argument("--split", default=None, help="split of the clip (default: the clip file's folder name)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import posixpath

    from rich.console import Console

    from drivetrack import show

    console = Console(stderr=True)
    outs = [str(o) for o in args.out]
    bad = [o for o in outs if posixpath.splitext(o)[1].lower() not in (".png", ".jpg", ".jpeg", ".mp4", ".gif")]
    if bad:
        console.print(f"[red]error:[/] --out {bad[0]!r}: use .png/.jpg (contact sheet) or .mp4/.gif (clip)")
        return 2
    if (args.depth_panel or args.errors) and not args.source:
        console.print("[red]error:[/] --depth-panel and --errors need --source SRC (the source root of the clip)")
        return 2
    try:
        url = show.select_clip(args.source_file, args.object_id, args.camera)
        clip = show.load_clip(url)
        if args.split:
            clip.split = args.split
        frames = show.parse_frames(args.frames, clip.num_frames)
        index = show.sample_tracks(clip, args.points, frames, seed=args.seed)
        depth = show.clip_depth(clip, args.source, frames, args.depth) if args.depth_panel else None
        errors = show.error_view(clip, args.source, args.split) if args.errors else None
    except (OSError, ValueError, KeyError, LookupError) as error:
        console.print(f"[red]error:[/] {error}")
        return 2
    console.print(f"clip {url}: {clip.num_tracks} tracks, {clip.num_frames} frames; drawing {index.size} "
                  f"tracks over frames {int(frames[0])}..{int(frames[-1])}")
    if errors is not None:
        s = errors.summary(frames)
        console.print(f"errors vs ground truth: matched {s['matched_fraction']:.1%} of tracks, median "
                      f"{s['median_error_px']:.3f} px, p90 {s['p90_error_px']:.3f} px, wrong occlusion flags "
                      f"{s['wrong_flag_fraction']:.2%}")
    for out in outs:
        try:
            if posixpath.splitext(out)[1].lower() in (".mp4", ".gif"):
                images = show.render_video(clip, index, frames, trail=args.trail, depth=depth, errors=errors)
                show.write_video(out, images, fps=args.fps)
            else:
                sheet = show.render_sheet(clip, index, frames, count=args.sheet_frames, columns=args.columns,
                                          trail=args.trail, depth=depth, errors=errors)
                show.write_image(out, sheet)
        except (OSError, ValueError) as error:
            console.print(f"[red]error:[/] {error}")
            return 1
        print(out)
    return 0
