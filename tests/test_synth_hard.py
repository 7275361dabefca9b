"""The hard synthetic world (issues 15 and 16): deterministic, valid v2 schema, contains every case
(back faces, poles, side-camera movers), cameras triggered by the sweep, label_time conventions."""
from __future__ import annotations

import glob
import os

import numpy as np
import pyarrow.parquet as pq
import pytest
from _waymo_parquet import assert_official_component

from drivetrack.geometry import invert_rigid, matrix_from_flat
from drivetrack.synth import SynthConfig, generate_segment, load_ground_truth
from drivetrack.waymo.schema import COMPONENTS, BoxType, CameraName, LaserName

CAMERAS = ("FRONT", "FRONT_LEFT", "SIDE_LEFT", "SIDE_RIGHT")
HARD = SynthConfig(seed=7, frames=6, preset="small", cameras=CAMERAS, world="hard")


@pytest.fixture(scope="module")
def hard(tmp_path_factory):
    root = str(tmp_path_factory.mktemp("hard"))
    summary = generate_segment(root, HARD, 0)
    return root, summary, load_ground_truth(root, "training", summary["segment"])


def _read(root, name, seg):
    return pq.read_table(f"{root}/training/{name}/{seg}.parquet")


def _files(root):
    return sorted(os.path.relpath(p, root) for p in glob.glob(f"{root}/**/*.*", recursive=True))


def test_hard_world_writes_the_official_schema(hard):
    root, summary, _ = hard
    seg = summary["segment"]
    for name in summary["files"]:
        assert_official_component(f"{root}/training/{name}/{seg}.parquet", name)
    assert len(summary["files"]) == 13


def test_hard_world_is_deterministic_and_keeps_the_default_objects(tmp_path):
    config = SynthConfig(seed=3, frames=2, preset="small", cameras=("SIDE_LEFT",), world="hard")
    generate_segment(str(tmp_path / "a"), config, 0)
    generate_segment(str(tmp_path / "b"), config, 0)
    files = _files(tmp_path / "a")
    assert len(files) == 13 + 3 and files == _files(tmp_path / "b")
    for rel in files:
        assert (tmp_path / "a" / rel).read_bytes() == (tmp_path / "b" / rel).read_bytes(), rel
    # the hard world adds objects: the default ones keep their ids, sizes and poses, but for the
    # overtaking car, whose lane beside the ego is the overtaken car's
    default = SynthConfig(seed=3, frames=2, preset="small", cameras=("SIDE_LEFT",))
    generate_segment(str(tmp_path / "d"), default, 0)
    seg = "drivetrack_synth_s3_0000"
    h = load_ground_truth(str(tmp_path / "a"), "training", seg).objects
    d = load_ground_truth(str(tmp_path / "d"), "training", seg).objects
    kept = np.flatnonzero(d["object_id"] != d["object_id"][1])         # the second object is the overtaking car
    k = kept.size
    assert h["object_id"].size > k + 1 and (h["object_id"][:k] == d["object_id"][kept]).all()
    np.testing.assert_array_equal(h["world_from_box"][:k], d["world_from_box"][kept])
    np.testing.assert_array_equal(h["world_from_vehicle"], d["world_from_vehicle"])
    assert "role" not in d and "facing" not in load_ground_truth(str(tmp_path / "d"), "training", seg).hits


def test_hard_world_contains_each_case(hard):
    root, summary, truth = hard
    objects, hits = truth.objects, truth.hits
    roles = objects["role"].astype(str)
    for role in ("oblique", "occluder", "hidden", "pole", "low_sign", "pedestrian_near_car",
                 "close_pass", "overtaken_right", "turning", "crossing_cyclist"):
        assert role in roles, role
    poles = np.flatnonzero(roles == "pole")
    assert (objects["type"][poles] == int(BoxType.SIGN)).all()
    assert np.allclose(objects["size"][poles, :2], 0.3)
    # back faces: points inside an image whose face points away from the camera; never visible
    inside = np.isfinite(hits["pixels"][..., 0])
    back = inside & ~hits["facing"]
    assert back.any()
    assert not (hits["visible"] & ~hits["facing"]).any()
    # oblique cars: the lidar returns come from two faces (an end and a side) of one car
    from drivetrack.synth.truth import face_normals_box
    oblique = np.flatnonzero(roles == "oblique")
    on = np.isin(hits["object_index"], oblique)
    normals = face_normals_box(hits["object_index"][on], hits["point_box"][on], objects["size"])
    assert np.abs(normals[:, 0]).sum() > 0 and np.abs(normals[:, 1]).sum() > 0
    # the car behind the van: seen at the start, progressively hidden
    k = int(np.flatnonzero(roles == "hidden")[0])
    seen = hits["visible"][hits["object_index"] == k].sum(axis=(0, 1))          # per frame
    assert seen[0] > 0 and seen[-1] < seen[0] / 2, seen
    # a mover beside the ego seen by a side camera, 1-3 m from the ego's side
    axis = {CameraName[c].value: i for i, c in enumerate(CAMERAS)}
    speed = np.linalg.norm(objects["velocity_world"], axis=-1)
    for role, cam in (("close_pass", "SIDE_LEFT"), ("overtaken_right", "SIDE_RIGHT")):
        k = int(np.flatnonzero(roles == role)[0])
        assert (speed[k] > 1.0).all(), role
        seen = hits["visible"][hits["object_index"] == k][:, axis[CameraName[cam].value]]
        assert seen.any(), (role, cam)
        box_v = invert_rigid(objects["world_from_vehicle"]) @ objects["world_from_box"][k]
        gap = np.abs(box_v[:, 1, 3]) - objects["size"][k, 1] / 2 - 1.0     # the ego is ~2 m wide
        assert (gap > 1.0).all() and (gap < 3.0).all(), (role, gap)


def test_cameras_fire_when_the_sweep_crosses_them(hard):
    root, summary, truth = hard
    seg = summary["segment"]
    ci = COMPONENTS["camera_image"]
    cc = COMPONENTS["camera_calibration"]
    yaw = {r["key.camera_name"]: np.arctan2(*matrix_from_flat(r[cc.col("extrinsic.transform")])[[1, 0], 0])
           for r in _read(root, "camera_calibration", seg).to_pylist()}
    rows = _read(root, "camera_image", seg).to_pylist()
    assert len(rows) == len(CAMERAS) * HARD.frames
    offsets = {}
    for r in rows:
        cam, frame_s = r["key.camera_name"], r["key.frame_timestamp_micros"] / 1e6
        offset = r[ci.col("pose_timestamp")] - frame_s
        # the TOP sweep runs from azimuth +pi (frame - 50 ms) to -pi (frame + 50 ms)
        assert offset == pytest.approx(-yaw[cam] / (2 * np.pi) * 0.1, abs=2e-6), cam
        trigger = r[ci.col("rolling_shutter_params.camera_trigger_time")]
        done = r[ci.col("rolling_shutter_params.camera_readout_done_time")]
        assert (trigger + done) / 2 == pytest.approx(r[ci.col("pose_timestamp")], abs=1e-6)
        offsets[cam] = offset
    assert offsets[int(CameraName.SIDE_LEFT)] == pytest.approx(-0.025, abs=1e-3)
    assert offsets[int(CameraName.SIDE_RIGHT)] == pytest.approx(0.025, abs=1e-3)
    # the image pose is the ego pose at the camera's time, not at the frame time
    t = 3
    pose = {r["key.camera_name"]: matrix_from_flat(r[ci.col("pose.transform")]) for r in rows
            if r["key.frame_timestamp_micros"] == truth.objects["timestamps_micros"][t]}
    side = pose[int(CameraName.SIDE_LEFT)]
    frame_pose = truth.objects["world_from_vehicle"][t]
    moved = np.linalg.norm(side[:3, 3] - frame_pose[:3, 3])
    assert 0.1 < moved < 0.3            # 25 ms at 7-9.5 m/s
    np.testing.assert_allclose(side, truth.objects["world_from_camera_vehicle"][axis_of(truth, "SIDE_LEFT"), t],
                               atol=1e-9)


def axis_of(truth, camera):
    return truth.camera_axis(camera)


def test_label_time_sweep_moves_boxes_by_velocity_times_the_sweep_offset(tmp_path):
    seg = "drivetrack_synth_s5_0000"
    boxes = {}
    for label_time in ("frame", "sweep"):
        config = SynthConfig(seed=5, frames=2, preset="small", cameras=("FRONT",), world="hard",
                             label_time=label_time)
        root = str(tmp_path / label_time)
        generate_segment(root, config, 0)
        boxes[label_time] = _read(root, "lidar_box", seg).to_pandas()
        truth = load_ground_truth(root, "training", seg)
    lb = COMPONENTS["lidar_box"]
    lc = COMPONENTS["lidar_calibration"]
    top = [r for r in _read(str(tmp_path / "frame"), "lidar_calibration", seg).to_pylist()
           if r["key.laser_name"] == int(LaserName.TOP)][0]
    vehicle_from_lidar = matrix_from_flat(top[lc.col("extrinsic.transform")])
    frame, sweep = boxes["frame"], boxes["sweep"]
    keys = ["key.frame_timestamp_micros", "key.laser_object_id"]
    assert (frame[keys].values == sweep[keys].values).all()
    center = [lb.col(f"box.center.{a}") for a in "xyz"]
    speed = [lb.col(f"speed.{a}") for a in "xyz"]    # z: the vehicle frame pitches and rolls
    c_frame, c_sweep = frame[center].to_numpy(), sweep[center].to_numpy()
    displacement = c_sweep - c_frame
    still = frame[speed].abs().max(axis=1).to_numpy() == 0
    np.testing.assert_array_equal(displacement[still], 0.0)
    # straight movers (constant world velocity: not weaving or turning): displacement = velocity
    # (vehicle frame) x dt, dt = when the sweep passed the box centre: -azimuth(centre in the lidar
    # frame) / 2 pi x 0.1 s
    velocity = truth.objects["velocity_world"]
    constant = np.abs(velocity - velocity[:, :1]).max(axis=(1, 2)) < 1e-12
    straight = set(truth.objects["object_id"].astype(str)[constant])
    rows = np.flatnonzero(~still & frame["key.laser_object_id"].isin(straight).to_numpy())
    assert rows.size >= 5
    v = sweep[speed].to_numpy()[rows]
    dt = np.sum(displacement[rows] * v, axis=1) / np.sum(v * v, axis=1)
    np.testing.assert_allclose(displacement[rows], v * dt[:, None], atol=1e-9)
    p = (invert_rigid(vehicle_from_lidar)[:3, :3] @ (c_sweep[rows] - vehicle_from_lidar[:3, 3]).T).T
    mount_yaw = np.arctan2(vehicle_from_lidar[1, 0], vehicle_from_lidar[0, 0])
    expected = -np.angle(np.exp(1j * (np.arctan2(p[:, 1], p[:, 0]) + mount_yaw))) / (2 * np.pi) * 0.1
    # the ego moves and turns during dt, so the frame-time azimuth is good to a few ms
    np.testing.assert_allclose(dt, expected, atol=3e-3)
    assert np.abs(dt).max() > 0.01
    # the truth stays at the frame time
    assert truth.objects["label_time_offset_s"].shape == truth.objects["labelled"].shape


def test_world_options_are_checked():
    with pytest.raises(ValueError, match=r"SynthConfig.world.*'nope'"):
        SynthConfig(world="nope")
    with pytest.raises(ValueError, match=r"SynthConfig.label_time.*'camera'"):
        SynthConfig(label_time="camera")
    with pytest.raises(ValueError, match=r"SynthConfig.camera_trigger"):
        SynthConfig(camera_trigger="lidar")
    # no camera, an unknown one, or a bare name (not a tuple): refused by name before any work
    for cameras in ((), ("FRONT", "REAR"), "FRONT"):
        with pytest.raises(ValueError, match=r"SynthConfig.cameras: .*found"):
            SynthConfig(cameras=cameras)
    assert SynthConfig().trigger == "frame" and SynthConfig(world="hard").trigger == "sweep"
    assert SynthConfig(world="hard", camera_trigger="frame").trigger == "frame"


def test_cli_world_and_timing_options(tmp_path, capsys):
    from drivetrack.cli import main

    assert main(["synth", str(tmp_path), "--frames", "1", "--cameras", "SIDE_RIGHT", "--world", "hard",
                 "--label-time", "sweep"]) == 0
    assert "world hard, cameras at sweep time, lidar_box at sweep time" in capsys.readouterr().out
    objects = load_ground_truth(str(tmp_path), "training", "drivetrack_synth_s7_0000").objects
    assert "pole" in objects["role"].astype(str)
    assert objects["camera_time_offset_s"][0] == pytest.approx(0.025, abs=1e-3)
    assert np.abs(objects["label_time_offset_s"]).max() > 0.01
    with pytest.raises(SystemExit):
        main(["synth", str(tmp_path), "--world", "harder"])


def test_camera_synced_boxes_are_at_the_most_visible_cameras_time(hard):
    root, summary, truth = hard
    seg = summary["segment"]
    lb, sb = COMPONENTS["lidar_box"], COMPONENTS["lidar_camera_synced_box"]
    label = _read(root, "lidar_box", seg).to_pandas()
    synced = _read(root, "lidar_camera_synced_box", seg).to_pandas()
    keys = ["key.frame_timestamp_micros", "key.laser_object_id"]
    assert (label[keys].values == synced[keys].values).all()
    c_label = label[[lb.col(f"box.center.{a}") for a in "xyz"]].to_numpy()
    c_synced = synced[[sb.col(f"camera_synced_box.center.{a}") for a in "xyz"]].to_numpy()
    v = label[[lb.col(f"speed.{a}") for a in "xyz"]].to_numpy()
    cam = synced[sb.col("most_visible_camera_name")].to_numpy()
    offset = {int(CameraName[c]): -0.1 * yaw / (2 * np.pi) for c, yaw in
              (("FRONT", 0.0), ("FRONT_LEFT", np.pi / 4), ("SIDE_LEFT", np.pi / 2), ("SIDE_RIGHT", -np.pi / 2))}
    rows = np.flatnonzero(cam > 0)
    dt = np.array([offset[c] for c in cam[rows]])
    # label.proto: c + v (t_capture - t_frame), same heading; a global shutter captures the whole
    # image at its pose time (the mount yaws' difference from the nominal: < 0.2 ms, < 4 mm)
    np.testing.assert_allclose(c_synced[rows], c_label[rows] + v[rows] * dt[:, None], atol=5e-3)
    np.testing.assert_array_equal(synced[sb.col("camera_synced_box.heading")], label[lb.col("box.heading")])
    moved = np.linalg.norm(c_synced[rows] - c_label[rows], axis=1)
    assert (moved > 0.2).any()          # a car beside the ego in a side camera: >= 8 m/s x 25 ms
    np.testing.assert_array_equal(c_synced[cam == 0], c_label[cam == 0])


def test_synced_boxes_follow_label_proto_under_rolling_shutter_and_label_noise(tmp_path):
    """Rolling shutter and 5 cm labels: each synced box is its label moved along the label's own
    speed by t_capture - t_frame, t_capture the most visible camera's capture time of the box
    centre (the reader's solve, :func:`drivetrack.tracks.trajectory.synced_samples`, agrees to a
    microsecond) within that image's exposure; the speed columns are a labeller's (fitted to its
    noisy boxes), not the truth's."""
    from drivetrack.tracks.trajectory import synced_samples
    from drivetrack.waymo.reader import load_scene

    noisy = SynthConfig(seed=7, frames=12, preset="small", cameras=CAMERAS, world="hard", rolling_shutter=True,
                        box_noise_m=0.05)
    seg = generate_segment(str(tmp_path / "noisy"), noisy, 0)["segment"]
    scene = load_scene(str(tmp_path / "noisy"), "training", seg, cameras=[int(CameraName[c]) for c in CAMERAS])
    boxes = scene.boxes
    offset, _ = synced_samples(scene)
    seen = np.isfinite(offset)
    assert seen.sum() > 20
    np.testing.assert_allclose(boxes.synced_shift[seen], boxes.speed[seen] * offset[seen, None], atol=1e-5)
    frame_s = scene.timestamps_micros[boxes.frame] * 1e-6
    for cam, frames in scene.cameras.items():
        rows = np.flatnonzero(seen & (boxes.synced_camera == cam))
        t = boxes.frame[rows]
        assert (frame_s[rows] + offset[rows] > frames.trigger_time[t] - 0.02).all()
        assert (frame_s[rows] + offset[rows] < frames.readout_done_time[t] + 0.02).all()
    assert np.ptp(offset[seen & (boxes.synced_camera == int(CameraName.SIDE_LEFT))]) > 0.004   # the readout
    # the truth's speeds: the same world with exact labels (its boxes and speeds do not depend on
    # the cameras or the shutter, so one global-shutter camera keeps the generation cheap)
    exact = generate_segment(str(tmp_path / "exact"), SynthConfig(**{**noisy.__dict__, "box_noise_m": 0.0,
                                                                     "cameras": ("FRONT",), "rolling_shutter": False}), 0)
    truth = load_scene(str(tmp_path / "exact"), "training", exact["segment"], cameras=[]).boxes
    assert (truth.object_id == boxes.object_id).all() and (truth.frame == boxes.frame).all()
    error = np.linalg.norm(boxes.speed - truth.speed, axis=1)
    assert 0.01 < np.median(error) < 0.3


def test_cabin_cars_are_a_body_and_a_cabin_inside_their_label_box(tmp_path):
    """``car_shape="cabin"``: every vehicle is a body and a narrower, shorter cabin whose tight
    bounding box is the label box; the LiDAR and the truth see that solid (returns on the bonnet
    at the body's height, none in the label box's empty corners), the labels and every other
    object are those of the box world, and the truth's face normals follow the solid hit."""
    from drivetrack.synth.raycast import intersect_solids
    from drivetrack.synth.truth import face_normals
    from drivetrack.synth.world import cabin_parts

    size = (4.6, 1.9, 1.6)
    parts = cabin_parts(size)
    lo = np.min([np.subtract(o, h) for o, h in parts], axis=0)
    hi = np.max([np.add(o, h) for o, h in parts], axis=0)
    np.testing.assert_allclose(lo, -np.array(size) / 2, atol=1e-12)
    np.testing.assert_allclose(hi, np.array(size) / 2, atol=1e-12)
    solids = tuple((np.asarray(o), np.asarray(h)) for o, h in parts)
    # straight down onto the bonnet: the body's top, not the label box's; onto the roof: the cabin's
    origins = np.array([[2.0, 0.0, 5.0], [0.0, 0.0, 5.0], [0.0, 0.93, 5.0]])
    t_in, _, axis, part = intersect_solids(origins, np.tile([0.0, 0.0, -1.0], (3, 1)), np.zeros(3), 0.0, solids)
    np.testing.assert_allclose(5.0 - t_in, [-0.8 + 0.55 * 1.6, 0.8, -0.8 + 0.55 * 1.6], atol=1e-9)
    assert axis.tolist() == [2, 2, 2] and part.tolist() == [0, 1, 0]

    root = str(tmp_path / "cabin")
    config = SynthConfig(seed=7, frames=4, preset="small", cameras=("FRONT", "SIDE_RIGHT"), world="hard",
                         car_shape="cabin")
    seg = generate_segment(root, config, 0)["segment"]
    truth = load_ground_truth(root, "training", seg)
    boxes = load_ground_truth(*_box_world(tmp_path, config), "training", seg)
    objects, hits = truth.objects, truth.hits
    for key in ("object_id", "size", "world_from_box", "type"):
        np.testing.assert_array_equal(objects[key], boxes.objects[key])
    vehicles = np.flatnonzero(objects["type"] == int(BoxType.VEHICLE))
    on = np.isin(hits["object_index"], vehicles)
    assert on.sum() > 1000
    point, k = hits["point_box"][on], hits["object_index"][on]
    half = objects["size"][k] / 2
    body_top = -half[:, 2] + 0.55 * 2 * half[:, 2]
    # nothing in the empty corners: above the body's top only within the cabin's footprint
    high = point[:, 2] > body_top + 1e-6
    assert high.any() and (np.abs(point[high, 1]) <= 0.86 * half[high, 1] + 1e-6).all()
    assert (np.abs(point[high, 0] + 0.06 * 2 * half[high, 0]) <= 0.25 * 2 * half[high, 0] + 1e-6).all()
    bonnet = (np.abs(point[:, 2] - body_top) < 1e-6) & (point[:, 0] > 0.3 * 2 * half[:, 0])
    assert bonnet.sum() > 10
    solids = {int(i): tuple((np.asarray(o), np.asarray(h)) for o, h in cabin_parts(objects["size"][i]))
              for i in vehicles.tolist()}
    normals = face_normals(k, point, [solids.get(i, ()) for i in range(int(k.max()) + 1)])
    np.testing.assert_array_equal(normals[bonnet], np.tile([0.0, 0.0, 1.0], (int(bonnet.sum()), 1)))
    # a cabin's side face (the glasshouse) faces sideways although it lies inside the label box
    glass = high & (np.abs(np.abs(point[:, 1]) - 0.86 * half[:, 1]) < 1e-6)
    assert glass.any() and (np.abs(normals[glass, 1]) == 1.0).all()
    assert not (hits["visible"] & ~hits["facing"]).any()


def _box_world(tmp_path, config):
    import dataclasses

    root = str(tmp_path / "box")
    generate_segment(root, dataclasses.replace(config, car_shape="box"), 0)
    return (root,)


def test_body_pedestrians_are_legs_torso_arms_and_head_inside_their_label_box(tmp_path):
    """``pedestrian_shape="body"``: every pedestrian is six solids whose tight bounding box is its
    label box; the LiDAR sees those solids (every return on the surface of one of them, both legs
    hit, none in the empty space between the legs) and the truth's visibility follows them."""
    from drivetrack.synth.world import body_parts

    size = (0.8, 0.7, 1.8)
    parts = body_parts(size)
    lo = np.min([np.subtract(o, h) for o, h in parts], axis=0)
    hi = np.max([np.add(o, h) for o, h in parts], axis=0)
    np.testing.assert_allclose(lo, -np.array(size) / 2, atol=1e-12)
    np.testing.assert_allclose(hi, np.array(size) / 2, atol=1e-12)

    root = str(tmp_path / "body")
    config = SynthConfig(seed=7, frames=4, preset="small", cameras=("FRONT", "SIDE_RIGHT"), world="hard",
                         pedestrian_shape="body")
    seg = generate_segment(root, config, 0)["segment"]
    truth = load_ground_truth(root, "training", seg)
    objects, hits = truth.objects, truth.hits
    walkers = np.flatnonzero(objects["type"] == int(BoxType.PEDESTRIAN))
    on = np.isin(hits["object_index"], walkers)
    assert on.sum() > 200
    point, k = hits["point_box"][on], hits["object_index"][on]
    depth = np.full(point.shape[0], -np.inf)            # the deepest inside any solid (0 on its surface)
    which = np.full(point.shape[0], -1)
    for i in walkers.tolist():
        rows = np.flatnonzero(k == i)
        for p, (offset, half) in enumerate(body_parts(objects["size"][i])):
            inside = np.min(np.asarray(half) - np.abs(point[rows] - offset), axis=1)
            better = inside > depth[rows]
            depth[rows[better]], which[rows[better]] = inside[better], p
    assert (np.abs(depth) < 1e-6).all()                 # on a solid's surface, never between them
    assert {0, 1} <= set(which.tolist())                 # both legs are seen
    assert not (hits["visible"] & ~hits["facing"]).any()
    with pytest.raises(ValueError, match="pedestrian_shape"):
        SynthConfig(pedestrian_shape="stick")


def test_rounded_cars_have_their_body_corners_rounded_inside_the_label_box():
    """``car_shape="rounded"``: the cabin car with each body corner cut by steps whose outer
    corners lie on a circle of radius 0.2 W, so a side's returns end where the corner turns away
    (which depends on where it is seen from); the label box is still their tight bounding box."""
    from drivetrack.synth.raycast import intersect_solids
    from drivetrack.synth.world import cabin_parts, rounded_parts, with_car_shape

    size = (4.6, 1.9, 1.6)
    parts = rounded_parts(size)
    assert parts[-1] == cabin_parts(size)[1]                      # the cabin, unchanged
    lo = np.min([np.subtract(o, h) for o, h in parts], axis=0)
    hi = np.max([np.add(o, h) for o, h in parts], axis=0)
    np.testing.assert_allclose(lo, -np.array(size) / 2, atol=1e-12)
    np.testing.assert_allclose(hi, np.array(size) / 2, atol=1e-12)
    radius = 0.2 * size[1]
    centre = np.array([size[0] / 2 - radius, size[1] / 2 - radius])
    corners = np.array([h[:2] for _, h in parts[:-1]])
    np.testing.assert_allclose(np.linalg.norm(corners - centre, axis=1), radius, atol=1e-12)
    # across the corner at 45 degrees: a box's corner would be hit at (2.3, 0.95); the rounded
    # body is hit inside the circle's bounding square, outside the circle
    solids = tuple((np.asarray(o), np.asarray(h)) for o, h in parts)
    direction = -np.array([[1.0, 1.0, 0.0]]) / np.sqrt(2.0)
    origin = np.array([[2.3 + 3.0, 0.95 + 3.0, -0.5]])
    t_in = intersect_solids(origin, direction, np.zeros(3), 0.0, solids)[0]
    hit = origin[0, :2] + t_in[0] * direction[0, :2]
    assert np.all(hit < [2.3, 0.95]) and np.linalg.norm(hit - centre) >= radius - 1e-9
    assert np.linalg.norm(hit - centre) < radius + 0.06
    with pytest.raises(ValueError, match="car shape"):
        with_car_shape(None, "round")
