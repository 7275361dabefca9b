"""Depth maps place labelled objects' returns where the objects are at the image's time
(``depth_object_motion``), scored against the synthetic world's exact depth images."""
from __future__ import annotations

import numpy as np
import pytest

from drivetrack.annotate import AnnotateConfig, load_scene_for
from drivetrack.depth.stage import depth_jobs, points_at_image_time, sparse_depth
from drivetrack.synth import SynthConfig, generate_segment, load_ground_truth
from drivetrack.tracks import plan_segment
from drivetrack.waymo.schema import CameraName

CAMERAS = ("FRONT_LEFT", "SIDE_LEFT")
# the hard world: cameras fire when the TOP sweep crosses them; a car passes 1.5-1.8 m beside the ego
WORLD = SynthConfig(seed=7, frames=4, preset="small", cameras=CAMERAS, world="hard")


def _config(**track) -> AnnotateConfig:
    base = AnnotateConfig()
    return AnnotateConfig.from_dict({**base.to_dict(), "track": {**base.track.to_dict(), "cameras": list(CAMERAS),
                                                                  "min_frames": 2, **track}})


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = str(tmp_path_factory.mktemp("motion"))
    segment = generate_segment(root, WORLD, 0)["segment"]
    config = _config()
    scene = load_scene_for(root, "training", segment, config)
    return scene, plan_segment(scene, config.track), load_ground_truth(root, "training", segment)


def _maps(scene, plan, track, camera):
    job = next(j for j in depth_jobs(scene, track, plan) if j.camera == int(CameraName[camera]))
    return job.frames, sparse_depth(scene, track, job, plan)


def test_moved_returns_agree_with_the_exact_depth_of_the_image(world):
    """FRONT_LEFT fires ~12 ms before the sweep reaches the passing car's side: returns left at
    their capture time land a few millimetres per metre off the exact depth; moved on the
    object's trajectory to the image time, they agree to well under that."""
    scene, plan, truth = world
    frames, moved = _maps(scene, plan, _config().track, "FRONT_LEFT")
    _, still = _maps(scene, plan, _config(depth_object_motion=False).track, "FRONT_LEFT")
    exact = truth.depth("FRONT_LEFT")[frames]
    changed = moved != still
    assert changed.any()
    # the near returns that moved (within 10 m: the passing and turning cars; 864 pixels), each map
    # at its own pixels
    near_moved, near_still = changed & (moved > 0) & (moved < 10), changed & (still > 0) & (still < 10)
    assert near_moved.sum() > 500 and near_still.sum() > 500
    err_moved = np.abs(moved[near_moved] - exact[near_moved]) / exact[near_moved]
    err_still = np.abs(still[near_still] - exact[near_still]) / exact[near_still]
    assert np.median(err_moved) < 0.5 * np.median(err_still)
    assert np.percentile(err_moved, 90) < 0.5 * np.percentile(err_still, 90)
    # pixels no labelled return reaches are untouched
    assert np.array_equal(moved[~changed], still[~changed])


def test_unlabelled_returns_and_other_time_models_are_left_alone(world):
    scene, plan, truth = world
    track = _config().track
    from drivetrack.depth.stage import _labelled_motion
    owner, trajectory, memo = _labelled_motion(scene, track, plan)
    part = scene.lidar.of_frame(1)
    rows = np.arange(part.start, part.stop, dtype=np.int64)
    points = scene.lidar.points_vehicle[part]
    out = points_at_image_time(scene, track, owner, trajectory, int(CameraName.FRONT_LEFT), 1, rows, points)
    # the memo of box-frame positions (shared by the cameras of a frame) changes nothing
    for _ in range(2):
        np.testing.assert_array_equal(points_at_image_time(scene, track, owner, trajectory, int(CameraName.FRONT_LEFT),
                                                           1, rows, points, memo=memo), out)
    labelled = owner[rows] >= 0
    assert labelled.any() and (~labelled).any()
    np.testing.assert_array_equal(out[~labelled], points[~labelled])
    shift = np.linalg.norm(out[labelled] - points[labelled], axis=-1)
    # a return is captured within the 0.1 s sweep of the image time (world speeds of the labels)
    fastest = np.linalg.norm(truth.objects["velocity_world"], axis=-1).max()
    assert shift.max() < 0.1 * fastest
    assert (shift > 1e-3).any()
    # the velocity time model and the switch turn it off: the maps are those of the returns as captured
    for off in (_config(time_model="velocity").track, _config(depth_object_motion=False).track):
        assert _labelled_motion(scene, off, plan) is None


def test_config_refuses_a_non_boolean_switch():
    with pytest.raises(ValueError, match="depth_object_motion"):
        _config(depth_object_motion="yes")
