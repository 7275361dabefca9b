"""drivetrack.refine.static: objects the labels show standing still get one world pose."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from drivetrack.geometry import rotation_from_rpy
from drivetrack.refine.static import static_object_centres
from drivetrack.scene import Boxes

FRAMES = 20


def _scene(world_centre, world_heading, noise_m=0.0, noise_deg=0.0, speed=None, seed=0):
    """An ego driving at 8 m/s while pitching and rolling, and one object's labels: the world
    pose ``world_centre(t)`` [T, 3], ``world_heading(t)`` [T] seen from the ego, yaw-only, with
    Gaussian noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(FRAMES) * 0.1
    world_from_vehicle = np.tile(np.eye(4), (FRAMES, 1, 1))
    world_from_vehicle[:, :3, :3] = rotation_from_rpy(0.004 * np.sin(t * 2.7), 0.006 * np.sin(t * 2.0), 0.05 * t)
    world_from_vehicle[:, :3, 3] = np.stack([8.0 * t, 0.3 * t, np.full(FRAMES, 0.2)], -1)
    vehicle_from_world = np.linalg.inv(world_from_vehicle)
    centre = np.einsum("tij,tj->ti", vehicle_from_world[:, :3, :3], world_centre(t)) + vehicle_from_world[:, :3, 3]
    h = world_heading(t)
    forward = np.einsum("tij,tj->ti", vehicle_from_world[:, :3, :3], np.stack([np.cos(h), np.sin(h), 0 * h], -1))
    heading = np.arctan2(forward[:, 1], forward[:, 0])
    centre = centre + rng.normal(0.0, noise_m, centre.shape)
    heading = heading + rng.normal(0.0, np.deg2rad(noise_deg), heading.shape)
    boxes = Boxes(object_id=np.array(["car"] * FRAMES, dtype=object), frame=np.arange(FRAMES, dtype=np.int32),
                  center=centre, size=np.tile([4.5, 2.0, 1.6], (FRAMES, 1)), heading=heading,
                  type=np.ones(FRAMES, np.int8),
                  speed=np.full((FRAMES, 3), np.nan) if speed is None else
                  np.broadcast_to(np.asarray(speed, np.float64), (FRAMES, 3)).copy(),
                  num_lidar_points_in_box=np.full(FRAMES, -1))
    return SimpleNamespace(segment="unit", boxes=boxes, world_from_vehicle=world_from_vehicle,
                           timestamps_micros=(t * 1e6).astype(np.int64))


def _world(scene, centre_v, heading_v):
    w = scene.world_from_vehicle
    centre = np.einsum("tij,tj->ti", w[:, :3, :3], centre_v) + w[:, :3, 3]
    forward = np.einsum("tij,tj->ti", w[:, :3, :3], np.stack([np.cos(heading_v), np.sin(heading_v), 0 * heading_v], -1))
    return centre, np.arctan2(forward[:, 1], forward[:, 0])


def _parked(t):
    return np.tile([30.0, -4.0, 0.8], (t.size, 1))


@pytest.mark.parametrize("speed", [None, [0.0, 0.0, 0.0]])
def test_a_parked_car_with_noisy_labels_gets_one_world_pose(speed):
    scene = _scene(_parked, lambda t: np.full(t.size, 0.4), noise_m=0.05, noise_deg=1.0, speed=speed)
    rows = np.arange(FRAMES)
    pose = static_object_centres(scene, rows, 0.1, 0.25)
    assert pose is not None and pose[2]
    centre_w, yaw_w = _world(scene, pose[0], pose[1])
    # one pose in the world, whatever the ego did (the yaw of a yaw-only box in a tilted frame
    # moves at second order in the tilt: 3e-5 rad here)
    assert np.ptp(centre_w, axis=0).max() < 1e-9 and np.ptp(yaw_w) < 1e-4
    # closer to the truth than a label is, on average
    label_w, label_yaw = _world(scene, scene.boxes.center, scene.boxes.heading)
    assert np.linalg.norm(centre_w[0] - [30.0, -4.0, 0.8]) < np.linalg.norm(label_w - [30.0, -4.0, 0.8], axis=-1).mean()
    assert abs(yaw_w[0] - 0.4) < np.abs(label_yaw - 0.4).mean()


def test_exact_labels_of_a_parked_car_are_static_and_kept_bit_for_bit():
    scene = _scene(_parked, lambda t: np.full(t.size, 0.4))
    centre, heading, replaced = static_object_centres(scene, np.arange(FRAMES), 0.1, 0.25)
    assert not replaced
    assert np.array_equal(centre, scene.boxes.center) and np.array_equal(heading, scene.boxes.heading)


@pytest.mark.parametrize("case", ["creeping", "drifting", "labelled_moving", "starting_off", "tilted", "one_frame"])
def test_objects_that_move_or_cannot_be_judged_keep_their_labels(case):
    if case == "creeping":        # 0.5 m/s: 1 m over the segment, ten times the label noise
        scene = _scene(lambda t: _parked(t) + np.outer(t, [0.5, 0.0, 0.0]), lambda t: np.zeros(t.size), noise_m=0.05)
    elif case == "drifting":      # 0.15 m/s, labelled 0: under the speed bounds, but 0.29 m over the segment
        scene = _scene(lambda t: _parked(t) + np.outer(t, [0.15, 0.0, 0.0]), lambda t: np.zeros(t.size),
                       noise_m=0.005, speed=[0.0, 0.0, 0.0])
    elif case == "starting_off":  # labelled 0 m/s but for its last two frames: 6 cm over the segment
        speed = np.zeros((FRAMES, 3))
        speed[-2:, 0] = 0.3
        scene = _scene(lambda t: _parked(t) + np.outer(np.clip(t - 1.7, 0, None), [0.3, 0.0, 0.0]),
                       lambda t: np.zeros(t.size), noise_m=0.005, speed=speed)
    else:
        scene = _scene(_parked, lambda t: np.zeros(t.size), noise_m=0.05,
                       speed=[1.5, 0.0, 0.0] if case == "labelled_moving" else [0.0, 0.0, 0.0])
    rows = np.arange(1 if case == "one_frame" else FRAMES)
    if case == "tilted":
        scene.boxes.pitch = np.full(FRAMES, 0.01)
    assert static_object_centres(scene, rows, 0.1, 0.25) is None


def test_refinement_of_a_noisy_synthetic_segment_holds_static_objects_still(tmp_path):
    """Hard world, 5 cm / 1 deg labels: every static object (parked cars, poles, signs) gets one
    world pose, is not registered frame by frame (reason ``static``) and its box is grown to hold
    its returns; moving objects are not touched by it."""
    from drivetrack.annotate import AnnotateConfig, load_scene_for, refine_scene
    from drivetrack.synth import SynthConfig, generate_segment, load_ground_truth
    from drivetrack.tracks import TrackConfig

    src = str(tmp_path / "src")
    seg = generate_segment(src, SynthConfig(seed=7, frames=10, preset="small", cameras=("FRONT",), world="hard",
                                            box_noise_m=0.05), 0)["segment"]
    truth = load_ground_truth(src, "training", seg).objects
    role = dict(zip(truth["object_id"].astype(str), truth["role"].astype(str)))
    config = AnnotateConfig(track=TrackConfig(cameras=("FRONT",), object_types=("VEHICLE", "PEDESTRIAN", "CYCLIST", "SIGN"),
                                              min_frames=4, max_camera_distance_m=75.0))
    scene = load_scene_for(src, "training", seg, config, refine=False)
    refined = refine_scene(scene, config)
    summary = refined.box_refinement
    static = {o for o, s in summary.items() if s["refine_reason"] == "static"}
    assert static and all(role[o] in ("parked", "pole", "sign", "occluder", "oblique", "pedestrian_near_car",
                                      "low_sign") for o in static)
    assert any(role[o] == "parked" for o in static)
    moving = {o for o in summary if role[o] in ("lead", "oncoming", "crossing", "close_pass", "turning")}
    assert moving and not (moving & static)
    for o in static:
        rows = np.flatnonzero(refined.boxes.object_id.astype(str) == o)
        assert not summary[o]["refine_fallback"] and summary[o]["refine_num_points"] >= 0
        centre_w, yaw_w = _world(refined, refined.boxes.center[rows], refined.boxes.heading[rows])
        # (a box grown by centimetres in the tilted vehicle frames moves by a fraction of a mm)
        assert np.ptp(centre_w, axis=0).max() < 1e-3 and np.ptp(np.unwrap(yaw_w)) < 1e-4, o
