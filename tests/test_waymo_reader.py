"""Waymo v2 reader: layout, decoding against hand-computed values, joins, producers' conventions."""
from __future__ import annotations

import math

import numpy as np
import pyarrow as pa
import pytest

from _waymo_parquet import (CAMERA_FROM, FRONT_FROM, SEGMENT, TIMESTAMPS, WORLD_FROM_VEHICLE,
                            flat, tiny_segment, top_range, write_component)
from drivetrack.waymo import columns, lidar, reader
from drivetrack.waymo.schema import COMPONENTS

SPLIT = "training"


def _point(scene, t, laser, ret, row, col):
    lid = scene.lidar
    m = ((lid.frame == t) & (lid.laser == laser) & (lid.return_index == ret) & (lid.row == row)
         & (lid.col == col))
    assert m.sum() == 1, (t, laser, ret, row, col, m.sum())
    return lid.points_vehicle[m][0]


@pytest.fixture(scope="module")
def segment_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("wod")
    tiny_segment(root, shuffle_seed=1)
    return root


@pytest.fixture(scope="module")
def scene(segment_root):
    return reader.load_scene(str(segment_root), SPLIT, SEGMENT, cameras=(1, 2),
                             with_camera_projection=True)


def test_list_segments_local_and_file_url(tmp_path):
    tiny_segment(tmp_path)
    tiny_segment(tmp_path, segment="seg_0000", skip=("lidar",))
    (tmp_path / SPLIT / "lidar" / "notes.txt").write_text("not a segment")
    assert reader.list_segments(str(tmp_path), SPLIT) == ["seg_0000", SEGMENT]
    assert reader.list_segments(f"file://{tmp_path}", SPLIT) == ["seg_0000", SEGMENT]
    with pytest.raises(FileNotFoundError, match="validation"):
        reader.list_segments(str(tmp_path), "validation")


def test_read_component_reads_keys_and_requested_columns_of_the_segment(tmp_path):
    col = "[VehiclePoseComponent].world_from_vehicle.transform"
    write_component(tmp_path, SPLIT, "vehicle_pose", SEGMENT, {
        "key.segment_context_name": [SEGMENT, "other", SEGMENT],
        "key.frame_timestamp_micros": [2, 1, 1],
        col: [flat(np.eye(4)), flat(np.eye(4)), flat(WORLD_FROM_VEHICLE[1])]})
    table = reader.read_component(str(tmp_path), SPLIT, "vehicle_pose", SEGMENT, columns=[col])
    assert table.column_names == ["key.segment_context_name", "key.frame_timestamp_micros", col]
    assert table["key.segment_context_name"].to_pylist() == [SEGMENT, SEGMENT]
    mats = columns.transforms_from_column(table[col])
    assert mats.shape == (2, 4, 4)
    np.testing.assert_array_equal(mats[1], WORLD_FROM_VEHICLE[1])
    keys_only = reader.read_component(str(tmp_path), SPLIT, "vehicle_pose", SEGMENT, columns=[])
    assert keys_only.column_names == list(COMPONENTS["vehicle_pose"].keys)


def test_frames_ordered_by_timestamp_and_poses_joined_on_keys(scene):
    assert scene.segment == SEGMENT and scene.split == SPLIT
    np.testing.assert_array_equal(scene.timestamps_micros, TIMESTAMPS)
    np.testing.assert_allclose(scene.world_from_vehicle, np.stack(WORLD_FROM_VEHICLE))
    assert set(scene.source_files) == {"vehicle_pose", "camera_calibration", "camera_image",
                                       "lidar_calibration", "lidar", "lidar_pose",
                                       "lidar_camera_projection", "lidar_box"}
    assert all(url.startswith("file://") and url.endswith(f"/{SEGMENT}.parquet")
               for url in scene.source_files.values())


def test_top_point_matches_method_formulas_with_per_pixel_pose(scene):
    # frame 1, row 0, column 1: range = 5 + row + 0.5 col + frame = 6.5 (top_range).
    h, w, r = 4, 8, 6.5
    incl = -0.2 + (h - 1 + 0.5) / h * (0.1 - (-0.2))       # uniform, reversed: row 0 = i = H-1
    az = (2 * (w - 1 - 0.5) / w - 1) * math.pi - 0.0        # TOP extrinsic has no yaw
    sensor = r * np.array([math.cos(incl) * math.cos(az), math.cos(incl) * math.sin(az),
                           math.sin(incl)])
    vehicle_at_pixel = sensor + np.array([1.0, 0.0, 2.0])
    # Pixel pose = frame pose shifted by 0.1 (col - W/2) = -0.3 m along world x; in the frame's
    # vehicle frame (yaw 0.1) that is (-0.3 cos 0.1, 0.3 sin 0.1, 0).
    expected = vehicle_at_pixel + np.array([-0.3 * math.cos(0.1), 0.3 * math.sin(0.1), 0.0])
    np.testing.assert_allclose(_point(scene, 1, 1, 1, 0, 1), expected, atol=1e-5)


def test_pixel_pose_kernel_matches_rotation_matrices():
    """The reader's one-pass pixel-pose kernel equals the matrix form (rotation_from_rpy, then the
    frame's inverse pose) to float64 rounding, at kilometre-scale world positions."""
    from drivetrack.geometry import invert_rigid, rigid_from_rotation_translation, rotation_from_rpy, transform_points

    rng = np.random.default_rng(3)
    m = 5000
    points = rng.normal(size=(m, 3)) * 40.0
    pose = np.concatenate([rng.normal(size=(m, 3)) * 0.2, rng.normal(size=(m, 3)) * 900.0], 1)
    pose = pose.astype(np.float32)  # lidar_pose stores float32 values
    world_from_vehicle = rigid_from_rotation_translation(rotation_from_rpy(0.02, -0.01, 2.5),
                                                         np.array([812.0, -1933.0, 41.0]))
    p64 = pose.astype(np.float64)
    rotation = rotation_from_rpy(p64[:, 0], p64[:, 1], p64[:, 2])
    world = np.einsum("mij,mj->mi", rotation, points) + p64[:, 3:6]
    expected = transform_points(invert_rigid(world_from_vehicle), world)
    got = lidar.apply_pixel_pose(points, pose, world_from_vehicle)
    assert got.dtype == np.float64 and got.shape == (m, 3)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)


def test_short_lidar_point_uses_explicit_inclinations_and_extrinsic_yaw(scene):
    # FRONT, frame 0, row 0, column 3: range 3 + 3 = 6; inclinations [-0.5, -0.1, 0.3] reversed.
    incl, yaw, w = 0.3, 0.3, 5
    az = (2 * (w - 3 - 0.5) / w - 1) * math.pi - yaw
    sensor = 6.0 * np.array([math.cos(incl) * math.cos(az), math.cos(incl) * math.sin(az),
                             math.sin(incl)])
    expected = FRONT_FROM[:3, :3] @ sensor + FRONT_FROM[:3, 3]
    np.testing.assert_allclose(_point(scene, 0, 2, 1, 0, 3), expected, atol=1e-9)


def test_returns_valid_where_range_positive_and_sorted_by_frame(scene):
    lid = scene.lidar
    for t in range(3):
        sl = lid.of_frame(t)
        assert np.all(lid.frame[sl] == t)
        for ret in (1, 2):
            img = top_range(t, ret)
            got = ((lid.frame == t) & (lid.laser == 1) & (lid.return_index == ret)).sum()
            assert got == np.count_nonzero(img[..., 0] > 0)
    assert lid.frame_offsets[-1] == len(lid)
    # FRONT return 2 is all zero: no points; FRONT return 1 has one hole per frame.
    assert not np.any((lid.laser == 2) & (lid.return_index == 2))
    assert ((lid.laser == 2) & (lid.return_index == 1)).sum() == 3 * (15 - 1)
    top = (lid.laser == 1) & (lid.frame == 0) & (lid.return_index == 1)
    np.testing.assert_allclose(lid.intensity[top], 0.25 * lid.row[top])
    assert lid.points_vehicle.dtype == np.float64 and lid.intensity.dtype == np.float32


def test_return2_shares_return1_pose(scene):
    # Return 2 of TOP frame 2 at (row 1, col 2): range 21, corrected with the same pixel pose.
    incl = -0.2 + (2 + 0.5) / 4 * 0.3                      # row 1 = i = 2
    az = (2 * (8 - 2 - 0.5) / 8 - 1) * math.pi
    p = 21.0 * np.array([math.cos(incl) * math.cos(az), math.cos(incl) * math.sin(az),
                         math.sin(incl)]) + [1.0, 0.0, 2.0]
    shift = -0.2  # 0.1 * (col - W/2)
    expected = p + np.array([shift * math.cos(0.2), -shift * math.sin(0.2), 0.0])
    np.testing.assert_allclose(_point(scene, 2, 1, 2, 1, 2), expected, atol=1e-5)


def test_lidar_camera_projection_follows_each_return_pixel(scene):
    lid = scene.lidar
    proj = lid.camera_projection
    assert proj.shape == (len(lid), 6) and proj.dtype == np.int16
    np.testing.assert_array_equal(proj[:, 0], 1)
    np.testing.assert_array_equal(proj[:, 1], lid.col * 10 + lid.return_index)
    np.testing.assert_array_equal(proj[:, 2], lid.row * 10 + lid.frame)
    np.testing.assert_array_equal(proj[:, 3:], 0)


def test_camera_metadata_and_lazy_jpeg(scene):
    cam = scene.cameras[1]
    assert cam.model.width == 16 and cam.model.height == 8
    assert cam.model.rolling_shutter_direction == 2
    assert scene.cameras[2].model.rolling_shutter_direction == 5
    np.testing.assert_allclose(cam.model.vehicle_from_camera, CAMERA_FROM)
    assert (cam.model.f_u, cam.model.c_u, cam.model.c_v, cam.model.k1) == (100.0, 8.0, 4.0, 0.01)
    np.testing.assert_allclose(cam.world_from_vehicle, np.stack(WORLD_FROM_VEHICLE))
    np.testing.assert_allclose(cam.pose_timestamp, np.array(TIMESTAMPS) / 1e6 + 0.01)
    np.testing.assert_allclose(cam.velocity, [[10.0, 0, 0, 0, 0, 0.05]] * 3)
    np.testing.assert_allclose(cam.trigger_time, np.array(TIMESTAMPS) / 1e6)
    np.testing.assert_allclose(cam.readout_done_time - cam.trigger_time, 0.03)
    np.testing.assert_allclose(cam.shutter, 0.002)
    assert all(isinstance(j, bytes) for j in cam.jpeg)
    rgb = scene.cameras[2].image(2)
    assert rgb.shape == (8, 16, 3) and rgb.dtype == np.uint8
    assert np.abs(rgb[4, 8].astype(int) - [20, 100, 60]).max() <= 3  # value=(10 t, 100, 30 c)


def test_boxes_all_types_ordered_with_nulls(scene):
    b = scene.boxes
    assert b.object_id.tolist() == ["car_a", "car_a", "ped_b", "car_a"]
    np.testing.assert_array_equal(b.frame, [0, 1, 1, 2])
    np.testing.assert_array_equal(b.type, [1, 1, 2, 1])
    np.testing.assert_allclose(b.center[2], [5.0, -2.0, 0.8])
    np.testing.assert_allclose(b.size[2], [0.6, 0.6, 1.8])
    np.testing.assert_allclose(b.heading, [0.0, 0.1, 1.0, 0.2])
    np.testing.assert_array_equal(b.num_lidar_points_in_box, [12, -1, 3, 9])
    assert np.isnan(b.speed[3]).all() and b.speed[0, 0] == 10.0
    assert b.object_ids() == ["car_a", "ped_b"]


@pytest.mark.parametrize("options", [
    {"list_child": "element"},
    {"large_list": True},
    {"compression": "snappy"},
    {"compression": "none"},
    {"shuffle_seed": 11, "shuffle_columns": True},
    {"extra_columns": {"[LiDARBoxComponent].future_field": [1, 2, 3, 4]}},
], ids=["element", "large_list", "snappy", "uncompressed", "shuffled", "extra-columns"])
def test_other_producers_conventions_give_the_same_scene(tmp_path, scene, options):
    extra = options.pop("extra_columns", None)
    tiny_segment(tmp_path, **options)
    if extra:  # an unknown column in one component must be ignored
        lb = reader.read_component(str(tmp_path), SPLIT, "lidar_box", SEGMENT)
        cols = {n: lb[n].to_pylist() for n in lb.column_names}
        write_component(tmp_path, SPLIT, "lidar_box", SEGMENT, cols, extra_columns=extra)
    other = reader.load_scene(str(tmp_path), SPLIT, SEGMENT, cameras=(1, 2),
                              with_camera_projection=True)
    key = lambda s: np.lexsort((s.lidar.col, s.lidar.row, s.lidar.return_index, s.lidar.laser,  # noqa: E731
                                s.lidar.frame))
    a, b = key(scene), key(other)
    np.testing.assert_allclose(other.lidar.points_vehicle[b], scene.lidar.points_vehicle[a])
    np.testing.assert_array_equal(other.lidar.camera_projection[b], scene.lidar.camera_projection[a])
    np.testing.assert_array_equal(other.lidar.frame_offsets, scene.lidar.frame_offsets)
    np.testing.assert_allclose(other.world_from_vehicle, scene.world_from_vehicle)
    assert other.boxes.object_id.tolist() == scene.boxes.object_id.tolist()
    np.testing.assert_allclose(other.boxes.center, scene.boxes.center)
    assert other.cameras[1].jpeg == scene.cameras[1].jpeg


def test_null_rows_are_missing_data_not_errors(tmp_path):
    tiny_segment(tmp_path, skip=("camera_image", "lidar"))
    ts = TIMESTAMPS
    ci = "[CameraImageComponent]."
    write_component(tmp_path, SPLIT, "camera_image", SEGMENT, {  # frame 1 has no FRONT image
        "key.frame_timestamp_micros": [ts[0], ts[2]], "key.camera_name": [1, 1],
        ci + "image": [b"x", None], ci + "pose.transform": [flat(np.eye(4))] * 2,
        ci + "pose_timestamp": [1.0, None]})
    img = top_range(0, 1)
    # Only frame 0 has a TOP row, and its second return has no valid pixel. (Null rows of the
    # fixed-size `shape` column cannot be read back by pyarrow < 23: test_waymo_errors.)
    write_component(tmp_path, SPLIT, "lidar", SEGMENT, {
        "key.frame_timestamp_micros": [ts[0]], "key.laser_name": [1],
        "[LiDARComponent].range_image_return1.values": [img.reshape(-1)],
        "[LiDARComponent].range_image_return1.shape": [list(img.shape)],
        "[LiDARComponent].range_image_return2.values": [np.zeros(img.size, np.float32)],
        "[LiDARComponent].range_image_return2.shape": [list(img.shape)]})
    s = reader.load_scene(str(tmp_path), SPLIT, SEGMENT, cameras=(1,))
    cam = s.cameras[1]
    assert cam.jpeg == [b"x", None, None]
    assert not np.isnan(cam.world_from_vehicle[[0, 2]]).any()
    assert np.isnan(cam.world_from_vehicle[1]).all()  # no row for frame 1
    assert cam.pose_timestamp[0] == 1.0 and np.isnan(cam.pose_timestamp[1:]).all()
    assert np.isnan(cam.velocity).all()  # never written: all-null columns
    assert set(s.lidar.return_index.tolist()) == {1} and set(s.lidar.frame.tolist()) == {0}
    np.testing.assert_array_equal(s.lidar.frame_offsets, [0, 21, 21, 21])


def test_options_select_lasers_returns_and_skip_images(segment_root):
    s = reader.load_scene(str(segment_root), SPLIT, SEGMENT, cameras=(), lasers=[2],
                          returns=(1,), with_images=False)
    assert s.cameras == {}
    assert set(s.lidar.laser.tolist()) == {2} and set(s.lidar.return_index.tolist()) == {1}
    assert "lidar_pose" not in s.source_files and "camera_image" not in s.source_files
    s = reader.load_scene(str(segment_root), SPLIT, SEGMENT, cameras=(1,), lasers=[],
                          with_images=False)
    assert len(s.lidar) == 0 and s.lidar.frame_offsets.tolist() == [0, 0, 0, 0]
    assert s.cameras[1].jpeg == [None, None, None]


def test_decoders_handle_nulls_and_child_names():
    shapes = pa.array([[2, 3, 1], None, [1, 1, 2]], pa.list_(pa.field("element", pa.int32()), 3))
    values = pa.array([[0, 1, 2, 3, 4, 5], None, [7, 8]], pa.large_list(pa.float32()))
    images = columns.range_images_from_columns(values, shapes)
    np.testing.assert_array_equal(images[0][..., 0], [[0, 1, 2], [3, 4, 5]])
    assert images[1] is None and images[2].shape == (1, 1, 2)
    sliced = columns.range_images_from_columns(values.slice(2), shapes.slice(2))
    np.testing.assert_array_equal(sliced[0].ravel(), [7, 8])
    mats = columns.transforms_from_column(pa.chunked_array(
        [pa.array([flat(np.eye(4))], pa.list_(pa.float64(), 16)),
         pa.array([None], pa.list_(pa.float64(), 16))]))
    assert mats.shape == (2, 4, 4)
    np.testing.assert_array_equal(mats[0], np.eye(4))
    assert np.isnan(mats[1]).all()


def test_lidar_points_function_matches_the_scene(scene):
    from _waymo_parquet import TOP_FROM, top_pose
    from drivetrack.waymo.lidar import beam_inclinations

    incl = beam_inclinations(4, None, -0.2, 0.1)
    pts, rows, cols, inten = lidar.lidar_points(top_range(1, 1), TOP_FROM, incl,
                                                 top_pose(1), WORLD_FROM_VEHICLE[1])
    m = (scene.lidar.frame == 1) & (scene.lidar.laser == 1) & (scene.lidar.return_index == 1)
    np.testing.assert_allclose(pts, scene.lidar.points_vehicle[m])
    np.testing.assert_array_equal(rows, scene.lidar.row[m])
    np.testing.assert_array_equal(cols, scene.lidar.col[m])
    empty = lidar.lidar_points(np.zeros((4, 8, 4), np.float32), TOP_FROM, incl)
    assert empty[0].shape == (0, 3) and empty[1].shape == (0,)


def test_s3_bucket_through_storage_options(tmp_path):
    moto_server = pytest.importorskip("moto.server")
    s3fs = pytest.importorskip("s3fs")
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    try:
        host, port = server.get_host_and_port()
        opts = {"endpoint_url": f"http://{host}:{port}", "key": "testing", "secret": "testing"}
        fs = s3fs.S3FileSystem(**opts)
        fs.mkdir("wod-bucket")
        tiny_segment(tmp_path)
        fs.put(str(tmp_path / SPLIT), "wod-bucket/v2/training", recursive=True)
        root = "s3://wod-bucket/v2"
        assert reader.list_segments(root, SPLIT, storage_options=opts) == [SEGMENT]
        table = reader.read_component(root, SPLIT, "lidar_box", SEGMENT,
                                      columns=["[LiDARBoxComponent].type"], storage_options=opts)
        assert table.num_rows == 4
        s = reader.load_scene(root, SPLIT, SEGMENT, cameras=(1,), storage_options=opts)
        assert s.source_files["lidar"] == f"s3://wod-bucket/v2/training/lidar/{SEGMENT}.parquet"
        assert len(s.lidar) == 118
    finally:
        server.stop()


def test_info_command_json_and_table(segment_root, tmp_path, capsys):
    import json

    from drivetrack.cli import main

    assert main(["info", str(segment_root), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    (s,) = out["segments"]
    assert s["segment"] == SEGMENT and s["num_frames"] == 3
    assert s["duration_s"] == pytest.approx(0.2)
    assert s["cameras"]["FRONT"] == {"width": 16, "height": 8, "images": 3}
    top = s["lasers"]["TOP"]
    assert top["shape"] == [4, 8, 4] and top["frames"] == 3
    assert top["valid_return1"] == sum(np.count_nonzero(top_range(t, 1)[..., 0] > 0) for t in range(3))
    assert top["valid_return2"] == 12 and s["lasers"]["FRONT"]["valid_return2"] == 0
    assert s["objects"] == {"VEHICLE": {"objects": 1, "boxes": 3},
                            "PEDESTRIAN": {"objects": 1, "boxes": 1}}

    assert main(["info", str(segment_root), "--segment", SEGMENT]) == 0
    text = capsys.readouterr().out
    assert SEGMENT in text and "FRONT_LEFT" in text and "PEDESTRIAN" in text and "4x8x4" in text

    tiny_segment(tmp_path, skip=("vehicle_pose",))
    assert main(["info", str(tmp_path), "--json"]) == 1
    bad = json.loads(capsys.readouterr().out)["segments"][0]
    assert "missing component file" in bad["error"] and "vehicle_pose" in bad["error"]
    assert main(["info", str(tmp_path), "--split", "validation"]) == 2
    assert main(["info", str(tmp_path), "--storage-option", "novalue"]) == 2


def test_return_keys_sort_like_tuples_and_bound_each_range_image():
    from drivetrack.waymo.lidar import RETURN_KEY_BITS, return_keys

    rng = np.random.default_rng(3)
    fields = [rng.integers(0, 4, 500), rng.integers(0, 6, 500), rng.integers(1, 3, 500),
              rng.integers(0, 64, 500), rng.integers(0, 2650, 500)]
    keys = return_keys(*fields)
    assert keys.dtype == np.int64 and keys.shape == (500,) and (keys >= 0).all()
    np.testing.assert_array_equal(np.argsort(keys, kind="stable"), np.lexsort(fields[::-1]))
    sel = (fields[0] == 2) & (fields[1] == 1) & (fields[2] == 2)
    inside = (keys >= return_keys(2, 1, 2, 0, 0)) & (keys < return_keys(2, 1, 3, 0, 0))
    np.testing.assert_array_equal(inside, sel)
    assert return_keys([], [], [], [], []).shape == (0,)
    assert sum(bits for _, bits in RETURN_KEY_BITS) == 63
    with pytest.raises(ValueError, match=r"clip x: LiDAR row value 16384 outside \[0, 16384\)"):
        return_keys(0, 1, 1, [3, 16384], 0, "clip x")
    with pytest.raises(ValueError, match=r"LiDAR laser value -1"):
        return_keys(0, -1, 1, 0, 0)
    # equal columns go through one numba pass: the same packing and the same first error
    expected = (((((fields[0] << 3) | fields[1]) << 2 | fields[2]) << 14 | fields[3]) << 16) | fields[4]
    np.testing.assert_array_equal(keys, expected)
    small = [f.astype(t) for f, t in zip(fields, (np.int32, np.int8, np.int8, np.int32, np.int32))]
    np.testing.assert_array_equal(return_keys(*small), keys)
    bad = [f.copy() for f in small]
    bad[3][[7, 9]] = [-2, 16384]
    bad[4][5] = 70000
    with pytest.raises(ValueError, match=r"clip y: LiDAR row value -2 outside \[0, 16384\)"):
        return_keys(*bad, "clip y")


def test_merge_rows_joins_on_shared_key_columns_not_row_order():
    from drivetrack.waymo.schema import COMPONENTS, KEY_CAMERA, KEY_LASER, KEY_TIMESTAMP, merge_rows

    assert KEY_CAMERA in COMPONENTS["camera_image"].keys and KEY_LASER in COMPONENTS["lidar"].keys
    left = {KEY_TIMESTAMP: np.array([30, 10, 20, 10]), KEY_CAMERA: np.array([1, 1, 1, 2])}
    right = {KEY_TIMESTAMP: np.array([10, 20, 10, 40]), KEY_CAMERA: np.array([2, 1, 1, 1]),
             "[X].value": np.arange(4)}
    row, found = merge_rows(left, right)
    np.testing.assert_array_equal(found, [True, True, True, False])
    np.testing.assert_array_equal(row[found], [3, 2, 1])
    row, found = merge_rows({KEY_TIMESTAMP: np.array([5, 7])}, {KEY_TIMESTAMP: np.array([7, 6, 5])})
    np.testing.assert_array_equal(found, [True, False, True])
    np.testing.assert_array_equal(row[found], [1, 0])
    assert merge_rows({KEY_TIMESTAMP: np.zeros(0)}, {KEY_TIMESTAMP: np.array([1])})[1].tolist() == [False]
    with pytest.raises(ValueError, match="no shared key column"):
        merge_rows({KEY_TIMESTAMP: np.array([1])}, {KEY_LASER: np.array([1])})


def test_per_pixel_poses_join_across_batches_in_any_row_order(tmp_path, monkeypatch):
    """TOP poses are applied while the range images stream (lidar_pose decoded on a helper
    thread): with one row per batch and both files' rows shuffled differently, every return and
    capture offset equals the one-batch read."""
    tiny_segment(tmp_path, shuffle_seed=5)
    whole = reader.load_scene(str(tmp_path), SPLIT, SEGMENT, cameras=())
    monkeypatch.setattr(reader, "LIDAR_BATCH_ROWS", 1)
    streamed = reader.load_scene(str(tmp_path), SPLIT, SEGMENT, cameras=())
    assert np.any(whole.lidar.laser == 1)
    np.testing.assert_array_equal(streamed.lidar.points_vehicle, whole.lidar.points_vehicle)
    np.testing.assert_array_equal(streamed.lidar.capture_offset_s, whole.lidar.capture_offset_s)
    np.testing.assert_array_equal(streamed.lidar.frame, whole.lidar.frame)


@pytest.mark.parametrize("channels", [1, 4])
def test_range_image_kernel_equals_the_numpy_reference(channels):
    """The reader's one-pass range-image kernel gives points_from_directions' returns bit for bit
    (NaN, inf, -inf, 0 and negative ranges are no return; NaN / inf counted)."""
    from drivetrack.waymo.kernel import returns_from_range_image

    rng = np.random.default_rng(8)
    h, w = 16, 40
    image = rng.uniform(-5.0, 80.0, (h, w, channels)).astype(np.float32)
    flat = image[..., 0].reshape(-1)
    flat[rng.choice(flat.size, 60, replace=False)] = rng.choice([np.nan, np.inf, -np.inf, 0.0, -1.0], 60)
    directions = rng.normal(size=(h, w, 3))
    origin = np.array([1.4, -0.1, 2.2])
    want = lidar.points_from_directions(image, directions, origin)
    got = returns_from_range_image(image, directions, origin)
    for a, b in zip(got[:4], want):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    assert got[4] == int(np.count_nonzero(~np.isfinite(image[..., 0]))) > 0


def test_posed_returns_kernel_equals_pose_and_time_references():
    """The TOP returns' one-pass pose kernel: apply_pixel_pose's points and pixel_time_offsets'
    samples (float32), and the first return whose pose is not finite."""
    from drivetrack.geometry import invert_rigid, rigid_from_rotation_translation, rotation_from_rpy
    from drivetrack.waymo import capture_time
    from drivetrack.waymo.kernel import posed_returns

    rng = np.random.default_rng(9)
    h, w, m = 8, 50, 300
    position = np.array([812.0, -1933.0, 41.0])
    pose = np.concatenate([rng.normal(size=(h, w, 3)) * 0.1, position + rng.normal(size=(h, w, 3)) * 8.0],
                          -1).astype(np.float32)
    rows, cols = rng.integers(0, h, m).astype(np.int32), rng.integers(0, w, m).astype(np.int32)
    points = rng.normal(size=(m, 3)) * 30.0
    world_from_vehicle = rigid_from_rotation_translation(rotation_from_rpy(0.01, 0.02, 1.0), position)
    args = (capture_time.MIN_EGO_SPEED_MPS, capture_time.MAX_ABS_OFFSET_S)
    finite = []
    for velocity in (np.array([30.0, -25.0, 0.4]), np.array([0.5, 0.0, 0.0])):   # moving; standing still
        out, dt, bad = posed_returns(points, rows, cols, pose, invert_rigid(world_from_vehicle), position, velocity,
                                     *args)
        pixel = pose[rows, cols]
        assert bad == -1
        np.testing.assert_array_equal(out, lidar.apply_pixel_pose(points, pixel, world_from_vehicle))
        want = capture_time.pixel_time_offsets(pixel[:, 3:6], position, velocity, args[0]).astype(np.float32)
        np.testing.assert_array_equal(dt, want)
        finite.append(int(np.isfinite(dt).sum()))
    assert 0 < finite[0] < m and finite[1] == 0        # beyond MAX_ABS_OFFSET_S: NaN; standing still: NaN
    pose[rows[17], cols[17], 4] = np.nan
    first = int(np.flatnonzero(~np.isfinite(pose[rows, cols]).all(axis=1))[0])
    assert posed_returns(points, rows, cols, pose, invert_rigid(world_from_vehicle), position, velocity, *args)[2] == first
