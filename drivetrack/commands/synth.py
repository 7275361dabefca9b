"""``drivetrack synth OUT``: procedural driving segments in the Waymo v2 schema + exact truth."""
from __future__ import annotations

import sys


def add_parser(sub) -> None:
    p = sub.add_parser(
        "synth", help="generate synthetic Waymo v2 segments with exact ground truth",
        description="Ray-cast procedural driving scenes (textured road, moving/parked vehicles, "
                    "pedestrians, a sign) into OUT/SPLIT/COMPONENT/SEGMENT.parquet in the official "
                    "v2 schema, and write exact ground truth (lidar-hit tracks, visibility, dense "
                    "depth, object poses) to OUT/SPLIT/drivetrack_ground_truth/SEGMENT/. "
                    "Same seed, same bytes.")
    p.add_argument("out", help="output root (local path or fsspec URL)")
    p.add_argument("--segments", type=int, default=1, help="number of segments (default 1)")
    p.add_argument("--seed", type=int, default=7, help="world seed (default 7)")
    p.add_argument("--frames", type=int, default=40, help="frames per segment at 10 Hz (default 40)")
    p.add_argument("--preset", choices=["small", "medium", "full"], default="small",
                   help="small: 480x320 cameras, TOP 32x650 (tests); medium: 960x640 cameras, Waymo's "
                        "lidars; full: Waymo sizes")
    p.add_argument("--split", default="training", choices=["training", "validation", "testing"])
    p.add_argument("--cameras", default="FRONT,FRONT_LEFT,FRONT_RIGHT",
                   help="comma-separated camera names (FRONT, FRONT_LEFT, FRONT_RIGHT, SIDE_LEFT, "
                        "SIDE_RIGHT)")
    p.add_argument("--box-noise", type=float, default=0.0, metavar="M",
                   help="sigma (metres) of Gaussian noise on the WRITTEN box centres; the ground "
                        "truth stays exact")
    p.add_argument("--heading-noise-deg", type=float, default=None,
                   help="sigma (degrees) of heading noise on written boxes (default: 1 degree per "
                        "5 cm of --box-noise)")
    p.add_argument("--rolling-shutter", action="store_true",
                   help="rolling-shutter cameras: real readout direction per camera (FRONT "
                        "top-to-bottom, FRONT_LEFT right-to-left, FRONT_RIGHT left-to-right), "
                        "33 ms readout, every pixel rendered at its own capture time, truth "
                        "solved with the same timing (default: global shutter)")
    p.add_argument("--world", choices=["default", "hard"], default="default",
                   help="hard: add the cases that break depth-ratio occlusion tests and frame-time "
                        "projection (oblique cars 20-70 m away, a car hidden behind a van, poles and "
                        "a low sign, pedestrians by cars, cars passing close beside the ego, a "
                        "turning car, a crossing cyclist); cameras then fire as the sweep passes "
                        "them (docs/synthetic.md)")
    p.add_argument("--camera-trigger", choices=["frame", "sweep"], default=None,
                   help="frame: every image at the frame time; sweep: each camera fires when the "
                        "TOP sweep crosses its axis (default: sweep in the hard world, else frame)")
    p.add_argument("--label-time", choices=["frame", "sweep"], default="frame",
                   help="lidar_box at the frame time (default) or where the object was when the "
                        "TOP sweep passed it")
    p.add_argument("--car-shape", choices=["box", "cabin", "rounded"], default="box",
                   help="box: every vehicle is its label box (default); cabin: a lower body and a "
                        "narrower, shorter cabin on it, the label box their bounding box (bonnet "
                        "and boot below the glasshouse: faces the box does not have, and empty "
                        "corners inside the label box); rounded: the cabin car with the body's "
                        "corners rounded in plan view")
    p.add_argument("--pedestrian-shape", choices=["box", "body"], default="box",
                   help="box: every pedestrian is its label box (default); body: legs mid-stride, a "
                        "torso, swinging arms and a head, the label box their bounding box (a near "
                        "leg hides the far one: faces the camera sees turned to it yet hidden)")
    p.add_argument("--speed-changes", type=float, default=0.0, metavar="MPS2",
                   help="moving vehicles and cyclists brake and speed up with accelerations up to "
                        "this (m/s^2, periods of 4-8 s); 0 (default): every mover keeps its speed")
    p.add_argument("--range-noise", type=float, default=0.0, metavar="M",
                   help="sigma (metres) of Gaussian noise on every written lidar range, as real "
                        "returns carry (each return moves along its ray; the ground truth keeps the "
                        "point where the ray hit); 0 (default): exact ranges")
    p.add_argument("--rear-axle", type=float, default=0.0, metavar="FRACTION",
                   help="moving vehicles and cyclists drive on their rear axle, this fraction of "
                        "their length behind the box centre (about 0.3 for a car): on a turn the "
                        "centre slips sideways, as real cars' do; 0 (default): the centre follows "
                        "the path")
    p.add_argument("--box-slack", type=float, default=0.0, metavar="M",
                   help="every written box is drawn this much wider than its object on each side "
                        "(metres), as hand-drawn labels are; 0 (default): the object's extent")
    p.add_argument("--workers", type=int, default=1, help="threads rendering cameras (default 1)")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from drivetrack.synth import SynthConfig, generate_segment
    from drivetrack.synth.sensors import _CAMERAS

    console = Console(stderr=True)
    cameras = tuple(c.strip().upper() for c in args.cameras.split(",") if c.strip())
    bad = [c for c in cameras if c not in _CAMERAS]
    if bad or not cameras:
        console.print(f"[red]error:[/] unknown camera(s) {bad or args.cameras!r}; "
                      f"choose from {', '.join(_CAMERAS)}")
        return 2
    if args.segments < 1 or args.frames < 1:
        console.print(f"[red]error:[/] --segments and --frames must be >= 1 "
                      f"(got {args.segments}, {args.frames})")
        return 2
    if args.box_noise < 0:
        console.print(f"[red]error:[/] --box-noise must be >= 0 (got {args.box_noise})")
        return 2
    if not 0 <= args.box_slack <= 0.5:
        console.print(f"[red]error:[/] --box-slack must be in [0, 0.5] m (got {args.box_slack})")
        return 2
    if not 0 <= args.range_noise <= 0.5:
        console.print(f"[red]error:[/] --range-noise must be in [0, 0.5] m (got {args.range_noise})")
        return 2
    if not 0 <= args.speed_changes < 20:
        console.print(f"[red]error:[/] --speed-changes must be in [0, 20) m/s^2 (got {args.speed_changes})")
        return 2
    if not 0 <= args.rear_axle < 0.5:
        console.print(f"[red]error:[/] --rear-axle must be in [0, 0.5) (got {args.rear_axle})")
        return 2
    config = SynthConfig(
        seed=args.seed, frames=args.frames, preset=args.preset, cameras=cameras, split=args.split,
        box_noise_m=args.box_noise, rolling_shutter=args.rolling_shutter, world=args.world,
        camera_trigger=args.camera_trigger, label_time=args.label_time, car_shape=args.car_shape,
        pedestrian_shape=args.pedestrian_shape,
        speed_changes_mps2=args.speed_changes, range_noise_m=args.range_noise, rear_axle_fraction=args.rear_axle,
        box_slack_m=args.box_slack,
        heading_noise_rad=None if args.heading_noise_deg is None else float(np.deg2rad(args.heading_noise_deg)))
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                  TimeElapsedColumn(), console=console) as progress:
        for index in range(args.segments):
            tasks = {}

            def report(stage, done, total, index=index, tasks=tasks):
                if stage not in tasks:
                    tasks[stage] = progress.add_task(f"segment {index + 1}/{args.segments} {stage}", total=total)
                progress.update(tasks[stage], completed=done)

            summary = generate_segment(args.out, config, index, progress=report, workers=args.workers)
            gt_mb = sum(summary["ground_truth_bytes"].values()) / 1e6
            progress.console.print(
                f"wrote segment [bold]{summary['segment']}[/]: {len(summary['files'])} components "
                f"under {args.out}/{args.split}/, {summary['num_frames']} frames, "
                f"{summary['num_objects']} objects, {summary['num_object_returns']} object returns; "
                f"ground truth {gt_mb:.1f} MB in {summary['ground_truth']}")
    shutter = "rolling" if args.rolling_shutter else "global"
    print(f"{args.segments} segment(s) written to {args.out} (split {args.split}, seed {args.seed}, "
          f"preset {args.preset}, {shutter} shutter"
          + (f", world {config.world}, cameras at {config.trigger} time, lidar_box at {config.label_time} time"
             if config.extended_truth else "")
          + (f", {config.car_shape} vehicles" if config.car_shape != "box" else "")
          + (f", {config.pedestrian_shape} pedestrians" if config.pedestrian_shape != "box" else "")
          + (f", speed changes up to {config.speed_changes_mps2:g} m/s^2" if config.speed_changes_mps2 else "")
          + (f", {config.range_noise_m * 100:g} cm range noise" if config.range_noise_m else "")
          + (f", labels {config.box_slack_m * 100:g} cm wide of their objects" if config.box_slack_m else "")
          + (f", rear axles {config.rear_axle_fraction:g} of the length behind the centre"
             if config.rear_axle_fraction else "")
          + ")", file=sys.stdout)
    return 0
