"""Track stage on tiny hand-built scenes: geometry known values, filters, occlusion, outputs."""
from __future__ import annotations

import cv2
import numpy as np
import pandas as pd
import pytest

from drivetrack.camera.model import CameraModel
from drivetrack.geometry import box_from_center_heading, invert_rigid, rotation_z, transform_points
from drivetrack.scene import Boxes, CameraFrames, LidarReturns, Scene
from drivetrack.depth.stage import depth_jobs
from drivetrack.tracks import (REJECTION_REASONS, TrackConfig, continuous_runs, object_jobs,
                               object_stats, plan_segment, prepare_segment, rejection_stats, run_object_job,
                               segment_stats, write_object_outputs, write_table)
from drivetrack.tracks.core import track_speeds
from drivetrack.outputs import OBJECT_COLUMNS, SEGMENT_COLUMNS

W, H, F, CX, CY = 160, 120, 100.0, 80.0, 60.0
DT = 0.1
CAMERA_IN_VEHICLE = np.array([1.5, 0.0, 1.5])
FRONT, SIDE_LEFT = 1, 4


def camera_model(k1=0.0, yaw=0.0, direction=0) -> CameraModel:
    vehicle_from_camera = np.eye(4)
    vehicle_from_camera[:3, :3] = rotation_z(yaw)
    vehicle_from_camera[:3, 3] = CAMERA_IN_VEHICLE
    return CameraModel(F, F, CX, CY, k1, 0.0, 0.0, 0.0, 0.0, W, H, vehicle_from_camera, direction)


_JPEG = cv2.imencode(".jpg", np.full((H, W, 3), 90, np.uint8))[1].tobytes()


def face_points(center, size, heading, spacing=0.1) -> np.ndarray:
    """Points (vehicle frame) on the rear face (-x side, facing the camera) of a box."""
    ys = np.arange(-size[1] / 2 + spacing / 2, size[1] / 2, spacing)
    zs = np.arange(-size[2] / 2 + spacing / 2, size[2] / 2, spacing)
    yy, zz = np.meshgrid(ys, zs, indexing="ij")
    local = np.stack([np.full(yy.size, -size[0] / 2), yy.ravel(), zz.ravel()], -1)
    return transform_points(box_from_center_heading(np.asarray(center, float), heading), local)


def wall_points(world_from_vehicle, x_world=40.0, spacing=0.3) -> np.ndarray:
    ys = np.arange(-15, 15, spacing)
    zs = np.arange(-3, 8, spacing)
    yy, zz = np.meshgrid(ys, zs, indexing="ij")
    world = np.stack([np.full(yy.size, x_world), yy.ravel(), zz.ravel()], -1)
    return transform_points(invert_rigid(world_from_vehicle), world)


class SceneBuilder:
    """Boxes given in the world frame per frame; LiDAR returns sampled on their rear faces."""

    def __init__(self, t=30, ego_speed=0.0, k1=0.0, cameras=(FRONT,), jpeg_missing=()):
        self.t = t
        self.timestamps = (1_000_000 + np.arange(t) * DT * 1e6).astype(np.int64)
        self.world_from_vehicle = np.repeat(np.eye(4)[None], t, 0)
        self.world_from_vehicle[:, 0, 3] = ego_speed * np.arange(t) * DT + 100.0
        self.world_from_vehicle[:, 1, 3] = -50.0
        self.k1 = k1
        self.cameras = cameras
        self.jpeg_missing = set(jpeg_missing)
        self.boxes = []        # (object_id, frame, center_world, size, heading_world, type, speed_world)
        self.points = [[] for _ in range(t)]
        self.wall = True
        #: objects whose boxes do not block the lidar (their returns are given as they are: an
        #: object that is not its box, with returns inside it)
        self.hollow: set[str] = set()
        self.lidar_origin = CAMERA_IN_VEHICLE      # returns are only where this point sees a surface

    def add_object(self, object_id, centers_world, size=(4.0, 2.0, 1.5), headings=None, type_=1,
                   frames=None, with_points=True, spacing=0.1, extra_local=None):
        frames = list(range(self.t)) if frames is None else list(frames)
        centers_world = np.asarray(centers_world, float)
        if centers_world.ndim == 1:
            centers_world = np.repeat(centers_world[None], self.t, 0)
        headings = np.zeros(self.t) if headings is None else np.asarray(headings, float)
        velocity = np.gradient(centers_world, DT, axis=0)
        for f in frames:
            vehicle_from_world = invert_rigid(self.world_from_vehicle[f])
            center_v = transform_points(vehicle_from_world, centers_world[f][None])[0]
            heading_v = headings[f]  # the ego never rotates here
            speed_v = vehicle_from_world[:3, :3] @ velocity[f]
            self.boxes.append((object_id, f, center_v, np.asarray(size, float), heading_v, type_, speed_v))
            if with_points:
                self.points[f].append(face_points(center_v, size, heading_v, spacing))
                if extra_local is not None:
                    self.points[f].append(transform_points(box_from_center_heading(center_v, heading_v),
                                                           np.asarray(extra_local, float)))

    def _seen_by_lidar(self, f: int, points: np.ndarray) -> np.ndarray:
        """bool [M]: the segment from the LiDAR to each point crosses no box of frame f."""
        seen = np.ones(len(points), bool)
        origin = np.asarray(self.lidar_origin, float)
        for object_id, frame, center, size, heading, *_ in self.boxes:
            if frame != f or object_id in self.hollow:
                continue
            box_from_vehicle = invert_rigid(box_from_center_heading(center, heading))
            o = transform_points(box_from_vehicle, origin[None])[0]
            d = transform_points(box_from_vehicle, points) - o
            with np.errstate(divide="ignore", invalid="ignore"):
                t1, t2 = (-size / 2 - o) / d, (size / 2 - o) / d
            t_in = np.nanmax(np.minimum(t1, t2), axis=1)
            t_out = np.nanmin(np.maximum(t1, t2), axis=1)
            seen &= ~((t_in <= t_out) & (t_out > 0) & (t_in < 1 - 1e-6))
        return seen

    def build(self) -> Scene:
        pts, frame = [], []
        for f in range(self.t):
            chunk = self.points[f] + ([wall_points(self.world_from_vehicle[f])] if self.wall else [])
            chunk = np.concatenate(chunk) if chunk else np.zeros((0, 3))
            chunk = chunk[self._seen_by_lidar(f, chunk)]
            pts.append(chunk)
            frame.append(np.full(len(chunk), f, np.int32))
        points = np.concatenate(pts)
        m = len(points)
        offsets = np.concatenate([[0], np.cumsum([len(p) for p in pts])]).astype(np.int64)
        lidar = LidarReturns(points, np.concatenate(frame), np.ones(m, np.int8), np.ones(m, np.int8),
                             np.arange(m, dtype=np.int32) % 64, np.arange(m, dtype=np.int32),
                             np.ones(m, np.float32), offsets)
        rows = self.boxes
        boxes = Boxes(np.array([r[0] for r in rows], dtype=object), np.array([r[1] for r in rows], np.int32),
                      np.array([r[2] for r in rows]).reshape(-1, 3), np.array([r[3] for r in rows]).reshape(-1, 3),
                      np.array([r[4] for r in rows], float), np.array([r[5] for r in rows], np.int8),
                      np.array([r[6] for r in rows]).reshape(-1, 3), np.full(len(rows), -1, np.int64))
        cams = {}
        for c in self.cameras:
            model = camera_model(self.k1, yaw=0.0 if c == FRONT else np.pi / 2)
            jpeg = [None if f in self.jpeg_missing else _JPEG for f in range(self.t)]
            cams[c] = CameraFrames(model, jpeg, self.world_from_vehicle.copy(), self.timestamps * 1e-6,
                                   np.zeros((self.t, 6)), np.zeros(self.t), self.timestamps * 1e-6,
                                   self.timestamps * 1e-6)
        return Scene("seg_test-1", "validation", self.timestamps, self.world_from_vehicle.copy(), cams, lidar, boxes)


def expected_pixel(point_camera_waymo, k1=0.0):
    x, y, z = point_camera_waymo
    u, v = -y / x, -z / x
    d = 1 + k1 * (u * u + v * v)
    return np.array([F * u * d + CX, F * v * d + CY])


CONFIG = TrackConfig(rolling_shutter=False, depth_completer_options={"max_reach_px": 3.0})


def world_center(builder, x, y=0.0, z=1.0):
    """A static world position given in the first frame's vehicle frame."""
    return transform_points(builder.world_from_vehicle[0], np.array([[x, y, z]]))[0]


def annotate(scene, config=CONFIG):
    ctx = prepare_segment(scene, config)
    results = {job.object_id: run_object_job(ctx, job) for job in object_jobs(ctx)}
    return ctx, results


# ---------------------------------------------------------------- geometry known values

def test_static_box_projects_where_expected_with_distortion():
    k1 = -0.5
    b = SceneBuilder(k1=k1)
    # one return exactly at vehicle (8, 0.93, 1.72) on the rear face, in every frame
    b.add_object("car", world_center(b, 10.0), extra_local=[[-2.0, 0.93, 0.72]])
    ctx, results = annotate(b.build())
    r = results["car"]
    assert r.projection == "global_shutter"
    point = np.array([8.0, 0.93, 1.72])
    hit = np.flatnonzero(np.all(np.abs(r.points3d[:, 0] - point) < 1e-5, axis=1))
    assert hit.size == b.t          # one track per frame's copy of the return
    expected = expected_pixel(point - CAMERA_IN_VEHICLE, k1)
    np.testing.assert_allclose(r.tracks[hit], np.broadcast_to(expected, (hit.size, b.t, 2)), atol=1e-3)
    undistorted = expected_pixel(point - CAMERA_IN_VEHICLE, 0.0)
    assert np.abs(undistorted - expected).max() > 0.1      # distortion matters at this pixel
    assert r.visibles[hit].all()
    assert r.tracks.dtype == np.float32 and r.tracks.shape == (r.num_tracks, b.t, 2)


def test_points_follow_paper_formula_for_turning_object_and_moving_ego():
    b = SceneBuilder(ego_speed=5.0)
    t = np.arange(b.t) * DT
    centers = np.stack([world_center(b, 12.0)[0] + 4.0 * t, world_center(b, 12.0)[1] + 0.5 * t ** 2,
                        np.full(b.t, 1.0)], -1)
    headings = 0.2 * t
    b.add_object("car", centers, headings=headings, spacing=0.25)
    scene = b.build()
    ctx, results = annotate(scene, TrackConfig(rolling_shutter=False, max_camera_distance_m=50,
                                               depth_completer_options={"max_reach_px": 3.0}))
    r = results["car"]
    boxes = scene.boxes
    frames = r.frames
    world_from_box = scene.world_from_vehicle[boxes.frame] @ box_from_center_heading(boxes.center, boxes.heading)
    # X_tau = W_tau^-1 B_tau B_t^-1 W_t X_t with X_t the original return
    for n in range(0, r.num_tracks, 37):
        src = int(r.query_frames[n])
        x_t = r.points3d[n, src].astype(float)
        b_t = world_from_box[boxes.frame == frames[src]][0]
        for tau in (0, 7, b.t - 1):
            b_tau = world_from_box[boxes.frame == frames[tau]][0]
            expected = transform_points(invert_rigid(scene.world_from_vehicle[frames[tau]]) @ b_tau
                                        @ invert_rigid(b_t) @ scene.world_from_vehicle[frames[src]], x_t[None])[0]
            np.testing.assert_allclose(r.points3d[n, tau], expected, atol=1e-4)
    # the query frame holds the original LiDAR return
    src_points = scene.lidar.points_vehicle[r.lidar_sources[:, 3]]
    np.testing.assert_allclose(r.points3d[np.arange(r.num_tracks), r.query_frames], src_points, atol=1e-5)
    assert set(np.unique(r.query_frames)) == set(range(b.t))


def test_object_moving_with_ego_is_static_in_image_and_speeds_agree():
    b = SceneBuilder(ego_speed=8.0)
    t = np.arange(b.t) * DT
    start = world_center(b, 10.0)
    centers = start[None] + np.outer(8.0 * t, [1, 0, 0])
    b.add_object("car", centers, spacing=0.25)
    ctx, results = annotate(b.build())
    r = results["car"]
    visible = r.visibles
    spread = np.nanmax(r.tracks, axis=1) - np.nanmin(r.tracks, axis=1)
    assert np.all(spread[visible.all(axis=1)] < 1e-3)
    np.testing.assert_allclose(r.track_speed_mps, 8.0, atol=1e-6)
    assert abs(r.box_speed_mps - 8.0) < 1e-6
    assert np.all(r.speed_error_mps < 1e-6)


def test_track_speeds_known_values():
    p = np.zeros((3, 2, 3))
    p[:, 0, 0] = [0.0, 1.0, 2.0]           # 1 m per 0.1 s -> 10 m/s
    p[:, 1, 1] = [0.0, 1.0, 0.0]           # back and forth: path 2 m over 0.2 s
    np.testing.assert_allclose(track_speeds(p, np.array([0, 100_000, 200_000])), [10.0, 10.0])
    assert np.isnan(track_speeds(p[:1], np.array([0]))).all()


# ---------------------------------------------------------------- filters

def test_filters_are_counted_by_reason_and_distance_is_from_the_camera():
    b = SceneBuilder(cameras=(FRONT, SIDE_LEFT))
    b.add_object("good", world_center(b, 10.0))
    # 21.1 m from the vehicle origin, 19.6 m from the camera: kept
    b.add_object("near_camera", world_center(b, 21.0, y=2.0), spacing=0.3)
    b.add_object("far", world_center(b, 30.0, y=-7.0))
    b.add_object("behind", world_center(b, -20.0))
    b.add_object("walker", world_center(b, 10.0, y=4.0), size=(0.8, 0.8, 1.8), type_=2)
    b.add_object("empty", world_center(b, 11.0, y=-6.0), with_points=False)
    half = b.t // 2
    gone = world_center(b, 10.0, y=80.0)
    here = world_center(b, 10.0, y=3.0)
    b.add_object("returns", [here if not 10 <= f < 14 else gone for f in range(b.t)])
    b.add_object("holey", world_center(b, 15.0, y=-3.0), frames=[f for f in range(b.t) if f != half])
    b.add_object("brief", world_center(b, 9.0, y=-2.5), frames=range(5))
    scene = b.build()
    plan = plan_segment(scene, CONFIG)
    reasons = {(r["camera"], r["object_id"]): r["reason"] for r in plan.rejections}
    assert reasons[(FRONT, "far")] == "too_far"
    assert reasons[(FRONT, "behind")] == "not_in_view"
    assert reasons[(FRONT, "walker")] == "object_type"
    assert reasons[(FRONT, "empty")] == "no_points"
    assert reasons[(FRONT, "returns")] == "left_and_returned"
    assert reasons[(FRONT, "holey")] == "label_gap"
    assert reasons[(FRONT, "brief")] == "too_few_frames"
    assert all(reasons[(SIDE_LEFT, oid)] == "camera" for oid in scene.boxes.object_ids())
    accepted = {job.object_id for job in plan.jobs}
    assert accepted == {"good", "near_camera"}
    near = next(j for j in plan.jobs if j.object_id == "near_camera")
    assert 19.0 < near.min_camera_distance_m < 20.0
    assert plan.num_clips_considered == 2 * len(scene.boxes.object_ids())
    assert "10-13" not in reasons and "0-9, 14-29" in next(
        r["detail"] for r in plan.rejections if r["object_id"] == "returns" and r["camera"] == FRONT)

    ctx = prepare_segment(scene, CONFIG, plan=plan)
    results = [run_object_job(ctx, job) for job in object_jobs(ctx)]
    seg = segment_stats(scene.split, scene.segment, plan, results)
    assert list(seg.columns) == list(SEGMENT_COLUMNS)
    row = seg.iloc[0]
    assert row.rejected_camera == 9 and row.rejected_too_far == 1 and row.rejected_label_gap == 1
    assert row.num_object_clips_annotated == 2
    assert row.num_object_clips_considered == 18
    assert sum(row[f"rejected_{r}"] for r in REJECTION_REASONS) + 2 == 18
    table = rejection_stats(plan, results)
    assert len(table) == 16 and set(table.camera) == {"FRONT", "SIDE_LEFT"}

    # without point selection (what pose refinement asks): the same filters but no_points
    quick = plan_segment(scene, CONFIG, select_points=False)
    assert {job.object_id for job in quick.jobs} == {"good", "near_camera", "empty"}
    assert {(r["camera"], r["object_id"]): r["reason"] for r in quick.rejections} == {
        k: v for k, v in reasons.items() if v != "no_points"}
    assert quick.box_points(quick.jobs[0].box_rows)[0].size == 0


def test_longest_run_policy_keeps_the_longest_run():
    b = SceneBuilder()
    gone = world_center(b, 10.0, y=80.0)
    here = world_center(b, 10.0)
    b.add_object("returns", [here if not 5 <= f < 9 else gone for f in range(b.t)])
    plan = plan_segment(b.build(), TrackConfig(fov_runs="longest", min_frames=10, rolling_shutter=False))
    assert [j.object_id for j in plan.jobs] == ["returns"]
    np.testing.assert_array_equal(plan.jobs[0].frames, np.arange(9, b.t))


def test_missing_image_splits_the_run_and_is_named():
    b = SceneBuilder(jpeg_missing={12})
    b.add_object("car", world_center(b, 10.0))
    plan = plan_segment(b.build(), CONFIG)
    assert [r["reason"] for r in plan.rejections] == ["image_gap"]


def test_continuous_runs():
    np.testing.assert_array_equal(continuous_runs(np.array([0, 1, 1, 0, 1], bool)), [[1, 2], [4, 4]])
    assert continuous_runs(np.zeros(4, bool)).shape == (0, 2)


def test_ground_points_are_removed():
    b = SceneBuilder()
    # box bottom at z = 0.25; a point 0.1 m above the bottom and one 0.5 m above it
    b.add_object("car", world_center(b, 10.0), extra_local=[[-1.0, 0.0, -0.65], [-1.0, 0.0, -0.25]])
    plan = plan_segment(b.build(), CONFIG)
    idx = plan.box_point_index[plan.box_point_offsets[0]:plan.box_point_offsets[1]]
    z = plan.scene.lidar.points_vehicle[idx, 2]
    assert np.isclose(z, 0.5).any() and not np.isclose(z, 0.1).any()


@pytest.mark.parametrize("scan_max_boxes", [0, 24], ids=["sorted", "scan"])
def test_returns_in_boxes_equal_a_brute_force_box_test(monkeypatch, scan_max_boxes):
    """drivetrack.boxes.returns_in_boxes (the plan's per-box selection): its x-slab pre-filter
    (found in the frame sorted by x, or by a scan of the frame) loses nothing against testing
    every return of the frame against the box."""
    from drivetrack import boxes as boxes_module
    from drivetrack.boxes import returns_in_boxes

    monkeypatch.setattr(boxes_module, "SCAN_MAX_BOXES", scan_max_boxes)

    b = SceneBuilder()
    b.add_object("car", world_center(b, 10.0), extra_local=[[-1.0, 0.0, -0.65], [-1.0, 0.0, -0.25]])
    b.add_object("near", world_center(b, 6.0, 2.0))
    scene = b.build()
    boxes, lidar = scene.boxes, scene.lidar
    rows = np.arange(len(boxes))
    offsets, index = returns_in_boxes(scene, rows, None, None, 0.0, 0.2, compensate_sweep_motion=False)
    for row in rows:
        part = lidar.of_frame(int(boxes.frame[row]))
        local = transform_points(invert_rigid(boxes.vehicle_from_box(row)), lidar.points_vehicle[part])
        ok = np.all(np.abs(local) <= boxes.size[row] / 2.0, axis=-1) & (local[:, 2] >= -boxes.size[row, 2] / 2 + 0.2)
        np.testing.assert_array_equal(index[offsets[row]:offsets[row + 1]], np.arange(part.start, part.stop)[ok])
    assert index.size > 0


@pytest.mark.parametrize("scan_max_boxes", [0, 24], ids=["sorted", "scan"])
def test_returns_in_boxes_keep_the_grown_corners(monkeypatch, scan_max_boxes):
    """With a positive margin the slab pre-filter reaches the grown box's corners: a return just
    inside the corner of a box grown by 0.5 m, turned so that its diagonal lies along x, is kept
    (the radius of the ungrown box plus the margin falls 0.11 m short of that corner)."""
    from drivetrack import boxes as boxes_module
    from drivetrack.boxes import inside_box, returns_in_boxes

    monkeypatch.setattr(boxes_module, "SCAN_MAX_BOXES", scan_max_boxes)

    size, margin = np.array([4.0, 2.0, 1.5]), 0.5
    corner = np.array([size[0] / 2 + 0.45, size[1] / 2 + 0.45, 0.0])
    b = SceneBuilder()
    b.add_object("car", world_center(b, 10.0), size=size, headings=np.full(b.t, -np.arctan2(corner[1], corner[0])),
                 extra_local=[corner, -corner])
    scene = b.build()
    boxes, lidar = scene.boxes, scene.lidar
    rows = np.arange(len(boxes))
    offsets, index = returns_in_boxes(scene, rows, None, None, margin, 0.2, compensate_sweep_motion=False)
    for row in rows:
        part = lidar.of_frame(int(boxes.frame[row]))
        local = transform_points(invert_rigid(boxes.vehicle_from_box(row)), lidar.points_vehicle[part])
        ok = inside_box(local, boxes.size[row], margin, 0.2)
        assert np.isclose(local[ok], -corner).all(axis=-1).any()      # the corner the lidar sees
        np.testing.assert_array_equal(index[offsets[row]:offsets[row + 1]], np.arange(part.start, part.stop)[ok])


def test_duplicate_box_is_an_error_naming_object_and_frame():
    b = SceneBuilder()
    b.add_object("car", world_center(b, 10.0))
    b.add_object("car", world_center(b, 10.0), frames=[3])
    with pytest.raises(ValueError, match=r"seg_test-1.*'car'.*frame 3"):
        plan_segment(b.build(), CONFIG)


def test_bad_config_names_the_field():
    with pytest.raises(ValueError, match="cameras.*BACK"):
        TrackConfig(cameras=("BACK",))
    with pytest.raises(ValueError, match="fov_runs"):
        TrackConfig(fov_runs="maybe")
    with pytest.raises(ValueError, match="blind_zone_laser.*depth_lasers.*'FRONT'"):
        TrackConfig(blind_zone_laser="FRONT", depth_lasers=("TOP",))
    assert TrackConfig.from_dict(TrackConfig().to_dict()) == TrackConfig()


# ---------------------------------------------------------------- occlusion

def test_occlusion_by_a_box_moving_in_front():
    b = SceneBuilder()
    b.add_object("back", world_center(b, 12.0))
    t = np.arange(b.t) * DT
    start = world_center(b, 6.0, y=-3.0)
    b.add_object("front", start[None] + np.outer(2.0 * t, [0, 1, 0]), size=(1.0, 0.8, 0.8), spacing=0.05)
    scene = b.build()
    ctx, results = annotate(scene, TrackConfig(rolling_shutter=False, max_camera_distance_m=30,
                                               depth_completer_options={"max_reach_px": 3.0}))
    back = results["back"]
    model = scene.cameras[FRONT].model
    front_rows = np.flatnonzero(scene.boxes.object_id == "front")
    n_inside = n_outside = 0
    for tau in range(b.t):
        row = front_rows[scene.boxes.frame[front_rows] == tau][0]
        face = face_points(scene.boxes.center[row], (1.0, 0.8, 0.8), 0.0, 0.05)
        px, _ = model.pixels_from_vehicle(face)
        lo, hi = px.min(axis=0), px.max(axis=0)
        p = back.tracks[:, tau]
        inside = np.all((p > lo + 2) & (p < hi - 2), axis=1)
        outside = np.any((p < lo - 3) | (p > hi + 3), axis=1)
        assert not back.visibles[inside, tau].any(), tau
        assert back.visibles[outside, tau].all(), tau
        n_inside += inside.sum()
        n_outside += outside.sum()
    assert n_inside > 1000 and n_outside > 1000


def test_objects_of_types_not_annotated_still_hide_annotated_ones():
    """A pedestrian steps in front of a parked car at frame 15, 0.45 m before its rear face: too
    close in depth for the depth map's 5% rule (12.05 m against 12.5 m), so only the z-buffer
    can hide the car's points behind it. Vehicles alone are annotated (the default); the
    pedestrian occludes through ``occluder_types`` (default every labelled type), and with
    ``occluder_types=("VEHICLE",)`` (the behaviour before it) those points stay visible."""
    b = SceneBuilder()
    b.add_object("car", world_center(b, 16.0))                      # rear face at x = 14 m
    b.add_object("walker", world_center(b, 13.75, z=0.9), size=(0.4, 0.6, 1.8), type_=2, frames=range(15, b.t),
                 spacing=0.05)
    scene = b.build()
    base = dict(rolling_shutter=False, depth_completer_options={"max_reach_px": 3.0})
    plan = plan_segment(scene, TrackConfig(**base))
    walker_rows = np.flatnonzero(scene.boxes.object_id == "walker")
    assert plan.box_points(walker_rows)[0].size > 100                  # its returns are selected ...
    assert {job.object_id for job in plan.jobs} == {"car"}           # ... but it is not annotated
    # seen from the camera (x = 1.5 m), a car point at |y| < 0.31 m lies behind the walker
    _, default = annotate(scene, TrackConfig(**base))
    _, vehicles = annotate(scene, TrackConfig(**base, occluder_types=("VEHICLE",)))
    for result in (default, vehicles):
        car = result["car"]
        y = car.points_box[:, 1]
        behind, clear = np.abs(y) < 0.25, np.abs(y) > 0.4
        assert behind.sum() > 100 and clear.sum() > 100
        assert car.visibles[:, :15].all()                              # no walker yet: all seen
        assert car.visibles[clear, 15:].all()
    assert not default["car"].visibles[np.abs(default["car"].points_box[:, 1]) < 0.25, 15:].any()
    assert vehicles["car"].visibles[np.abs(vehicles["car"].points_box[:, 1]) < 0.25, 15:].all()


def test_object_seen_by_lidar_but_hidden_from_camera_is_rejected():
    b = SceneBuilder()
    b.lidar_origin = np.array([0.0, 0.0, 3.0])          # roof LiDAR sees over the wall
    b.add_object("hidden", world_center(b, 14.0), size=(2.0, 1.0, 1.0))
    b.add_object("wall", world_center(b, 5.0), size=(0.2, 4.0, 2.0), spacing=0.03, type_=3)  # a sign
    scene = b.build()
    ctx, results = annotate(scene)
    assert ctx.plan.jobs[[j.object_id for j in ctx.plan.jobs].index("hidden")].num_points > 100
    hidden = results["hidden"]
    assert hidden.rejection == "no_visible_points" and hidden.num_tracks == 0
    seg = segment_stats(scene.split, scene.segment, ctx.plan, list(results.values()))
    assert seg.iloc[0].rejected_no_visible_points == 1
    with pytest.raises(ValueError, match="rejected"):
        write_object_outputs("/nonexistent", "validation", hidden)


def test_rolling_shutter_path_matches_global_for_a_global_shutter_camera():
    b = SceneBuilder(ego_speed=3.0)
    b.add_object("car", world_center(b, 10.0), spacing=0.3)
    scene = b.build()
    _, gs = annotate(scene)
    _, rs = annotate(scene, TrackConfig(rolling_shutter=True, depth_completer_options={"max_reach_px": 3.0}))
    assert rs["car"].projection == "rolling_shutter"
    np.testing.assert_allclose(rs["car"].tracks, gs["car"].tracks, atol=1e-6)
    np.testing.assert_array_equal(rs["car"].visibles, gs["car"].visibles)


def test_depth_jobs_cover_only_needed_frames():
    b = SceneBuilder(cameras=(FRONT, SIDE_LEFT))
    b.add_object("car", world_center(b, 10.0))
    jobs = depth_jobs(b.build(), TrackConfig(depth_batch=8, rolling_shutter=False))
    assert {j.camera for j in jobs} == {FRONT}
    np.testing.assert_array_equal(np.concatenate([j.frames for j in jobs]), np.arange(b.t))
    assert max(j.frames.size for j in jobs) == 8


def test_max_tracks_subsample_is_seeded():
    b = SceneBuilder()
    b.add_object("car", world_center(b, 10.0))
    cfg = TrackConfig(rolling_shutter=False, max_tracks_per_object=100, depth_completer_options={"max_reach_px": 3.0})
    scene = b.build()
    _, r1 = annotate(scene, cfg)
    _, r2 = annotate(scene, cfg)
    assert r1["car"].num_tracks <= 100
    np.testing.assert_array_equal(r1["car"].lidar_sources, r2["car"].lidar_sources)


# ---------------------------------------------------------------- outputs

def test_outputs_load_without_pickle_with_documented_layout(tmp_path):
    b = SceneBuilder()
    b.add_object("car-1", world_center(b, 10.0), extra_local=[[-2.0, 0.0, 0.0]], spacing=0.25)
    scene = b.build()
    ctx, results = annotate(scene)
    r = results["car-1"]
    urls = write_object_outputs(str(tmp_path), "validation", r)
    assert urls[0].endswith("tracks/validation/waymo_seg_test-1_FRONT_car-1.npz")
    assert urls[1].endswith("tapvid3d/validation/waymo_seg_test-1_FRONT_car-1.npz")
    n, t = r.num_tracks, b.t
    with np.load(urls[0], allow_pickle=False) as d:
        expect = {"video": (np.uint8, (t, H, W, 3)), "tracks": (np.float32, (n, t, 2)),
                  "visibles": (np.bool_, (n, t)), "timestamps_micros": (np.int64, (t,)),
                  "query_frames": (np.int32, (n,)), "lidar_sources": (np.int32, (n, 4)),
                  "points3d": (np.float32, (n, t, 3))}
        assert set(d.files) == set(expect)
        for key, (dtype, shape) in expect.items():
            assert d[key].dtype == dtype and d[key].shape == shape, key
        assert abs(int(d["video"][0, 5, 5, 0]) - 90) <= 2
        np.testing.assert_array_equal(d["timestamps_micros"], scene.timestamps_micros)
    with np.load(urls[1], allow_pickle=False) as d:
        assert d["tracks_XYZ"].shape == (t, n, 3) and d["visibility"].shape == (t, n)
        assert d["images_jpeg_bytes"].shape == (t,) and d["images_jpeg_bytes"].dtype.kind == "S"
        assert d["images_jpeg_bytes"][3] == _JPEG
        assert d["queries_xyt"].shape == (n, 3) and d["extrinsics_w2c"].shape == (t, 4, 4)
        np.testing.assert_allclose(d["fx_fy_cx_cy"], [F, F, CX, CY])
        hit = np.flatnonzero(np.all(np.abs(r.points3d[:, 0] - [8.0, 0.0, 1.0]) < 1e-5, axis=1))[0]
        # OpenCV camera frame: X = -y, Y = -z, Z = x of the Waymo camera point (6.5, 0, -0.5)
        np.testing.assert_allclose(d["tracks_XYZ"][:, hit], np.tile([0.0, 0.5, 6.5], (t, 1)), atol=1e-4)
        # pinhole projection of tracks_XYZ with fx_fy_cx_cy gives the pixel (no distortion here)
        xyz = d["tracks_XYZ"][0]
        proj = np.stack([F * xyz[:, 0] / xyz[:, 2] + CX, F * xyz[:, 1] / xyz[:, 2] + CY], -1)
        np.testing.assert_allclose(proj, r.tracks[:, 0], atol=1e-3)
        # world -> camera extrinsics agree with tracks_XYZ
        world = transform_points(scene.world_from_vehicle[0], r.points3d[:, 0].astype(float))
        np.testing.assert_allclose(transform_points(d["extrinsics_w2c"][0].astype(float), world), xyz, atol=2e-2)
        q = d["queries_xyt"]
        assert np.all(r.visibles[np.arange(n), q[:, 2].astype(int)])


def test_stats_tables_have_the_documented_columns(tmp_path):
    b = SceneBuilder()
    b.add_object("car", world_center(b, 10.0), spacing=0.25)
    scene = b.build()
    ctx, results = annotate(scene)
    objects = object_stats(list(results.values()), {(FRONT, "car"): "validation/x.npz"})
    required = ["split", "segment", "camera", "object_id", "object_type", "file", "num_tracks", "num_frames",
                "visible_fraction", "min_camera_distance_m", "box_speed_mean_mps", "speed_err_p25",
                "speed_err_p50", "speed_err_p75", "speed_err_p95", "speed_err_p99", "num_nonfinite_visible",
                "num_visible_outside_image"]
    assert set(required) <= set(objects.columns) and list(objects.columns) == list(OBJECT_COLUMNS)
    row = objects.iloc[0]
    assert row.camera == "FRONT" and row.object_type == "VEHICLE" and row.num_frames == b.t
    assert row.num_nonfinite_visible == 0 and row.num_visible_outside_image == 0
    assert 0 < row.visible_fraction <= 1
    url = write_table(str(tmp_path / "stats" / "objects.parquet"), objects)
    back = pd.read_parquet(url)
    assert list(back.columns) == list(OBJECT_COLUMNS) and len(back) == 1
    failed = segment_stats("validation", "seg_x", None, status="failed", error="boom")
    assert failed.iloc[0].status == "failed" and failed.iloc[0].rejected_camera == 0


def test_unsafe_object_id_is_refused_by_the_writer(tmp_path):
    b = SceneBuilder()
    b.add_object("a/b", world_center(b, 10.0), spacing=0.3)
    _, results = annotate(b.build())
    with pytest.raises(ValueError, match="object_id name 'a/b'"):
        write_object_outputs(str(tmp_path), "validation", results["a/b"])


def test_staged_depth_gives_the_same_tracks_and_missing_maps_are_named():
    from drivetrack.depth.stage import complete_depth, sparse_depth

    b = SceneBuilder()
    b.add_object("car", world_center(b, 10.0), spacing=0.25)
    scene = b.build()
    plan = plan_segment(scene, CONFIG)
    staged = {}
    for job in depth_jobs(scene, CONFIG, plan):          # what an orchestrator would fan out
        maps = complete_depth(sparse_depth(scene, CONFIG, job), CONFIG)
        frames, stack = staged.get(job.camera, (np.zeros(0, np.int64), np.zeros((0, H, W), np.float32)))
        staged[job.camera] = (np.concatenate([frames, job.frames]), np.concatenate([stack, maps]))
    ctx = prepare_segment(scene, CONFIG, depth=staged, plan=plan)
    _, direct = annotate(scene)
    staged_result = run_object_job(ctx, object_jobs(ctx)[0])
    np.testing.assert_array_equal(staged_result.visibles, direct["car"].visibles)
    frames, maps = staged[FRONT]
    with pytest.raises(ValueError, match=r"seg_test-1.*FRONT.*missing for frames \[0\]"):
        prepare_segment(scene, CONFIG, depth={FRONT: (frames[1:], maps[1:])}, plan=plan)


def test_speed_filter_drops_points_far_from_the_box_centre_of_a_spinning_box():
    b = SceneBuilder()
    t = np.arange(b.t) * DT
    b.add_object("spinner", world_center(b, 10.0), headings=1.0 * t, spacing=0.25)
    scene = b.build()
    _, plain = annotate(scene)
    errors = plain["spinner"].speed_error_mps
    # the box centre does not move: a point's speed is its lever arm times 1 rad/s
    np.testing.assert_allclose(plain["spinner"].box_speed_mps, 0.0, atol=1e-9)
    radius = np.linalg.norm((plain["spinner"].points3d[:, 0] - scene.boxes.center[0])[:, :2], axis=1)
    np.testing.assert_allclose(errors, radius, rtol=0.02)
    cfg = TrackConfig(rolling_shutter=False, max_speed_deviation_mps=1.5,
                      depth_completer_options={"max_reach_px": 3.0})
    _, filtered = annotate(scene, cfg)
    assert filtered["spinner"].num_dropped_speed == int((errors > 1.5).sum()) > 0
    assert np.all(filtered["spinner"].speed_error_mps <= 1.5)


def test_writers_go_through_fsspec_for_remote_urls():
    import fsspec

    from drivetrack.tracks.writers import write_npz

    url = write_npz("memory://tracks-test/validation/x.npz", {"a": np.arange(3, dtype=np.int32)})
    with fsspec.open(url, "rb") as handle, np.load(handle, allow_pickle=False) as d:
        np.testing.assert_array_equal(d["a"], [0, 1, 2])
    with pytest.raises(ValueError, match=r"memory://tracks-test/y.npz.*'b'.*dtype object"):
        write_npz("memory://tracks-test/y.npz", {"b": np.array([None])})
    table = pd.DataFrame({"x": [1]})
    url = write_table("memory://tracks-test/stats/t.parquet", table)
    with fsspec.open(url, "rb") as handle:
        assert pd.read_parquet(handle).x.tolist() == [1]


def test_fill_invalid_positions_holds_nearest_valid_frame():
    from drivetrack.tracks.core import fill_invalid_positions

    nan = np.nan
    tracks = np.array([[[nan, nan], [1, 1], [nan, nan], [nan, nan], [nan, nan], [5, 5]],
                       [[0, 0], [1, 1], [2, 2], [3, 3], [4, 4], [5, 5]],
                       [[nan, nan]] * 6], dtype=np.float32)
    out = fill_invalid_positions(tracks)
    # frame 0 takes frame 1; frame 2 the nearer frame 1; frame 3 ties -> earlier (1); frame 4 -> 5
    np.testing.assert_array_equal(out[0, :, 0], [1, 1, 1, 1, 5, 5])
    np.testing.assert_array_equal(out[1], tracks[1])                 # all finite: unchanged
    assert np.isnan(out[2]).all()                                      # no finite frame: left alone
    assert fill_invalid_positions(np.zeros((0, 4, 2), np.float32)).shape == (0, 4, 2)


@pytest.mark.parametrize("dtype", [np.int8, np.uint8, np.int64])
def test_return_mask_equals_isin_for_every_dtype(dtype):
    """The reader's int8 columns go through a 256-entry table; values a dtype cannot hold match nothing."""
    from drivetrack.boxes import return_mask

    rng = np.random.default_rng(1)
    laser, ret = rng.integers(0, 8, 1000).astype(dtype), rng.integers(1, 3, 1000).astype(dtype)
    for lasers, returns in ((None, None), ((1, 3), (1,)), ([2], None), ((-1, 200, 300, 5), (2,)), ((), None)):
        want = np.ones(1000, bool)
        if lasers is not None:
            want &= np.isin(laser, lasers)
        if returns is not None:
            want &= np.isin(ret, returns)
        np.testing.assert_array_equal(return_mask(laser, ret, lasers, returns), want)
