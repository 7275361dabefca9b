"""Issue 16 end to end on a small hard-world scene: a car passing close beside the ego, seen by
SIDE_LEFT (triggered ~30 ms before the frame time as the sweep passes it), ``lidar_box`` at the
sweep time. The old model (labels at the frame time, moved along a finite-difference velocity)
misplaces it by pixels; the trajectory with ``label_time: auto`` places it at each image's time."""
from __future__ import annotations

import numpy as np
import pytest

from drivetrack.annotate import AnnotateConfig, annotate_segment
from drivetrack.evaluation import evaluate_tracks
from drivetrack.synth import SynthConfig, generate_segment, load_ground_truth
from drivetrack.tracks import TrackConfig

SCENE = SynthConfig(seed=7, frames=10, preset="small", cameras=("SIDE_LEFT",), world="hard", label_time="sweep")


@pytest.fixture(scope="module")
def side_scene(tmp_path_factory):
    root = str(tmp_path_factory.mktemp("time_scene"))
    segment = generate_segment(root, SCENE, 0)["segment"]
    objects = load_ground_truth(root, "training", segment).objects
    close_pass = str(objects["object_id"][list(objects["role"].astype(str)).index("close_pass")])
    return root, segment, close_pass


def _close_pass_clip(side_scene, tmp_path, time_model, **track):
    root, segment, close_pass = side_scene
    config = AnnotateConfig(track=TrackConfig(cameras=("SIDE_LEFT",), min_frames=8, time_model=time_model,
                                              rolling_shutter=False, **track), refine_poses=False)
    out = tmp_path / (time_model + "".join(f"_{k}" for k in track))
    result = annotate_segment(root, "training", segment, str(out), config, keep_tracks=True)
    assert result.status == "done", result.error
    tracks = [t for t in result.tracks if t.rejection is None and t.object_id == close_pass]
    assert len(tracks) == 1, "the close pass is not a SIDE_LEFT clip of this scene"
    clip = evaluate_tracks(tracks, root).clips
    return clip[clip["query_mode"] == "first"].iloc[0], result


def test_side_camera_mover_is_placed_at_the_image_time(side_scene, tmp_path):
    old, _ = _close_pass_clip(side_scene, tmp_path, "velocity")
    new, result = _close_pass_clip(side_scene, tmp_path, "trajectory")
    # measured: velocity 9.8 px median (AJ 0.17), trajectory 0.50 px (AJ 0.80; the rest: the car
    # passes 1.5 m from the camera, where the non-time error floor of docs/time.md is largest)
    assert old["pixel_error_median"] > 3.0
    assert new["pixel_error_median"] < 0.75 and new["average_jaccard"] > 0.7
    assert result.segment_row["label_time"].tolist() == ["sweep"]
    assert (result.segment_row["label_time_residual_sweep_m"] < result.segment_row["label_time_residual_frame_m"]).all()
    objects = result.objects
    assert set(objects["time_model"]) == {"trajectory"} and set(objects["label_time"]) == {"sweep"}
    assert np.all(np.isfinite(objects["time_residual_m"]))


def test_synced_boxes_as_samples_end_to_end(side_scene, tmp_path):
    """``synced_boxes: true``: the scene's Waymo-defined synced boxes (the sweep-time label moved
    along its speed to SIDE_LEFT's capture time of the centre) join the trajectory as samples a
    capture offset after their label's time; the close pass stays where the labels alone put it
    (they add the labelled speed, exact here), and the segment row counts them."""
    default, plain = _close_pass_clip(side_scene, tmp_path, "trajectory")
    synced, result = _close_pass_clip(side_scene, tmp_path, "trajectory", synced_boxes=True)
    assert plain.segment_row["num_synced_samples"].tolist() == [0]
    assert result.segment_row["num_synced_samples"].iloc[0] >= 5
    assert result.segment_row["label_time"].tolist() == ["sweep"]
    assert synced["pixel_error_median"] < default["pixel_error_median"] + 0.02
    assert synced["average_jaccard"] > default["average_jaccard"] - 0.01
