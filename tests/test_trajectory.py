"""drivetrack.tracks.trajectory: continuous-time box trajectories and the label-time decision."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from drivetrack.scene import Boxes, LidarReturns
from drivetrack.tracks import TrackConfig
from drivetrack.tracks.trajectory import (build_trajectory, points_box_at, points_box_at_numpy, segment_trajectory,
                                          sweep_label_offsets)
from drivetrack.waymo.schema import LaserName

SWEEP_S = 0.1
SIZE = np.array([4.5, 2.0, 1.5])


def _sweep_offset(xy: np.ndarray) -> np.ndarray:
    """The synthetic TOP law: azimuth +pi at -50 ms, -pi at +50 ms (drivetrack.synth.config)."""
    return -np.arctan2(xy[..., 1], xy[..., 0]) / (2 * np.pi) * SWEEP_S


def _circle(t, radius=12.0, speed=9.0, accel=2.5):
    """Centre [.., 3] and heading of a car on a circle (left turn) while accelerating."""
    s = speed * t + 0.5 * accel * t * t
    angle = s / radius
    centre = np.stack([radius * np.sin(angle), 4.0 + radius * (1 - np.cos(angle)), np.full_like(t, 0.75)], -1)
    return centre, angle


def _straight(t, x0=-6.0, speed=12.0, accel=-4.0):
    """A car braking beside the ego (y = 4 m), heading 0."""
    centre = np.stack([x0 + speed * t + 0.5 * accel * t * t, np.full_like(t, 4.0), np.full_like(t, 0.75)], -1)
    return centre, np.zeros_like(t)


def _scene(motion, label_time: str, frames: int = 12, with_returns: bool = True):
    """A static ego at the world origin and one object following ``motion``, labelled per
    ``label_time``; TOP returns on its ego-facing side at their true capture times."""
    times = np.arange(frames) * 0.1
    label_times = times.copy()
    if label_time == "sweep":
        for _ in range(8):      # fixed point: when the sweep passes the centre
            label_times = times + _sweep_offset(motion(label_times)[0])
    centre, heading = motion(label_times)
    boxes = Boxes(object_id=np.array(["car"] * frames, dtype=object), frame=np.arange(frames, dtype=np.int32),
                  center=centre, size=np.tile(SIZE, (frames, 1)), heading=heading,
                  type=np.ones(frames, np.int8), speed=np.full((frames, 3), np.nan),
                  num_lidar_points_in_box=np.full(frames, -1))
    gx, gz = np.meshgrid(np.linspace(-2.1, 2.1, 30), np.linspace(-0.5, 0.6, 6))
    body = np.stack([gx.ravel(), np.full(gx.size, -1.0), gz.ravel()], -1)              # right side face
    points, frame, offsets = [], [], []
    for t in range(frames if with_returns else 0):
        dt = np.zeros(body.shape[0])
        for _ in range(8):
            c, h = motion(times[t] + dt)
            rot = np.stack([np.cos(h), -np.sin(h), np.sin(h), np.cos(h)], -1).reshape(-1, 2, 2)
            world = np.concatenate([c[:, :2] + np.einsum("nij,nj->ni", rot, body[:, :2]), c[:, 2:] + body[:, 2:]], -1)
            dt = _sweep_offset(world)
        points.append(world)
        frame.append(np.full(world.shape[0], t, np.int32))
        offsets.append(dt)
    m = sum(p.shape[0] for p in points)
    counts = np.bincount(np.concatenate(frame), minlength=frames) if m else np.zeros(frames, np.int64)
    lidar = LidarReturns(
        points_vehicle=np.concatenate(points) if m else np.zeros((0, 3)),
        frame=np.concatenate(frame) if m else np.zeros(0, np.int32),
        laser=np.full(m, int(LaserName.TOP), np.int8), return_index=np.ones(m, np.int8),
        row=np.zeros(m, np.int32), col=np.zeros(m, np.int32), intensity=np.zeros(m, np.float32),
        frame_offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        capture_offset_s=np.concatenate(offsets).astype(np.float32) if m else None)
    scene = SimpleNamespace(segment="unit", boxes=boxes, lidar=lidar, timestamps_micros=(times * 1e6).astype(np.int64),
                            world_from_vehicle=np.tile(np.eye(4), (frames, 1, 1)))
    return scene, times, label_times


def _plan(scene, label_time="auto"):
    from drivetrack.boxes import returns_in_boxes

    config = TrackConfig(label_time=label_time)
    offsets, index = returns_in_boxes(scene, np.arange(len(scene.boxes)), config.laser_values, config.returns,
                                      0.0, 0.0, False)
    return SimpleNamespace(scene=scene, config=config, box_point_offsets=offsets, box_point_index=index)


@pytest.mark.parametrize("motion", [_circle, _straight])
def test_trajectory_follows_accelerating_and_turning_objects_between_frames(motion):
    scene, times, _ = _scene(motion, "frame", with_returns=False)
    trajectory = build_trajectory(scene, np.zeros(len(scene.boxes)), "frame")
    rows = np.repeat(np.arange(len(times)), 5)
    query = times[rows] + np.tile([-0.045, -0.02, 0.0, 0.015, 0.045], len(times))
    centre, yaw, _, _, velocity, _ = trajectory.motion(rows, query)
    true_centre, true_yaw = motion(query)
    # local quadratic through the labels: exact for constant acceleration, a few millimetres on a
    # 12 m circle at 9-12 m/s
    error = np.linalg.norm(centre - true_centre, axis=-1)
    assert error.max() < (1e-9 if motion is _straight else 4e-3)
    # the old model: constant finite-difference velocity from the label (7-38 mm here)
    from drivetrack.tracks.sweep_motion import box_motion_world

    world_from_box = np.tile(np.eye(4), (len(times), 1, 1))
    world_from_box[:, :3, 3] = scene.boxes.center
    old = scene.boxes.center[rows] + (query - times[rows])[:, None] * box_motion_world(world_from_box, times)[0][rows]
    assert error.max() < np.linalg.norm(old - true_centre, axis=-1).max() / 5
    assert np.abs(np.angle(np.exp(1j * (yaw - true_yaw)))).max() < 5e-4
    eps = 1e-6
    true_velocity = (motion(query + eps)[0] - motion(query - eps)[0]) / (2 * eps)
    assert np.abs(velocity - true_velocity).max() < (1e-6 if motion is _straight else 0.15)
    # the labels themselves are reproduced exactly
    at_labels = trajectory.world_from_box(np.arange(len(times)), times)
    np.testing.assert_allclose(at_labels[:, :3, 3], scene.boxes.center, atol=1e-12)


def test_trajectory_handles_single_and_empty_objects():
    scene, times, _ = _scene(_straight, "frame", frames=1, with_returns=False)
    scene.boxes.speed[:] = [3.0, 0.0, 0.0]
    trajectory = build_trajectory(scene, np.zeros(1))
    centre = trajectory.motion(np.array([0]), np.array([0.02]))[0]
    np.testing.assert_allclose(centre[0], scene.boxes.center[0] + [0.06, 0, 0], atol=1e-12)
    empty = trajectory.world_from_box(np.zeros(0, np.int64), np.zeros(0))
    assert empty.shape == (0, 4, 4)


def test_points_box_at_kernel_is_bit_identical_to_numpy():
    """``points_box_at`` (numba, one pass) equals its numpy form bit for bit: a turning,
    accelerating object with pitch and roll, points scattered round it, times before, at and
    after the samples; and no points at all."""
    from drivetrack.numba_compat import NUMBA_AVAILABLE

    scene, times, _ = _scene(_circle, "sweep")
    trajectory = build_trajectory(scene, np.zeros(len(scene.boxes)))
    rng = np.random.default_rng(4)
    trajectory.pitch[:] = rng.uniform(-0.05, 0.05, trajectory.pitch.shape)
    trajectory.roll[:] = rng.uniform(-0.05, 0.05, trajectory.roll.shape)
    rows = rng.integers(0, len(scene.boxes), 5000)
    time_s = trajectory.time_s[rows] + rng.uniform(-0.06, 0.06, rows.size)
    time_s[:50] = trajectory.time_s[rows[:50]]
    world = trajectory.centre[rows] + rng.normal(0.0, 3.0, (rows.size, 3))
    want = points_box_at_numpy(trajectory, rows, time_s, world)
    got = points_box_at(trajectory, rows, time_s, world)
    assert NUMBA_AVAILABLE and got.shape == (rows.size, 3)
    np.testing.assert_array_equal(got, want)
    assert points_box_at(trajectory, np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3))).shape == (0, 3)


@pytest.mark.parametrize("label_time", ["frame", "sweep"])
def test_sweep_label_offsets_and_both_conventions(label_time):
    scene, times, label_times = _scene(_straight, label_time)
    plan = _plan(scene, label_time)
    offsets = sweep_label_offsets(scene, plan.box_point_offsets, plan.box_point_index)
    # the object sits 4 m to the left: the sweep passes it ~25 ms before the frame time
    truth = _sweep_offset(_straight(times)[0])
    assert np.abs(offsets - truth).max() < 2e-3
    trajectory, decision = segment_trajectory(plan, label_time)
    assert decision["label_time"] == label_time
    np.testing.assert_allclose(trajectory.time_s, label_times, atol=2e-3 if label_time == "sweep" else 0)
    # under the right convention every return lies on the box surface at its capture time
    lidar = scene.lidar
    rows = lidar.frame.astype(np.int64)
    local = points_box_at(trajectory, rows, times[rows] + lidar.capture_offset_s, lidar.points_vehicle)
    assert np.abs(local[:, 1] + 1.0).max() < 0.01


@pytest.mark.parametrize("label_time", ["frame", "sweep"])
@pytest.mark.parametrize("motion", [_circle, _straight])
def test_auto_picks_the_convention_of_the_labels(label_time, motion):
    scene, _, _ = _scene(motion, label_time)
    trajectory, decision = segment_trajectory(_plan(scene), "auto")
    assert decision["requested"] == "auto" and decision["votes"] > 0
    assert decision["label_time"] == label_time == trajectory.label_time
    wrong = "residual_sweep_m" if label_time == "frame" else "residual_frame_m"
    right = "residual_frame_m" if label_time == "frame" else "residual_sweep_m"
    assert decision[right] < 0.5 * decision[wrong]


def test_refined_boxes_keep_the_label_times_they_were_registered_at():
    """``carry_label_times`` hands the labels' sweep times to the refined boxes row for row: the
    refinement registered each box's returns at its label's time, and times recomputed from the
    refined centres (moved by the label error) would differ by the error's azimuth."""
    from drivetrack.tracks.trajectory import carry_label_times, scene_label_times

    scene, _, _ = _scene(_straight, "sweep")
    config = TrackConfig(label_time="auto")
    offsets, decision = scene_label_times(scene, config)
    assert decision["label_time"] == "sweep"

    def refined():              # the same rows, centres 30 cm further out (another azimuth)
        boxes = Boxes(**{k: v for k, v in scene.boxes.__dict__.items()})
        boxes.center = scene.boxes.center + [0.0, 0.3, 0.0]
        return SimpleNamespace(segment="unit", boxes=boxes, lidar=scene.lidar, timestamps_micros=scene.timestamps_micros,
                               world_from_vehicle=scene.world_from_vehicle)

    recomputed = scene_label_times(refined(), TrackConfig(label_time="sweep"))[0]
    assert np.abs(recomputed - offsets).max() > 2e-4          # what the refined boxes would get alone
    carried = refined()
    carry_label_times(scene, carried, config)
    for label_time in ("auto", "sweep"):
        got, got_decision = scene_label_times(carried, TrackConfig(label_time=label_time))
        np.testing.assert_array_equal(got, offsets)
        assert got_decision["label_time"] == "sweep"
    assert not scene_label_times(carried, TrackConfig(label_time="frame"))[0].any()


def test_labels_motion_is_timed_at_their_label_times():
    """``scene_box_motion(..., label_offset_s=)``: a car keeping its speed beside the ego, each box
    labelled when the sweep passed it (up to ~4 ms later each frame as it comes alongside),
    moves at its speed; its finite differences over the frame times are off by that change."""
    from drivetrack.tracks.sweep_motion import scene_box_motion

    scene, times, label_times = _scene(lambda t: _straight(t, accel=0.0), "sweep")
    velocity, yaw_rate = scene_box_motion(scene, label_offset_s=label_times - times)
    np.testing.assert_allclose(velocity, np.tile([12.0, 0.0, 0.0], (times.size, 1)), atol=1e-9)
    np.testing.assert_allclose(yaw_rate, 0.0, atol=1e-12)
    at_frame_times = scene_box_motion(scene)[0]
    assert np.abs(at_frame_times[:, 0] - 12.0).max() > 0.2


def test_track_config_checks_time_settings():
    with pytest.raises(ValueError, match="time_model"):
        TrackConfig(time_model="spline")
    with pytest.raises(ValueError, match="label_time"):
        TrackConfig(label_time="capture")
    with pytest.raises(ValueError, match="label_tilt"):
        TrackConfig(label_tilt="ground")


@pytest.mark.parametrize("motion", [_straight, None])
def test_yaw_only_labels_of_a_pitching_ego_carry_level_objects_exactly(motion):
    """The ego pitches and rolls on its suspension (about a second's period) on a flat road; the
    labels are yaw-only in its frame, so their world tilt is the ego's. A level object's body
    points, carried from one time to another by the trajectory, must land where the truth puts
    them: to 0.1 mm under ``label_tilt="constant"`` (a constant tilt cancels), off by millimetres
    under ``"linear"`` (the line follows the ego's tilt changes)."""
    from drivetrack.geometry import rotation_from_rpy

    motion = motion or (lambda t: (np.stack([np.full_like(t, 15.0), np.full_like(t, -3.0), np.full_like(t, 0.75)], -1),
                                   np.full_like(t, 0.3)))
    frames = 20
    scene, times, _ = _scene(motion, "frame", frames=frames, with_returns=False)
    pitch = 0.006 * np.sin(2 * np.pi * times / 1.3)
    roll = 0.004 * np.sin(2 * np.pi * times / 0.9 + 1.0)
    world_from_vehicle = np.tile(np.eye(4), (frames, 1, 1))
    world_from_vehicle[:, :3, :3] = rotation_from_rpy(roll, pitch, np.zeros(frames))
    world_from_vehicle[:, 2, 3] = 0.3
    centre_world, heading_world = motion(times)
    # the labels: the level world box seen from the tilted ego, heading only (tilt dropped)
    vehicle_from_world = np.linalg.inv(world_from_vehicle)
    scene.boxes.center[:] = np.einsum("nij,nj->ni", vehicle_from_world[:, :3, :3], centre_world) + vehicle_from_world[:, :3, 3]
    forward = np.stack([np.cos(heading_world), np.sin(heading_world), np.zeros(frames)], -1)
    forward_vehicle = np.einsum("nij,nj->ni", vehicle_from_world[:, :3, :3], forward)
    scene.boxes.heading[:] = np.arctan2(forward_vehicle[:, 1], forward_vehicle[:, 0])
    scene.world_from_vehicle = world_from_vehicle
    body = np.array([[2.2, 0.9, 0.7], [-2.2, -0.9, -0.7], [2.2, -0.9, 0.7], [0.0, 0.0, 0.7]])

    def world_at(trajectory, row, points_body):
        w = trajectory.world_from_box(np.full(len(points_body), row), np.full(len(points_body), times[row]))
        return np.einsum("nij,nj->ni", w[:, :3, :3], points_body) + w[:, :3, 3]

    errors = {}
    for tilt in ("constant", "linear"):
        trajectory = build_trajectory(scene, np.zeros(frames), "frame", tilt)
        worst = 0.0
        for a, b in [(0, 7), (3, 19), (12, 5)]:
            # truth: a level body, heading_world, centre_world at both times
            def truth(row, points):
                c, s = np.cos(heading_world[row]), np.sin(heading_world[row])
                return points @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + centre_world[row]
            seen = truth(a, body)                                         # where the return was at a
            carried = world_at(trajectory, b, points_box_at(trajectory, np.full(len(body), a),
                                                             np.full(len(body), times[a]), seen))
            worst = max(worst, float(np.abs(carried - truth(b, body)).max()))
        errors[tilt] = worst
    # (second order: the world yaw of a yaw-only label in a tilted frame, ~1e-5 rad)
    assert errors["constant"] < 1e-4, errors
    assert errors["linear"] > 10 * errors["constant"] and errors["linear"] > 5e-4, errors
    with pytest.raises(ValueError, match="label_tilt"):
        build_trajectory(scene, np.zeros(frames), "frame", "ground")


def _side_left(frames: int, times: np.ndarray, offset_s: float, direction: int = 5):
    """A SIDE_LEFT camera (looking along +y) of the static ego, triggered ``offset_s`` after each
    frame time; global shutter (5) or a 20 ms left-to-right readout (2)."""
    from drivetrack.camera.model import CameraModel
    from drivetrack.scene import CameraFrames

    vehicle_from_camera = np.eye(4)
    vehicle_from_camera[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]   # x_cam -> +y
    vehicle_from_camera[:3, 3] = [1.5, 0.0, 2.0]
    model = CameraModel(f_u=1000.0, f_v=1000.0, c_u=960.0, c_v=443.0, k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0,
                        width=1920, height=886, vehicle_from_camera=vehicle_from_camera,
                        rolling_shutter_direction=direction)
    pose = times + offset_s
    return CameraFrames(model=model, jpeg=[None] * frames, world_from_vehicle=np.tile(np.eye(4), (frames, 1, 1)),
                        pose_timestamp=pose, velocity=np.zeros((frames, 6)), shutter=np.full(frames, 0.002),
                        trigger_time=pose - 0.011, readout_done_time=pose + 0.011)


def _with_synced(scene, times, offset_s, camera=4, direction=5):
    """Waymo's synced boxes for ``scene``: the label moved by its (exact) speed x offset_s."""
    from drivetrack.waymo.schema import CameraName

    eps = 1e-6
    label_times = times
    scene.boxes.speed = (_straight(label_times + eps)[0] - _straight(label_times - eps)[0]) / (2 * eps)
    scene.boxes.synced_shift = scene.boxes.speed * offset_s
    scene.boxes.synced_camera = np.full(len(scene.boxes), camera, np.int8)
    scene.cameras = {int(CameraName.SIDE_LEFT): _side_left(len(times), times, offset_s, direction)}
    return scene


def test_synced_boxes_are_samples_at_their_capture_time():
    """An object labelled in two frames only: through the labels alone its trajectory is a
    straight line (the braking car's position off by up to 13 mm between and around them);
    Waymo's synced boxes (label + speed x (t_capture - t_frame), seen by a side camera fired 25 ms
    before the frame) add the labelled speed at a known time, and the fit follows the braking."""
    from drivetrack.tracks.trajectory import synced_samples

    scene, times, _ = _scene(_straight, "frame", frames=2, with_returns=False)
    scene = _with_synced(scene, times, -0.025)
    offset, shift = synced_samples(scene)
    np.testing.assert_allclose(offset, [-0.025, -0.025], atol=1e-6)
    np.testing.assert_allclose(shift, scene.boxes.synced_shift, atol=1e-12)
    rows = np.repeat([0, 1], 5)
    query = times[rows] + np.tile([-0.045, -0.02, 0.0, 0.03, 0.05], 2)
    truth = _straight(query)[0]
    errors = {}
    for synced in (False, True):
        trajectory = build_trajectory(scene, np.zeros(2), "frame", synced=synced)
        errors[synced] = np.linalg.norm(trajectory.motion(rows, query)[0] - truth, axis=-1).max()
        np.testing.assert_allclose(trajectory.centre, scene.boxes.center, atol=1e-12)   # labels kept
    assert errors[False] > 5e-3 and errors[True] < errors[False] / 4


def test_synced_samples_solve_the_rolling_shutter_and_skip_what_they_cannot_place():
    """With a left-to-right readout the box centre's column decides its capture time; rows whose
    camera is not loaded, whose centre is behind the camera, or which were captured at their
    frame time give no sample."""
    from drivetrack.tracks.trajectory import synced_samples
    from drivetrack.camera.rolling_shutter import project_world

    scene, times, _ = _scene(_straight, "frame", frames=4, with_returns=False)
    scene = _with_synced(scene, times, -0.025, direction=2)
    offset, _ = synced_samples(scene)
    frames = scene.cameras[4]
    for t in range(4):   # the capture time of the moving centre, solved by the camera model
        velocity = scene.boxes.speed[t:t + 1]
        at_pose = scene.boxes.center[t:t + 1] + velocity * (frames.pose_timestamp[t] - times[t])
        want = project_world(frames, t, at_pose, velocity).capture_time[0] - times[t]
        assert offset[t] == pytest.approx(want, abs=1e-9)
    # the car drives from x = -6 m to -4.8 m, left of the camera's axis at x = 1.5 m (its centre
    # off the image's left edge: the readout law extended): read before the pose time, later
    # each frame as it moves right
    assert (offset < -0.03).all() and (np.diff(offset) > 0.002).all()

    scene, times, _ = _scene(_straight, "frame", frames=4, with_returns=False)
    scene = _with_synced(scene, times, -0.025)
    scene.boxes.synced_camera[0] = 2                          # FRONT_LEFT: not loaded
    scene.boxes.center[1, 1] = -4.0                           # right of the ego: behind SIDE_LEFT
    scene.boxes.synced_shift[2] = np.nan                      # no synced box for this row
    offset, shift = synced_samples(scene)
    assert np.isnan(offset[:3]).all() and np.isnan(shift[:3]).all() and np.isfinite(offset[3])
    scene, times, _ = _scene(_straight, "frame", frames=2, with_returns=False)
    assert np.isnan(synced_samples(_with_synced(scene, times, 0.0))[0]).all()   # at the frame time


def test_objects_standing_still_take_no_synced_samples():
    """All of an object's boxes at one world position (pose refinement's static objects): a
    labelled speed, however it came, does not move it."""
    from drivetrack.tracks.trajectory import synced_samples

    scene, times, _ = _scene(_straight, "frame", frames=3, with_returns=False)
    scene = _with_synced(scene, times, -0.025)
    scene.boxes.center[:] = scene.boxes.center[0]
    assert np.isnan(synced_samples(scene)[0]).all()
    trajectory = build_trajectory(scene, np.zeros(3), "frame", synced=True)
    assert np.abs(trajectory.velocity).max() < 1e-12
