"""The refinement's sweep compensation with the registered boxes' motion (``RefineConfig.motion_passes``).

Returns are captured while the TOP sweep passes an object; the refinement first moves each
candidate to its box's time with the labels' finite-difference motion, which 5 cm labels get
wrong by ~0.5 m/s (a centimetre of shear across a near object's sweep). The second pass
(default) moves them with the motion of the boxes registered in the first, the least-squares
slope over two boxes either side (``RefineConfig.motion_window``).
"""
from __future__ import annotations

import numpy as np
import pytest

from drivetrack.annotate import AnnotateConfig, load_scene_for, refine_scene
from drivetrack.refine import RefineConfig
from drivetrack.synth import SynthConfig, generate_segment, load_ground_truth
from drivetrack.tracks import TrackConfig
from drivetrack.tracks.sweep_motion import box_motion_world

CAMERAS = ("FRONT", "SIDE_RIGHT")


@pytest.fixture(scope="module")
def noisy(tmp_path_factory):
    src = str(tmp_path_factory.mktemp("motion") / "src")
    seg = generate_segment(src, SynthConfig(seed=7, frames=10, preset="small", cameras=CAMERAS, world="hard",
                                            box_noise_m=0.05), 0)["segment"]
    return src, seg, load_ground_truth(src, "training", seg).objects


def _errors(scene, truth, object_id: str) -> np.ndarray:
    """float64 [T, 3] metres: the box centres' frame-to-frame error (their median taken out) in
    the true box frame (along, across, up), against the truth at each box's label time."""
    k = list(truth["object_id"].astype(str)).index(object_id)
    rows = np.flatnonzero(scene.boxes.object_id.astype(str) == object_id)
    f = scene.boxes.frame[rows]
    world = (np.einsum("tij,tj->ti", scene.world_from_vehicle[f, :3, :3], scene.boxes.center[rows])
             + scene.world_from_vehicle[f, :3, 3])
    true_box = truth["world_from_box"][k, f]
    true_centre = true_box[:, :3, 3] + truth["velocity_world"][k, f] * truth["label_time_offset_s"][k, f][:, None]
    error = np.einsum("tji,tj->ti", true_box[:, :3, :3], world - true_centre)
    return error - np.median(error, axis=0)


def test_second_pass_removes_the_shear_of_the_labels_motion(noisy):
    """The car the ego overtakes 1.5-2 m beside it (SIDE_RIGHT): its across and up errors (the
    directions its faces pin down) fall by more than half with the second pass; objects kept at
    their labels are not touched."""
    src, seg, truth = noisy
    role = dict(zip(truth["object_id"].astype(str), truth["role"].astype(str)))
    track = TrackConfig(cameras=CAMERAS, min_frames=4, max_camera_distance_m=75.0)
    scene = load_scene_for(src, "training", seg, AnnotateConfig(track=track), refine=False)
    one, two = (refine_scene(scene, AnnotateConfig(track=track, refine_options={"motion_passes": n})) for n in (1, 2))
    beside = next(o for o, r in role.items() if r == "overtaken_right")
    assert two.box_refinement[beside]["refine_applied"]
    e1, e2 = (np.median(np.abs(_errors(s, truth, beside)), axis=0) for s in (one, two))
    assert np.all(e2[1:] < 0.6 * e1[1:]), (e1, e2)
    for oid, summary in one.box_refinement.items():
        if not summary["refine_applied"]:      # kept at the labels (static, consistent): the same boxes
            rows = one.boxes.object_id.astype(str) == oid
            np.testing.assert_array_equal(one.boxes.center[rows], two.boxes.center[rows], err_msg=oid)


def test_exact_labels_are_kept_whatever_the_passes(tmp_path):
    src = str(tmp_path / "src")
    seg = generate_segment(src, SynthConfig(seed=3, frames=6, preset="small", cameras=("SIDE_RIGHT",),
                                            world="hard"), 0)["segment"]
    track = TrackConfig(cameras=("SIDE_RIGHT",), min_frames=4)
    scene = load_scene_for(src, "training", seg, AnnotateConfig(track=track), refine=False)
    for n in (1, 2, 3):
        refined = refine_scene(scene, AnnotateConfig(track=track, refine_options={"motion_passes": n}))
        np.testing.assert_array_equal(refined.boxes.center, scene.boxes.center)
        assert refined.box_refinement and not any(s["refine_applied"] for s in refined.box_refinement.values())


@pytest.mark.parametrize("value", [0, -1, 1.5, True, "2"])
def test_motion_passes_must_be_a_positive_integer(value):
    with pytest.raises(ValueError, match="motion_passes"):
        RefineConfig(motion_passes=value)


def test_windowed_motion_is_exact_for_constant_acceleration_inside_the_track():
    """``box_motion_world(..., half=2)``: the least-squares slope over a symmetric window equals
    the true velocity and yaw rate under constant acceleration (the quadratic term is orthogonal
    to it); ``half=1`` keeps the central differences; tracks of different objects do not mix."""
    t = np.arange(8) * 0.1
    x = 3.0 * t + 0.5 * 2.0 * t ** 2
    yaw = 0.2 * t
    poses = np.tile(np.eye(4), (2 * t.size, 1, 1))
    poses[: t.size, 0, 3] = x
    poses[: t.size, 0, 0] = poses[: t.size, 1, 1] = np.cos(yaw)
    poses[: t.size, 1, 0], poses[: t.size, 0, 1] = np.sin(yaw), -np.sin(yaw)
    poses[t.size:, 1, 3] = 100.0 - 5.0 * t                           # another object, far away
    times = np.concatenate([t, t])
    group = np.repeat(["a", "b"], t.size)
    v2, w2, ok = box_motion_world(poses, times, group, half=2)
    v1, _, _ = box_motion_world(poses, times, group, half=1)
    middle = np.arange(2, t.size - 2)                 # a full window on both sides
    np.testing.assert_allclose(v2[middle, 0], 3.0 + 2.0 * t[middle], atol=1e-9)
    np.testing.assert_allclose(w2[: t.size], 0.2, atol=1e-9)
    np.testing.assert_allclose(v2[t.size:], np.tile([0.0, -5.0, 0.0], (t.size, 1)), atol=1e-9)
    assert ok.all()
    np.testing.assert_allclose(v1[1, 0], (x[2] - x[0]) / 0.2)         # central differences
    assert abs(v2[0, 0] - 3.0) > 0.05       # (a one-sided window at the ends: biased by the acceleration)


def test_motion_prior_runs_at_the_label_times_unless_they_do_not_advance():
    """The refinement's motion prior samples each box at its label time (frame time + label
    offset); an object on the sweep's seam behind the vehicle (labelled at the end of one sweep,
    the start of the next) keeps its frame times rather than two boxes a few ms apart."""
    from drivetrack.refine.scene import _box_times

    frame = np.arange(5) * 0.1
    np.testing.assert_array_equal(_box_times(frame, None), frame)
    beside = np.array([-0.030, -0.028, -0.025, -0.021, -0.016])
    np.testing.assert_allclose(_box_times(frame, beside), frame + beside)
    seam = np.array([0.040, 0.048, -0.045, -0.040, -0.035])
    np.testing.assert_array_equal(_box_times(frame, seam), frame)
    np.testing.assert_array_equal(_box_times(frame[:1], seam[:1]), frame[:1])


@pytest.fixture(scope="module")
def sweep_noisy(tmp_path_factory):
    """A car passing close beside the ego seen by SIDE_LEFT, boxes labelled when the sweep passed
    them, 5 cm / 1 deg label noise (the scene of tests/test_time_scene.py with noisy labels)."""
    src = str(tmp_path_factory.mktemp("sweep_noisy") / "src")
    seg = generate_segment(src, SynthConfig(seed=7, frames=10, preset="small", cameras=("SIDE_LEFT",), world="hard",
                                            label_time="sweep", box_noise_m=0.05), 0)["segment"]
    return src, seg, load_ground_truth(src, "training", seg).objects


def test_the_extent_term_pins_a_box_car_seen_side_on_along_the_road(sweep_noisy):
    """The close pass shows the lidar its side (a plane: nothing along the road) in most frames;
    where the side's returns end pins it there (``extent_sigma_m``, docs/refinement.md, "Extent").
    Measured at the fixed jerk stiffness of before; with the stiffness chosen from the labels (the
    default since 2026-12-03) this car's labels get 1 m/s^3 and its along-road error is at most
    5.5 mm without the extent term, 10 mm with it (the term is off by default)."""
    src, seg, truth = sweep_noisy
    role = dict(zip(truth["object_id"].astype(str), truth["role"].astype(str)))
    close = next(o for o, r in role.items() if r == "close_pass")
    track = TrackConfig(cameras=("SIDE_LEFT",), min_frames=8, label_time="sweep")
    scene = load_scene_for(src, "training", seg, AnnotateConfig(track=track), refine=False)
    off, on = (refine_scene(scene, AnnotateConfig(track=track, refine_options={"extent_sigma_m": sigma,
                                                                               "jerk_sigma_choices_mps3": ()}))
               for sigma in (None, 0.01))
    assert on.box_refinement[close]["refine_applied"]
    along_off, along_on = (np.abs(_errors(s, truth, close)[:, 0]) for s in (off, on))
    assert along_on.max() < 0.6 * along_off.max(), (along_off, along_on)
