"""Synthetic Waymo v2 segments: schema, determinism, lidar geometry, exact ground truth."""
from __future__ import annotations

import glob
import os

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from _waymo_parquet import assert_official_component

from drivetrack.camera.model import CameraModel
from drivetrack.geometry import invert_rigid, matrix_from_flat, rotation_from_rpy, transform_points
from drivetrack.synth import SynthConfig, generate_segment, load_ground_truth
from drivetrack.waymo import lidar as lidar_geometry
from drivetrack.waymo.schema import COMPONENTS, CameraName, LaserName, types_compatible
from drivetrack.waymo.writer import build_table, write_component

WRITTEN = ["camera_image", "camera_calibration", "lidar", "lidar_calibration", "lidar_pose",
           "lidar_box", "camera_box", "vehicle_pose", "camera_to_lidar_box_association",
           "lidar_camera_projection", "projected_lidar_box", "lidar_camera_synced_box", "stats"]


@pytest.fixture(scope="module")
def segment(tmp_path_factory):
    root = str(tmp_path_factory.mktemp("synth"))
    summary = generate_segment(root, SynthConfig(seed=11, frames=8, preset="small"), 0)
    return root, summary


def _read(root, name, segment):
    return pq.read_table(f"{root}/training/{name}/{segment}.parquet")


def _calibrations(root, seg):
    cc = COMPONENTS["camera_calibration"]
    rows = _read(root, "camera_calibration", seg).to_pylist()
    models = {}
    for r in rows:
        models[r["key.camera_name"]] = CameraModel(
            *[r[cc.col(f"intrinsic.{p}")] for p in ("f_u", "f_v", "c_u", "c_v", "k1", "k2", "p1", "p2", "k3")],
            width=r[cc.col("width")], height=r[cc.col("height")],
            vehicle_from_camera=matrix_from_flat(r[cc.col("extrinsic.transform")]))
    return models


# ------------------------------------------------------------------ writer
def test_writer_fills_every_column_with_official_types_and_brotli(tmp_path):
    comp = COMPONENTS["camera_calibration"]
    url = write_component({"key.segment_context_name": ["seg"], "key.camera_name": [1],
                           comp.col("extrinsic.transform"): np.eye(4).reshape(1, 16)},
                          str(tmp_path), "training", "camera_calibration", "seg")
    assert url.endswith("training/camera_calibration/seg.parquet")
    table = pq.read_table(url)
    assert table.column_names == [c.name for c in comp.columns]
    for col in comp.columns:
        assert types_compatible(col.type, table.schema.field(col.name).type), col.name
    assert table.column(comp.col("intrinsic.f_u")).null_count == 1
    assert table.column(comp.col("extrinsic.transform")).to_pylist()[0][0] == 1.0
    meta = pq.ParquetFile(url).metadata
    assert {meta.row_group(0).column(i).compression for i in range(meta.num_columns)} == {"BROTLI"}


def test_writer_refuses_unknown_mistyped_and_foreign_rows(tmp_path):
    with pytest.raises(KeyError, match=r"vehicle_pose.*\[VehiclePoseComponent\]\.nope"):
        build_table("vehicle_pose", {"[VehiclePoseComponent].nope": [1.0]})
    with pytest.raises(TypeError, match=r"key.frame_timestamp_micros.*string"):
        build_table("vehicle_pose", {"key.frame_timestamp_micros": pa.array(["x"])})
    with pytest.raises(TypeError, match="key.frame_timestamp_micros"):
        build_table("vehicle_pose", {"key.frame_timestamp_micros": ["not a number"]})
    with pytest.raises(ValueError, match=r"world_from_vehicle.transform.*missing"):
        build_table("vehicle_pose", {"key.frame_timestamp_micros": [1]})
    with pytest.raises(ValueError, match=r"other.*segment 'seg'"):
        write_component({"key.segment_context_name": ["other"],
                         "[VehiclePoseComponent].world_from_vehicle.transform": np.eye(4).reshape(1, 16)},
                        str(tmp_path), "training", "vehicle_pose", "seg")


# ------------------------------------------------------------------ components
def test_every_component_has_every_column_with_official_types(segment):
    root, summary = segment
    seg = summary["segment"]
    assert sorted(summary["files"]) == sorted(WRITTEN)
    for name in WRITTEN:
        table = assert_official_component(f"{root}/training/{name}/{seg}.parquet", name)
        assert set(table.column("key.segment_context_name").to_pylist()) == {seg}


def test_calibrations_are_waymo_like(segment):
    root, summary = segment
    models = _calibrations(root, summary["segment"])
    assert sorted(models) == [1, 2, 3]
    for m in models.values():
        assert (m.width, m.height) == (480, 320)
        assert all(v != 0 for v in (m.k1, m.k2, m.p1, m.p2, m.k3))
        assert 1.5 <= m.vehicle_from_camera[2, 3] <= 2.5
    lc = COMPONENTS["lidar_calibration"]
    rows = {r["key.laser_name"]: r for r in _read(root, "lidar_calibration", summary["segment"]).to_pylist()}
    assert sorted(rows) == [1, 2, 3, 4, 5]
    assert len(rows[int(LaserName.TOP)][lc.col("beam_inclination.values")]) == 32


def test_range_images_decode_to_the_ray_cast_points(segment):
    """Decode TOP and short-range images with lidar.py alone; compare with the exact hits."""
    root, summary = segment
    seg = summary["segment"]
    truth = load_ground_truth(root, "training", seg)
    lc, li, lp, vp = (COMPONENTS[n] for n in ("lidar_calibration", "lidar", "lidar_pose", "vehicle_pose"))
    calib = {r["key.laser_name"]: r for r in _read(root, "lidar_calibration", seg).to_pylist()}
    poses = {r["key.frame_timestamp_micros"]: matrix_from_flat(r[vp.col("world_from_vehicle.transform")])
             for r in _read(root, "vehicle_pose", seg).to_pylist()}
    pixel_poses = {r["key.frame_timestamp_micros"]: np.array(r[lp.col("range_image_return1.values")], np.float64)
                   .reshape(r[lp.col("range_image_return1.shape")])
                   for r in _read(root, "lidar_pose", seg).to_pylist()}
    stamps = sorted(poses)
    h = truth.hits
    max_err, checked, ground_z = 0.0, 0, []
    for r in _read(root, "lidar", seg).to_pylist():
        laser, ts = r["key.laser_name"], r["key.frame_timestamp_micros"]
        t = stamps.index(ts)
        c = calib[laser]
        vehicle_from_lidar = matrix_from_flat(c[lc.col("extrinsic.transform")])
        for ret in (1, 2):
            img = np.array(r[li.col(f"range_image_return{ret}.values")], np.float64).reshape(
                r[li.col(f"range_image_return{ret}.shape")])
            H, W, _ = img.shape
            incl = lidar_geometry.beam_inclinations(H, c[lc.col("beam_inclination.values")],
                                                    c[lc.col("beam_inclination.min")],
                                                    c[lc.col("beam_inclination.max")])
            dirs = lidar_geometry.sensor_directions(incl, lidar_geometry.beam_azimuths(W, vehicle_from_lidar))
            rows, cols = np.nonzero(img[..., 0] > 0)
            pts = transform_points(vehicle_from_lidar, img[rows, cols, 0:1] * dirs[rows, cols])
            if laser == int(LaserName.TOP):
                pp = pixel_poses[ts][rows, cols]
                world_from_pixel = np.zeros((rows.size, 4, 4))
                world_from_pixel[:, :3, :3] = rotation_from_rpy(pp[:, 0], pp[:, 1], pp[:, 2])
                world_from_pixel[:, :3, 3] = pp[:, 3:]
                world_from_pixel[:, 3, 3] = 1
                world = np.einsum("nij,nj->ni", world_from_pixel[:, :3, :3], pts) + pp[:, 3:]
            else:
                world = transform_points(poses[ts], pts)
            ground_z.append(world[:, 2])
            pts_frame = transform_points(invert_rigid(poses[ts]), world)
            sel = (h["frame"] == t) & (h["laser"] == laser) & (h["return_index"] == ret)
            lookup = {(a, b): i for i, (a, b) in enumerate(zip(rows.tolist(), cols.tolist()))}
            idx = np.array([lookup[(a, b)] for a, b in zip(h["row"][sel].tolist(), h["col"][sel].tolist())], int)
            if idx.size:
                max_err = max(max_err, float(np.abs(pts_frame[idx] - h["point_vehicle"][sel]).max()))
                checked += idx.size
    assert checked > 1000
    # float32 storage of range (and of the per-pixel pose) bounds the error well below 1 mm
    assert max_err < 1e-3, max_err
    z = np.concatenate(ground_z)
    assert (np.abs(z) < 1e-3).mean() > 0.5      # most returns lie on the ground plane z = 0


def test_second_returns_exist_but_are_sparse(segment):
    root, summary = segment
    li = COMPONENTS["lidar"]
    r = _read(root, "lidar", summary["segment"]).to_pylist()[0]
    first = np.array(r[li.col("range_image_return1.values")]).reshape(-1, 4)
    second = np.array(r[li.col("range_image_return2.values")]).reshape(-1, 4)
    assert (second[:, 0] > 0).sum() < 0.2 * (first[:, 0] > 0).sum()
    tables = [_read(root, "lidar", summary["segment"])]
    vals = np.concatenate([np.array(v).reshape(-1, 4)[:, 0] for v in
                           tables[0].column(li.col("range_image_return2.values")).to_pylist()])
    assert (vals > 0).sum() > 0


def test_ground_truth_projection_equals_camera_model(segment):
    root, summary = segment
    seg = summary["segment"]
    truth = load_ground_truth(root, "training", seg)
    models = _calibrations(root, seg)
    obj, h = truth.objects, truth.hits
    n = h["frame"].size
    pick = np.random.default_rng(0).choice(n, size=min(n, 500), replace=False)
    for cam in truth.camera_names:
        ci = truth.camera_axis(cam)
        model = models[cam]
        for tau in (0, 7):
            world_from_box = obj["world_from_box"][h["object_index"][pick], tau]
            pw = np.einsum("nij,nj->ni", world_from_box[:, :3, :3], h["point_box"][pick]) + world_from_box[:, :3, 3]
            camera_from_world = invert_rigid(obj["world_from_vehicle"][tau] @ model.vehicle_from_camera)
            px, ok = model.pixels_from_camera(transform_points(camera_from_world, pw))
            got = h["pixels"][pick, ci, tau]
            assert np.array_equal(np.isfinite(got[:, 0]), ok)
            assert np.abs(got[ok] - px[ok]).max() < 1e-3
            vis = h["visible"][pick, ci, tau]
            assert not (vis & ~(ok & model.inside_image(px))).any()


def test_ground_truth_visibility_has_visible_and_occluded_points(segment):
    root, summary = segment
    truth = load_ground_truth(root, "training", summary["segment"])
    h = truth.hits
    px = h["pixels"]
    C = len(truth.camera_names)
    inside = np.zeros(h["visible"].shape, bool)
    for ci, cam in enumerate(truth.camera_names):
        depth = truth.depth(cam)
        H, W = depth.shape[1:]
        with np.errstate(invalid="ignore"):
            inside[:, ci] = (px[:, ci, :, 0] >= 0) & (px[:, ci, :, 0] < W) & (px[:, ci, :, 1] >= 0) & (px[:, ci, :, 1] < H)
    visible, occluded = h["visible"], inside & ~h["visible"]
    assert visible.sum() > 1000 and occluded.sum() > 1000
    assert C == 3
    # each return's own frame, own lidar-facing side: visible in some camera most of the time
    # the dense depth agrees with visible points (same surface within a pixel footprint)
    ci = 0
    depth = truth.depth(truth.camera_names[ci])
    models = _calibrations(root, summary["segment"])
    model = models[truth.camera_names[ci]]
    n_idx, t_idx = np.nonzero(visible[:, ci])
    obj = truth.objects
    wfb = obj["world_from_box"][h["object_index"][n_idx], t_idx]
    pw = np.einsum("nij,nj->ni", wfb[:, :3, :3], h["point_box"][n_idx]) + wfb[:, :3, 3]
    camera_from_world = invert_rigid(obj["world_from_vehicle"][t_idx] @ model.vehicle_from_camera)
    x_cam = np.einsum("nj,nj->n", camera_from_world[:, 0, :3], pw) + camera_from_world[:, 0, 3]
    p = px[n_idx, ci, t_idx].astype(int)
    d = depth[t_idx, p[:, 1], p[:, 0]]
    assert np.median(np.abs(d - x_cam) / x_cam) < 0.01
    assert depth.dtype == np.float32 and (depth == 0).any() and (depth > 0).mean() > 0.4


def test_boxes_carry_exact_vehicle_frame_speed(segment):
    root, summary = segment
    seg = summary["segment"]
    truth = load_ground_truth(root, "training", seg)
    lb = COMPONENTS["lidar_box"]
    boxes = _read(root, "lidar_box", seg).to_pylist()
    stamps = list(truth.objects["timestamps_micros"])
    ids = list(truth.objects["object_id"])
    moving, counted = 0, 0
    wfb = truth.objects["world_from_box"]
    for r in boxes:
        t, k = stamps.index(r["key.frame_timestamp_micros"]), ids.index(r["key.laser_object_id"])
        speed = np.array([r[lb.col(f"speed.{a}")] for a in "xyz"])
        if 0 < t < len(stamps) - 1:
            # central difference of the exact world positions, rotated into the vehicle frame
            v_world = (wfb[k, t + 1, :3, 3] - wfb[k, t - 1, :3, 3]) / 0.2
            v_vehicle = truth.objects["world_from_vehicle"][t, :3, :3].T @ v_world
            assert np.abs(speed - v_vehicle).max() < 0.05
        center = np.array([r[lb.col(f"box.center.{a}")] for a in "xyz"])
        exact = transform_points(invert_rigid(truth.objects["world_from_vehicle"][t]), wfb[k, t, :3, 3][None])[0]
        assert np.abs(center - exact).max() < 1e-9
        moving += np.linalg.norm(speed) > 1.0
        counted += r[lb.col("num_lidar_points_in_box")] > 0
    assert moving > 0 and counted > 0


def test_determinism_and_box_noise_changes_labels_only(tmp_path):
    config = SynthConfig(seed=5, frames=2, preset="small", cameras=("FRONT",))
    generate_segment(str(tmp_path / "a"), config, 0)
    generate_segment(str(tmp_path / "b"), config, 0)
    noisy = SynthConfig(seed=5, frames=2, preset="small", cameras=("FRONT",), box_noise_m=0.2)
    generate_segment(str(tmp_path / "c"), noisy, 0)
    files_a = sorted(os.path.relpath(p, tmp_path / "a") for p in glob.glob(str(tmp_path / "a/**/*.*"), recursive=True))
    assert len(files_a) == 13 + 3
    for rel in files_a:
        a, b, c = ((tmp_path / d / rel).read_bytes() for d in "abc")
        assert a == b, rel
        labels = rel.split("/")[1] in ("lidar_box", "lidar_camera_synced_box", "projected_lidar_box")
        assert (a != c) if labels else (a == c), rel


def test_range_noise_moves_the_returns_along_their_rays_and_keeps_the_truth(tmp_path):
    """``range_noise_m``: every written range is the true one plus Gaussian noise of that sigma
    (same returns, zero mean); the cameras, the labels' boxes and the ground truth (where each ray
    hit the surface, its pixels and visibility) stay as without it."""
    exact = SynthConfig(seed=5, frames=2, preset="small", cameras=("FRONT",))
    noisy = SynthConfig(seed=5, frames=2, preset="small", cameras=("FRONT",), range_noise_m=0.03)
    seg = generate_segment(str(tmp_path / "a"), exact, 0)["segment"]
    generate_segment(str(tmp_path / "b"), noisy, 0)
    li = COMPONENTS["lidar"]
    diffs = []
    for ra, rb in zip(_read(str(tmp_path / "a"), "lidar", seg).to_pylist(), _read(str(tmp_path / "b"), "lidar", seg).to_pylist()):
        for ret in (1, 2):
            a = np.array(ra[li.col(f"range_image_return{ret}.values")]).reshape(-1, 4)[:, 0]
            b = np.array(rb[li.col(f"range_image_return{ret}.values")]).reshape(-1, 4)[:, 0]
            np.testing.assert_array_equal(a > 0, b > 0)
            diffs.append((b - a)[a > 0])
    diff = np.concatenate(diffs)
    assert diff.size > 10000
    assert abs(diff.mean()) < 0.002 and 0.028 < diff.std() < 0.032
    ta, tb = (load_ground_truth(str(tmp_path / d), "training", seg) for d in "ab")
    for key in ("point_box", "point_vehicle", "pixels", "visible"):
        np.testing.assert_array_equal(ta.hits[key], tb.hits[key])
    for name in ("camera_image", "lidar_calibration", "vehicle_pose"):
        assert (tmp_path / "a" / "training" / name / f"{seg}.parquet").read_bytes() == \
            (tmp_path / "b" / "training" / name / f"{seg}.parquet").read_bytes(), name
    with pytest.raises(ValueError, match="range_noise_m"):
        SynthConfig(range_noise_m=-0.01)


def test_box_slack_draws_the_labels_wider_and_keeps_the_rest(tmp_path):
    """``box_slack_m``: every written box (``lidar_box``, ``lidar_camera_synced_box``) is that much
    wider than its object on each side, centres and headings unchanged; the lidar, the cameras and
    the ground truth (the objects' own sizes) stay as without it."""
    exact = SynthConfig(seed=5, frames=2, preset="small", cameras=("FRONT",))
    slack = SynthConfig(seed=5, frames=2, preset="small", cameras=("FRONT",), box_slack_m=0.1)
    seg = generate_segment(str(tmp_path / "a"), exact, 0)["segment"]
    generate_segment(str(tmp_path / "b"), slack, 0)
    for component, box in (("lidar_box", "box"), ("lidar_camera_synced_box", "camera_synced_box")):
        c = COMPONENTS[component]
        a, b = (_read(str(tmp_path / d), component, seg).to_pandas() for d in "ab")
        assert len(a) == len(b) > 0
        for axis in "xyz":
            np.testing.assert_allclose(b[c.col(f"{box}.size.{axis}")], a[c.col(f"{box}.size.{axis}")] + 0.2)
            np.testing.assert_array_equal(b[c.col(f"{box}.center.{axis}")], a[c.col(f"{box}.center.{axis}")])
    ta, tb = (load_ground_truth(str(tmp_path / d), "training", seg) for d in "ab")
    np.testing.assert_array_equal(ta.objects["size"], tb.objects["size"])
    for key in ("point_box", "pixels", "visible"):
        np.testing.assert_array_equal(ta.hits[key], tb.hits[key])
    for name in ("lidar", "camera_image", "vehicle_pose"):
        assert (tmp_path / "a" / "training" / name / f"{seg}.parquet").read_bytes() == \
            (tmp_path / "b" / "training" / name / f"{seg}.parquet").read_bytes(), name
    with pytest.raises(ValueError, match="box_slack_m"):
        SynthConfig(box_slack_m=-0.01)


def test_cli_writes_segments_and_rejects_bad_camera(tmp_path, capsys):
    from drivetrack.cli import main

    assert main(["synth", str(tmp_path), "--frames", "1", "--segments", "2", "--cameras", "FRONT",
                 "--split", "validation"]) == 0
    assert len(glob.glob(str(tmp_path / "validation/lidar/*.parquet"))) == 2
    assert main(["synth", str(tmp_path), "--frames", "1", "--cameras", "BACK"]) == 2
    assert "BACK" in capsys.readouterr().err


def test_load_ground_truth_missing_names_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="drivetrack_ground_truth/nope/objects.npz"):
        load_ground_truth(str(tmp_path), "training", "nope")
    with pytest.raises(KeyError, match="SIDE_LEFT"):
        truth_root = tmp_path / "x"
        generate_segment(str(truth_root), SynthConfig(seed=1, frames=1, cameras=("FRONT",)), 0)
        load_ground_truth(str(truth_root), "training", "drivetrack_synth_s1_0000").camera_axis("SIDE_LEFT")


def test_screen_rectangles_contain_every_object_pixel():
    """Casting objects only inside their screen rectangles gives the same image as casting
    every pixel against every object (the rectangle is a speed-up, never an approximation)."""
    from drivetrack.synth.generate import _Generator, _box_matrix, _pixel_rays, _rect_indices, _screen_rect, _undistorted_extent
    from drivetrack.synth.raycast import cast

    g = _Generator(SynthConfig(seed=3, frames=12, preset="small"), 0)
    checked = 0
    for cam, model in g.cameras.items():
        rays = _pixel_rays(model)
        extent = _undistorted_extent(model, rays)
        for t in (0, 11):
            world_from_camera = g.world_from_vehicle[t] @ model.vehicle_from_camera
            dirs = rays @ world_from_camera[:3, :3].T
            origins = np.broadcast_to(world_from_camera[:3, 3], dirs.shape)
            everything = np.arange(dirs.shape[0])
            rects = [_screen_rect(model, extent, invert_rigid(world_from_camera)
                                  @ _box_matrix(g.centers[k, t], g.headings[k, t]), g.sizes[k])
                     for k in range(g.K)]

            def pose_of(k, idx, t=t):
                return g.centers[k, t], g.headings[k, t]

            fast = cast(origins, dirs, g.world, pose_of,
                        [None if r is None else _rect_indices(r, model.width) for r in rects])
            slow = cast(origins, dirs, g.world, pose_of, [everything] * g.K)
            assert np.array_equal(fast.obj, slow.obj)
            assert np.array_equal(fast.t, slow.t)
            checked += int((slow.obj >= 0).sum())
    assert checked > 1000


def test_preview_renders(segment):
    from drivetrack.synth.preview import render_preview

    root, summary = segment
    img = render_preview(root, "training", summary["segment"], frame=7)
    assert img.shape == (640, 1440, 3) and img.dtype == np.uint8
    with pytest.raises(IndexError, match="frame 99"):
        render_preview(root, "training", summary["segment"], frame=99)


def test_presets_scale_the_cameras_and_keep_waymo_lidars_from_medium_up():
    from drivetrack.synth import PRESETS
    from drivetrack.synth.sensors import camera_models

    full = camera_models(PRESETS["full"], ("FRONT", "SIDE_LEFT"))
    medium = camera_models(PRESETS["medium"], ("FRONT", "SIDE_LEFT"))
    for name, model in medium.items():
        assert (model.width, model.height) == (full[name].width // 2, full[name].height // 2)
        assert model.f_u == full[name].f_u / 2
    assert PRESETS["medium"].top_shape == PRESETS["full"].top_shape == (64, 2650)
    assert PRESETS["medium"].short_shape == PRESETS["full"].short_shape
