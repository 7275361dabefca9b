"""Benchmark: load a full-size Waymo v2 segment's LiDAR with drivetrack.waymo.reader.load_scene.

Writes a synthetic segment of real dimensions (TOP 64 x 2650, four 200 x 600 short lidars, both
returns, per-pixel TOP pose, 200 frames; BROTLI like the release) to a scratch folder, then times
``load_scene`` (no cameras). Usage: ``.venv/bin/python bench/bench_waymo_reader.py [--frames N]``.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from drivetrack.waymo import reader
from drivetrack.waymo.summary import segment_summary
from drivetrack.waymo.schema import KEY_LASER, KEY_LASER_OBJECT, KEY_SEGMENT, KEY_TIMESTAMP, component

SEGMENT = "bench_segment"
SIZES = {1: (64, 2650), 2: (200, 600), 3: (200, 600), 4: (200, 600), 5: (200, 600)}
VALID = {1: (0.9, 0.05), 2: (0.3, 0.02), 3: (0.3, 0.02), 4: (0.3, 0.02), 5: (0.3, 0.02)}


def _writer(root: Path, name: str, compression: str):
    comp = component(name)
    path = root / "training" / name / f"{SEGMENT}.parquet"
    path.parent.mkdir(parents=True, exist_ok=True)
    return pq.ParquetWriter(path, comp.arrow_schema(), compression=compression), comp


def _table(comp, cols: dict, n: int) -> pa.Table:
    arrays = []
    for c in comp.columns:
        if c.name == KEY_SEGMENT:
            arrays.append(pa.array([SEGMENT] * n, c.type))
        elif c.name in cols:
            v = cols[c.name]
            arrays.append(v if isinstance(v, pa.Array) else pa.array(v, c.type))
        else:
            arrays.append(pa.nulls(n, c.type))
    return pa.Table.from_arrays(arrays, schema=comp.arrow_schema())


def _list(values: list[np.ndarray], t: pa.DataType) -> pa.Array:
    offsets = np.concatenate([[0], np.cumsum([v.size for v in values])]).astype(np.int32)
    return pa.ListArray.from_arrays(pa.array(offsets), pa.array(np.concatenate(values), t.value_type))


def write_segment(root: Path, frames: int, compression: str) -> float:
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    ts = 1_000_000 + 100_000 * np.arange(frames)
    w, comp = _writer(root, "vehicle_pose", compression)
    poses = np.tile(np.eye(4).reshape(1, 16), (frames, 1))
    poses[:, 3] = np.arange(frames)
    w.write_table(_table(comp, {KEY_TIMESTAMP: ts,
                                comp.col("world_from_vehicle.transform"): poses.tolist()}, frames))
    w.close()
    w, comp = _writer(root, "lidar_calibration", compression)
    ext = np.eye(4)
    ext[2, 3] = 2.0
    w.write_table(_table(comp, {KEY_LASER: list(SIZES),
                                comp.col("extrinsic.transform"): [ext.ravel().tolist()] * 5,
                                comp.col("beam_inclination.min"): [-0.3] * 5,
                                comp.col("beam_inclination.max"): [0.05] * 5}, 5))
    w.close()
    w, comp = _writer(root, "lidar_box", compression)
    w.write_table(_table(comp, {KEY_TIMESTAMP: ts,
                                KEY_LASER_OBJECT: ["a"] * frames,
                                **{comp.col(f"box.{p}.{a}"): [1.0] * frames
                                   for p in ("center", "size") for a in "xyz"},
                                comp.col("box.heading"): [0.0] * frames,
                                comp.col("type"): [1] * frames}, frames))
    w.close()
    lw, lcomp = _writer(root, "lidar", compression)
    pw, pcomp = _writer(root, "lidar_pose", compression)
    list_t = lcomp.by_name[lcomp.col("range_image_return1.values")].type
    for t in range(frames):
        cols = {KEY_TIMESTAMP: [int(ts[t])] * 5, KEY_LASER: list(SIZES)}
        for r in (1, 2):
            vals, shapes = [], []
            for laser, (h, wd) in SIZES.items():
                img = rng.uniform(1, 75, size=(h, wd, 4)).astype(np.float32)
                img[..., 0] *= rng.random((h, wd)) < VALID[laser][r - 1]
                vals.append(img.ravel())
                shapes.append([h, wd, 4])
            cols[lcomp.col(f"range_image_return{r}.values")] = _list(vals, list_t)
            cols[lcomp.col(f"range_image_return{r}.shape")] = shapes
        lw.write_table(_table(lcomp, cols, 5))
        pose = np.zeros((64, 2650, 6), np.float32)
        pose[..., 3] = t + np.linspace(-0.05, 0.05, 2650, dtype=np.float32)[None]
        pw.write_table(_table(pcomp, {
            KEY_TIMESTAMP: [int(ts[t])], KEY_LASER: [1],
            pcomp.col("range_image_return1.values"): _list([pose.ravel()], list_t),
            pcomp.col("range_image_return1.shape"): [[64, 2650, 6]]}, 1))
    lw.close()
    pw.close()
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--compression", default="brotli")
    ap.add_argument("--dir", default=None, help="scratch folder (default: a temporary one)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        root = Path(tmp)
        written = write_segment(root, args.frames, args.compression)
        size = sum(p.stat().st_size for p in root.rglob("*.parquet")) / 1e6
        print(f"wrote {args.frames} frames ({size:.0f} MB, {args.compression}) in {written:.1f} s")
        t0 = time.perf_counter()
        scene = reader.load_scene(str(root), "training", SEGMENT, cameras=())
        seconds = time.perf_counter() - t0
        print(f"load_scene: {len(scene.lidar):,} returns over {scene.num_frames} frames "
              f"in {seconds:.1f} s ({len(scene.lidar) / seconds / 1e6:.1f} M returns/s)")
        t0 = time.perf_counter()
        summary = segment_summary(str(root), "training", SEGMENT)
        print(f"segment_summary (drivetrack info): {time.perf_counter() - t0:.1f} s, "
              f"TOP valid return 1 = {summary['lasers']['TOP']['valid_return1']:,}")


if __name__ == "__main__":
    main()
