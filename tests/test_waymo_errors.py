"""Bad Waymo v2 input: every error names the file, segment, component and column."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from _waymo_parquet import expect_format_error, SEGMENT, TIMESTAMPS, flat, tiny_segment, top_range, write_component
from drivetrack.waymo import reader
from drivetrack.waymo.reader import WaymoFormatError

SPLIT = "training"
LB = "[LiDARBoxComponent]."
VP = "[VehiclePoseComponent].world_from_vehicle.transform"
R1 = "[LiDARComponent].range_image_return1."


def _expect(exc_info, component: str, column: str, *fragments: str):
    expect_format_error(exc_info, SPLIT, component, column, *fragments)


def _load(root, **kw):
    return reader.load_scene(str(root), SPLIT, SEGMENT, cameras=(1, 2), **kw)


def test_missing_component_file(tmp_path):
    tiny_segment(tmp_path, skip=("lidar_box",))
    with pytest.raises(WaymoFormatError) as e:
        reader.read_component(str(tmp_path), SPLIT, "lidar_box", SEGMENT)
    _expect(e, "lidar_box", "key.laser_object_id", "missing component file", "no such file")


def test_segment_present_in_one_component_absent_from_another(tmp_path):
    tiny_segment(tmp_path, skip=("lidar_pose",))
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "lidar_pose", "key.laser_name", "absent from component 'lidar_pose'",
            "present in components", "'vehicle_pose'")


def test_segment_absent_from_its_file(tmp_path):
    tiny_segment(tmp_path)
    write_component(tmp_path, SPLIT, "vehicle_pose", "another_segment",
                    {"key.frame_timestamp_micros": [1], VP: [flat(np.eye(4))]},
                    filename=f"{SEGMENT}.parquet")
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "vehicle_pose", "key.segment_context_name", "segment absent", "no rows")


def test_missing_column(tmp_path):
    tiny_segment(tmp_path, drop=(LB + "box.heading",))
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "lidar_box", LB + "box.heading", "missing column", "expected double",
            "no such column")


def test_wrong_column_type(tmp_path):
    tiny_segment(tmp_path, override_types={VP: pa.list_(pa.float32(), 16)})
    with pytest.raises(WaymoFormatError) as e:
        reader.read_component(str(tmp_path), SPLIT, "vehicle_pose", SEGMENT)
    _expect(e, "vehicle_pose", VP, "wrong column type",
            "expected fixed_size_list<item: double>[16]", "found fixed_size_list<", "float>[16]")


def test_wrong_key_type(tmp_path):
    tiny_segment(tmp_path, override_types={"key.frame_timestamp_micros": pa.int32()})
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "vehicle_pose", "key.frame_timestamp_micros", "expected int64", "found int32")


def test_unknown_column_requested(tmp_path):
    tiny_segment(tmp_path)
    with pytest.raises(WaymoFormatError) as e:
        reader.read_component(str(tmp_path), SPLIT, "lidar_box", SEGMENT,
                              columns=[LB + "no_such_field"])
    _expect(e, "lidar_box", LB + "no_such_field", "not a column of the official schema")


@pytest.mark.parametrize("damage", ["truncated", "garbage"])
def test_truncated_or_corrupt_parquet(tmp_path, damage):
    paths = tiny_segment(tmp_path)
    path = paths["lidar_box"]
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2] if damage == "truncated" else b"PAR1" + bytes(300))
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "lidar_box", "column", "truncated or corrupt parquet file")


def test_corrupt_range_image_pages_name_the_lidar_file(tmp_path):
    """Range images are decoded on a helper thread while the previous batch is turned into points:
    a damaged data page (footer intact, so the file opens) still fails the load with the lidar file
    named, from the caller's thread."""
    import pyarrow.parquet as pq

    path = tiny_segment(tmp_path)["lidar"]
    chunk = pq.ParquetFile(path).metadata.row_group(0).column(3)
    assert chunk.path_in_schema.startswith(R1 + "values")
    data = bytearray(path.read_bytes())
    start = chunk.data_page_offset + 20
    data[start: chunk.data_page_offset + chunk.total_compressed_size - 5] = (
        b"\xab" * (chunk.total_compressed_size - 25))
    path.write_bytes(bytes(data))
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "lidar", R1 + "values", "truncated or corrupt parquet file", "readable column chunks")


def test_corrupt_per_pixel_pose_pages_name_the_lidar_pose_file(tmp_path):
    """``lidar_pose`` is decoded on its own helper thread while the range images stream: a
    damaged data page fails the load from the caller's thread, naming that file, and leaves no
    reader thread behind."""
    import threading

    import pyarrow.parquet as pq

    path = tiny_segment(tmp_path)["lidar_pose"]
    meta = pq.ParquetFile(path).metadata.row_group(0)
    chunk = next(meta.column(i) for i in range(meta.num_columns)
                 if meta.column(i).path_in_schema.startswith("[LiDARPoseComponent].range_image_return1.values"))
    data = bytearray(path.read_bytes())
    first = chunk.dictionary_page_offset if chunk.has_dictionary_page else chunk.data_page_offset
    start, stop = chunk.data_page_offset + 20, first + chunk.total_compressed_size - 5    # the chunk's own bytes
    data[start:stop] = b"\xab" * (stop - start)
    path.write_bytes(bytes(data))
    before = threading.active_count()
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "lidar_pose", "[LiDARPoseComponent].range_image_return1.values", "truncated or corrupt parquet file")
    assert threading.active_count() == before


def test_nan_in_vehicle_pose(tmp_path):
    tiny_segment(tmp_path, skip=("vehicle_pose",))
    poses = [flat(np.eye(4)) for _ in TIMESTAMPS]
    poses[1][7] = float("nan")
    write_component(tmp_path, SPLIT, "vehicle_pose", SEGMENT,
                    {"key.frame_timestamp_micros": TIMESTAMPS, VP: poses}, shuffle_seed=2)
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "vehicle_pose", VP, "NaN in a transform", f"{TIMESTAMPS[1]}")


def test_nan_in_camera_image_pose(tmp_path):
    tiny_segment(tmp_path)
    table = reader.read_component(str(tmp_path), SPLIT, "camera_image", SEGMENT)
    cols = {n: table[n].to_pylist() for n in table.column_names}
    pose = "[CameraImageComponent].pose.transform"
    cols[pose][3] = [float("nan")] * 16
    write_component(tmp_path, SPLIT, "camera_image", SEGMENT, cols)
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "camera_image", pose, "NaN in a transform", "key.camera_name")


def test_null_row_in_a_fixed_size_column(tmp_path):
    tiny_segment(tmp_path, skip=("vehicle_pose",))
    write_component(tmp_path, SPLIT, "vehicle_pose", SEGMENT,
                    {"key.frame_timestamp_micros": TIMESTAMPS,
                     VP: [flat(np.eye(4)), flat(np.eye(4)), None]})  # pyarrow 22 writes
    # a null fixed-size row only at the end of a chunk, and cannot read it back.
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "vehicle_pose", VP, "null")


def _rewrite_lidar(tmp_path, values, shape):
    tiny_segment(tmp_path, skip=("lidar",))
    img = top_range(0, 1)
    write_component(tmp_path, SPLIT, "lidar", SEGMENT, {
        "key.frame_timestamp_micros": TIMESTAMPS[:2], "key.laser_name": [1, 1],
        R1 + "values": [img.reshape(-1), values], R1 + "shape": [list(img.shape), shape],
        "[LiDARComponent].range_image_return2.values": [img.reshape(-1)] * 2,
        "[LiDARComponent].range_image_return2.shape": [list(img.shape)] * 2})


def test_empty_range_image(tmp_path):
    _rewrite_lidar(tmp_path, [], [0, 0, 4])
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "lidar", R1 + "values", "empty range image", f"{TIMESTAMPS[1]}")


def test_range_image_shape_does_not_match_values(tmp_path):
    _rewrite_lidar(tmp_path, top_range(0, 1).reshape(-1), [4, 7, 4])
    with pytest.raises(WaymoFormatError) as e:
        reader.read_component(str(tmp_path), SPLIT, "lidar", SEGMENT)
    _expect(e, "lidar", R1 + "shape", "does not match", "128 values", "[4.0, 7.0, 4.0]")


def test_duplicate_keys(tmp_path):
    tiny_segment(tmp_path, skip=("vehicle_pose",))
    write_component(tmp_path, SPLIT, "vehicle_pose", SEGMENT, {
        "key.frame_timestamp_micros": TIMESTAMPS + [TIMESTAMPS[2]],
        VP: [flat(np.eye(4))] * 4})
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "vehicle_pose", "key.frame_timestamp_micros", "duplicate key", "2 rows",
            f"{TIMESTAMPS[2]}")


def test_duplicate_lidar_rows(tmp_path):
    tiny_segment(tmp_path, skip=("lidar",))
    img = top_range(0, 1)
    write_component(tmp_path, SPLIT, "lidar", SEGMENT, {
        "key.frame_timestamp_micros": [TIMESTAMPS[0]] * 2, "key.laser_name": [1, 1],
        R1 + "values": [img.reshape(-1)] * 2, R1 + "shape": [list(img.shape)] * 2,
        "[LiDARComponent].range_image_return2.values": [img.reshape(-1)] * 2,
        "[LiDARComponent].range_image_return2.shape": [list(img.shape)] * 2})
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "lidar", "key.laser_name", "duplicate key")


def test_timestamp_that_is_no_frame(tmp_path):
    tiny_segment(tmp_path, skip=("lidar_box",))
    write_component(tmp_path, SPLIT, "lidar_box", SEGMENT, {
        "key.frame_timestamp_micros": [TIMESTAMPS[0], 999], "key.laser_object_id": ["a", "b"],
        **{LB + f"box.{p}.{a}": [1.0, 1.0] for p in ("center", "size") for a in "xyz"},
        LB + "box.heading": [0.0, 0.0], LB + "type": [1, 1]})
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "lidar_box", "key.frame_timestamp_micros", "not present in vehicle_pose", "999")


def test_requested_camera_without_calibration(tmp_path):
    tiny_segment(tmp_path)
    with pytest.raises(WaymoFormatError) as e:
        reader.load_scene(str(tmp_path), SPLIT, SEGMENT, cameras=(1, 3))
    _expect(e, "camera_calibration", "key.camera_name", "expected 3", "found [1, 2]")


def test_missing_per_pixel_pose_row(tmp_path):
    tiny_segment(tmp_path, skip=("lidar_pose",))
    pose = np.zeros((4, 8, 6), np.float32).reshape(-1)
    write_component(tmp_path, SPLIT, "lidar_pose", SEGMENT, {
        "key.frame_timestamp_micros": TIMESTAMPS[:2], "key.laser_name": [1, 1],
        "[LiDARPoseComponent].range_image_return1.values": [pose, pose],
        "[LiDARPoseComponent].range_image_return1.shape": [[4, 8, 6]] * 2})
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "lidar_pose", "[LiDARPoseComponent].range_image_return1.values",
            "no per-pixel pose", f"{TIMESTAMPS[2]}")
