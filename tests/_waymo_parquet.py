"""Tiny Waymo v2 parquet fixtures for the reader tests, written with plain pyarrow.

``write_component`` writes one component table from the official schema with knobs for other
producers' conventions (list child name, large_list, compression, shuffled rows and columns,
extra columns). ``tiny_segment`` writes a complete, small segment whose geometry is chosen so
expected values can be computed by hand from METHOD.md's formulas.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from drivetrack.waymo.schema import KEY_SEGMENT, component

SEGMENT = "seg_0001"
TIMESTAMPS = [1_000_000, 1_100_000, 1_200_000]


def _retype(t: pa.DataType, list_child: str, large_list: bool) -> pa.DataType:
    if pa.types.is_fixed_size_list(t):
        return pa.list_(pa.field(list_child, t.value_type), t.list_size)
    if pa.types.is_list(t):
        field = pa.field(list_child, t.value_type)
        return pa.large_list(field) if large_list else pa.list_(field)
    return t


def write_component(root, split: str, name: str, segment: str, columns: dict, *,
                    list_child: str = "item", large_list: bool = False, compression="brotli",
                    shuffle_seed: int | None = None, shuffle_columns: bool = False,
                    extra_columns: dict | None = None, drop: tuple = (),
                    override_types: dict | None = None, filename: str | None = None) -> Path:
    """Write ``{root}/{split}/{name}/{segment}.parquet``; unspecified columns are all-null.

    ``columns`` maps full column names to Python lists (``key.segment_context_name`` defaults
    to ``segment``). Returns the file path.
    """
    comp = component(name)
    n = max(len(v) for v in columns.values())
    arrays, fields = [], []
    for col in comp.columns:
        if col.name in drop:
            continue
        t = (override_types or {}).get(col.name) or _retype(col.type, list_child, large_list)
        if col.name == KEY_SEGMENT and col.name not in columns:
            values = [segment] * n
        else:
            values = columns.get(col.name, [None] * n)
        values = [v.tolist() if isinstance(v, np.ndarray) else v for v in values]
        arrays.append(pa.array(values, type=t))
        fields.append(pa.field(col.name, t))
    for extra, values in (extra_columns or {}).items():
        arrays.append(pa.array(values))
        fields.append(pa.field(extra, arrays[-1].type))
    table = pa.Table.from_arrays(arrays, schema=pa.schema(fields))
    if shuffle_seed is not None:
        table = table.take(np.random.default_rng(shuffle_seed).permutation(n))
    if shuffle_columns:
        order = np.random.default_rng(7).permutation(table.num_columns)
        table = table.select([table.column_names[i] for i in order])
    path = Path(root) / split / name / (filename or f"{segment}.parquet")
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path, compression=compression)
    return path


def flat(m: np.ndarray) -> list:
    return np.asarray(m, np.float64).reshape(-1).tolist()


def rigid(yaw: float, t) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = t
    return m


# Geometry of the tiny segment (all chosen to make hand computation easy).
WORLD_FROM_VEHICLE = [rigid(0.1 * i, [10.0 * i, 2.0 * i, 0.5]) for i in range(3)]
TOP_FROM = rigid(0.0, [1.0, 0.0, 2.0])           # vehicle_from_lidar of TOP (no yaw)
FRONT_FROM = rigid(0.3, [3.0, 0.0, 0.5])         # vehicle_from_lidar of FRONT (yawed)
TOP_INCL = (-0.2, 0.1)                           # uniform min/max, H = 4
FRONT_INCL_VALUES = [-0.5, -0.1, 0.3]            # explicit, ascending, H = 3
TOP_HW, FRONT_HW = (4, 8), (3, 5)
CAMERA_FROM = rigid(0.0, [1.5, 0.0, 2.0])        # vehicle_from_camera of FRONT camera


def top_range(frame: int, ret: int) -> np.ndarray:
    """float32 [4, 8, 4]: range grows with row and column, a checkerboard of invalid pixels."""
    h, w = TOP_HW
    img = np.zeros((h, w, 4), np.float32)
    rr, cc = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    img[..., 0] = np.where((rr + cc + frame) % 3 == 0, -1.0, 5.0 + rr + 0.5 * cc + frame)
    if ret == 2:
        img[..., 0] = np.where(cc == 2, 20.0 + rr, 0.0)
    img[..., 1] = 0.25 * rr  # intensity
    return img


def front_range(frame: int, ret: int) -> np.ndarray:
    h, w = FRONT_HW
    img = np.zeros((h, w, 4), np.float32)
    if ret == 1:
        img[..., 0] = 3.0 + np.arange(w)[None, :] + 0 * np.arange(h)[:, None]
        img[1, 1, 0] = 0.0
    return img


def top_pose(frame: int) -> np.ndarray:
    """float32 [4, 8, 6]: per-pixel world_from_vehicle (roll, pitch, yaw, x, y, z); the vehicle
    moves 0.1 m along world x per column during the sweep, yaw of the frame pose."""
    h, w = TOP_HW
    pose = np.zeros((h, w, 6), np.float32)
    pose[..., 2] = 0.1 * frame
    pose[..., 3] = 10.0 * frame + 0.1 * (np.arange(w)[None, :] - w / 2)
    pose[..., 4] = 2.0 * frame
    pose[..., 5] = 0.5
    return pose


def jpeg_bytes(width=16, height=8, value=(10, 200, 30)) -> bytes:
    import cv2

    img = np.zeros((height, width, 3), np.uint8)
    img[:] = value[::-1]
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    return buf.tobytes()


def tiny_segment(root, split: str = "training", segment: str = SEGMENT, *, skip: tuple = (),
                 **options) -> dict:
    """Write every component the reader needs; returns ``{component: path}``.

    ``options`` go to every :func:`write_component` call (conventions under test).
    """
    paths = {}
    ts = TIMESTAMPS

    def write(name, cols, **kw):
        if name not in skip:
            paths[name] = write_component(root, split, name, segment, cols, **{**options, **kw})

    write("vehicle_pose", {
        "key.frame_timestamp_micros": ts,
        "[VehiclePoseComponent].world_from_vehicle.transform": [flat(m) for m in WORLD_FROM_VEHICLE],
    })
    write("lidar_calibration", {
        "key.laser_name": [1, 2],
        "[LiDARCalibrationComponent].extrinsic.transform": [flat(TOP_FROM), flat(FRONT_FROM)],
        "[LiDARCalibrationComponent].beam_inclination.min": [TOP_INCL[0], -0.5],
        "[LiDARCalibrationComponent].beam_inclination.max": [TOP_INCL[1], 0.3],
        "[LiDARCalibrationComponent].beam_inclination.values": [None, FRONT_INCL_VALUES],
    })
    rows = [(t, laser) for t in range(3) for laser in (1, 2)]
    imgs = {(t, l, r): (top_range(t, r) if l == 1 else front_range(t, r))
            for t, l in rows for r in (1, 2)}
    lidar_cols = {"key.frame_timestamp_micros": [ts[t] for t, _ in rows],
                  "key.laser_name": [l for _, l in rows]}
    for r in (1, 2):
        lidar_cols[f"[LiDARComponent].range_image_return{r}.values"] = [
            imgs[(t, l, r)].reshape(-1) for t, l in rows]
        lidar_cols[f"[LiDARComponent].range_image_return{r}.shape"] = [
            list(imgs[(t, l, r)].shape) for t, l in rows]
    write("lidar", lidar_cols)
    write("lidar_pose", {
        "key.frame_timestamp_micros": ts, "key.laser_name": [1, 1, 1],
        "[LiDARPoseComponent].range_image_return1.values": [top_pose(t).reshape(-1) for t in range(3)],
        "[LiDARPoseComponent].range_image_return1.shape": [[4, 8, 6]] * 3,
    })
    proj_cols = {"key.frame_timestamp_micros": [ts[t] for t, _ in rows],
                 "key.laser_name": [l for _, l in rows]}
    for r in (1, 2):
        vals, shapes = [], []
        for t, l in rows:
            h, w = TOP_HW if l == 1 else FRONT_HW
            p = np.zeros((h, w, 6), np.float32)
            p[..., 0] = 1
            p[..., 1] = np.arange(w)[None, :] * 10 + r
            p[..., 2] = np.arange(h)[:, None] * 10 + t
            vals.append(p.reshape(-1))
            shapes.append([h, w, 6])
        proj_cols[f"[LiDARCameraProjectionComponent].range_image_return{r}.values"] = vals
        proj_cols[f"[LiDARCameraProjectionComponent].range_image_return{r}.shape"] = shapes
    write("lidar_camera_projection", proj_cols)
    cc = "[CameraCalibrationComponent]."
    write("camera_calibration", {
        "key.camera_name": [1, 2],
        cc + "intrinsic.f_u": [100.0, 90.0], cc + "intrinsic.f_v": [100.0, 90.0],
        cc + "intrinsic.c_u": [8.0, 8.0], cc + "intrinsic.c_v": [4.0, 4.0],
        cc + "intrinsic.k1": [0.01, 0.0], cc + "intrinsic.k2": [0.0, 0.0],
        cc + "intrinsic.p1": [0.0, 0.0], cc + "intrinsic.p2": [0.0, 0.0],
        cc + "intrinsic.k3": [0.0, 0.0],
        cc + "extrinsic.transform": [flat(CAMERA_FROM), flat(rigid(0.8, [1.4, 0.3, 2.0]))],
        cc + "width": [16, 16], cc + "height": [8, 8],
        cc + "rolling_shutter_direction": [2, 5],
    })
    ci = "[CameraImageComponent]."
    cam_rows = [(t, c) for t in range(3) for c in (1, 2)]
    write("camera_image", {
        "key.frame_timestamp_micros": [ts[t] for t, _ in cam_rows],
        "key.camera_name": [c for _, c in cam_rows],
        ci + "image": [jpeg_bytes(value=(10 * t, 100, 30 * c)) for t, c in cam_rows],
        ci + "pose.transform": [flat(WORLD_FROM_VEHICLE[t]) for t, _ in cam_rows],
        ci + "velocity.linear_velocity.x": [10.0] * 6, ci + "velocity.linear_velocity.y": [0.0] * 6,
        ci + "velocity.linear_velocity.z": [0.0] * 6,
        ci + "velocity.angular_velocity.x": [0.0] * 6, ci + "velocity.angular_velocity.y": [0.0] * 6,
        ci + "velocity.angular_velocity.z": [0.05] * 6,
        ci + "pose_timestamp": [ts[t] / 1e6 + 0.01 for t, _ in cam_rows],
        ci + "rolling_shutter_params.shutter": [0.002] * 6,
        ci + "rolling_shutter_params.camera_trigger_time": [ts[t] / 1e6 for t, _ in cam_rows],
        ci + "rolling_shutter_params.camera_readout_done_time": [ts[t] / 1e6 + 0.03 for t, _ in cam_rows],
    })
    lb = "[LiDARBoxComponent]."
    write("lidar_box", {
        "key.frame_timestamp_micros": [ts[0], ts[1], ts[1], ts[2]],
        "key.laser_object_id": ["car_a", "car_a", "ped_b", "car_a"],
        lb + "box.center.x": [10.0, 11.0, 5.0, 12.0], lb + "box.center.y": [1.0, 1.0, -2.0, 1.0],
        lb + "box.center.z": [0.8] * 4, lb + "box.size.x": [4.0, 4.0, 0.6, 4.0],
        lb + "box.size.y": [2.0, 2.0, 0.6, 2.0], lb + "box.size.z": [1.6, 1.6, 1.8, 1.6],
        lb + "box.heading": [0.0, 0.1, 1.0, 0.2], lb + "type": [1, 1, 2, 1],
        lb + "num_lidar_points_in_box": [12, None, 3, 9],
        lb + "speed.x": [10.0, 10.0, 1.0, None], lb + "speed.y": [0.0, 0.0, 0.0, None],
        lb + "speed.z": [0.0, 0.0, 0.0, None],
    })
    return paths


def assert_official_component(path: str, name: str):
    """The parquet file ``path`` of component ``name`` has exactly the official columns, with
    compatible arrow types, BROTLI compression and at least one row; returns its table."""
    from drivetrack.waymo.schema import COMPONENTS, types_compatible

    table = pq.read_table(path)
    comp = COMPONENTS[name]
    assert table.column_names == [c.name for c in comp.columns], name
    for col in comp.columns:
        assert types_compatible(col.type, table.schema.field(col.name).type), (name, col.name)
    meta = pq.ParquetFile(path).metadata
    assert all(meta.row_group(0).column(i).compression == "BROTLI" for i in range(meta.num_columns))
    assert table.num_rows > 0, name
    return table


def expect_format_error(exc_info, split: str, component: str, column: str, *fragments: str) -> None:
    """The raised error is a WaymoFormatError naming the file (split, component, segment), the
    column and every fragment (found values, rules)."""
    from drivetrack.waymo.reader import WaymoFormatError

    err = exc_info.value
    msg = str(err)
    assert isinstance(err, WaymoFormatError), msg
    assert f"/{split}/{component}/{SEGMENT}.parquet" in msg and "file://" in msg
    assert f"segment {SEGMENT!r}" in msg and f"component {component!r}" in msg
    assert column in msg, msg
    for fragment in fragments:
        assert fragment in msg, (fragment, msg)
    assert err.component == component and err.segment == SEGMENT
