"""Speed consistency under the labelled poses (drivetrack.tracks.consistency) and its objects-table columns."""
from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest

from drivetrack.annotate import AnnotateConfig, annotate_segment, load_scene_for
from drivetrack.tracks.consistency import label_speed_errors, lidar_rows_from_sources, sorted_return_keys
from drivetrack.tracks import TrackConfig


@pytest.fixture(scope="module")
def tracked(synth_source, synth_segments, tmp_path_factory):
    """Tracks carried with the labels as read (no refinement, no sweep compensation, no
    trajectory: it levels the labels' ego tilt) + scene."""
    config = AnnotateConfig(track=TrackConfig(compensate_sweep_motion=False, time_model="velocity"),
                            refine_poses=False)
    segment = synth_segments[0]
    result = annotate_segment(synth_source, "training", segment, str(tmp_path_factory.mktemp("cons")),
                              config, keep_tracks=True)
    assert result.status == "done", result.error
    scene = load_scene_for(synth_source, "training", segment, config, refine=False)
    return scene, [t for t in result.tracks if t.rejection is None], result.objects


def test_labels_as_used_reproduce_the_track_stage_speed_errors(tracked):
    scene, tracks, _ = tracked
    assert tracks
    for t in tracks:
        np.testing.assert_allclose(label_speed_errors(scene, scene.boxes, t), t.speed_error_mps,
                                   rtol=1e-7, atol=1e-9, err_msg=t.object_id)


def test_jittered_labels_are_less_consistent(tracked):
    """5 cm of per-frame label jitter adds path length: every clip's median error grows (by
    ~n_perp^2 / (2 |v dt|) per step for a moving object: centimetres per second at 10 m/s)."""
    scene, tracks, _ = tracked
    rng = np.random.default_rng(0)
    boxes = scene.boxes
    noisy = dataclasses.replace(boxes, center=boxes.center + rng.normal(0, 0.05, boxes.center.shape))
    for t in tracks:
        exact = np.median(label_speed_errors(scene, boxes, t))
        jittered = np.median(label_speed_errors(scene, noisy, t))
        assert jittered > exact + 0.01, (t.object_id, exact, jittered)


def test_missing_label_frame_gives_nan(tracked):
    scene, tracks, _ = tracked
    t = tracks[0]
    drop = (scene.boxes.object_id == t.object_id) & (scene.boxes.frame == t.frames[3])
    errors = label_speed_errors(scene, scene.boxes.select(~drop), t)
    assert errors.shape == (t.num_tracks,) and np.isnan(errors).all()


def test_unknown_source_return_is_named(tracked):
    scene, tracks, _ = tracked
    t = tracks[0]
    sources = t.lidar_sources.copy()
    sources[2] = (1, 1, 63, 9999)
    with pytest.raises(ValueError, match=r"obj.*track 2 names a LiDAR return \(frame \d+, laser 1, return 1, "
                                         r"row 63, col 9999\)"):
        lidar_rows_from_sources(scene.lidar, t.frames[t.query_frames], sources, where=f"obj {t.object_id}")


def test_objects_table_carries_the_labels_figures(tracked, annotated_output):
    _, _, objects = tracked
    columns = [f"label_speed_err_p{p}" for p in (25, 50, 75, 95, 99)]
    # labels used as read: identical columns
    for p in (25, 50, 75, 95, 99):
        np.testing.assert_array_equal(objects[f"label_speed_err_p{p}"], objects[f"speed_err_p{p}"])
    # default run (pose refinement on; exact synthetic labels are kept): finite, close to the used poses'
    table = pd.read_parquet(f"{annotated_output}/stats/objects.parquet")
    assert set(columns) <= set(table.columns)
    assert np.isfinite(table[columns].to_numpy()).all()
    assert np.all(np.abs(table["label_speed_err_p50"] - table["speed_err_p50"]) < 0.05)


def test_source_rows_with_a_shared_sorted_key_table(tracked):
    """One sorted key table per segment, passed to every clip, finds the same rows as building it
    per call; the rows name exactly the tracks' source returns."""
    scene, tracks, _ = tracked
    keys = sorted_return_keys(scene.lidar)
    assert np.all(np.diff(keys[1]) > 0)                       # keys are unique and ascending
    for t in tracks:
        frames = t.frames[t.query_frames]
        rows = lidar_rows_from_sources(scene.lidar, frames, t.lidar_sources, "shared", keys)
        np.testing.assert_array_equal(rows, lidar_rows_from_sources(scene.lidar, frames, t.lidar_sources, "own"))
        for name, column in (("laser", 0), ("return_index", 1), ("row", 2), ("col", 3)):
            np.testing.assert_array_equal(getattr(scene.lidar, name)[rows], t.lidar_sources[:, column])
        np.testing.assert_array_equal(scene.lidar.frame[rows], frames)
        np.testing.assert_array_equal(label_speed_errors(scene, scene.boxes, t, keys),
                                      label_speed_errors(scene, scene.boxes, t))


def test_sorted_return_keys_of_returns_in_any_order(tracked):
    """The reader's returns come in key order (no sort needed); returns in any other order are
    sorted, and the same sources are found."""
    from types import SimpleNamespace

    scene, tracks, _ = tracked
    lidar = scene.lidar
    order, keys = sorted_return_keys(lidar)
    np.testing.assert_array_equal(order, np.arange(len(lidar.frame)))          # already in key order
    perm = np.random.default_rng(2).permutation(len(lidar.frame))
    names = ("frame", "laser", "return_index", "row", "col")
    shuffled = SimpleNamespace(**{n: getattr(lidar, n)[perm] for n in names})
    s_order, s_keys = sorted_return_keys(shuffled)
    np.testing.assert_array_equal(s_keys, keys)
    np.testing.assert_array_equal(perm[s_order], order)
    t = next(t for t in tracks if t.num_tracks)
    rows = lidar_rows_from_sources(shuffled, t.frames[t.query_frames], t.lidar_sources, "shuffled", (s_order, s_keys))
    np.testing.assert_array_equal(perm[rows], lidar_rows_from_sources(lidar, t.frames[t.query_frames], t.lidar_sources))


def test_label_speeds_kernel_equals_the_numpy_path(tracked, monkeypatch):
    """The path-length kernel gives the numpy chunks' speeds (to float64 rounding)."""
    from drivetrack.tracks import consistency

    scene, tracks, _ = tracked
    t = next(t for t in tracks if t.num_tracks)
    fused = label_speed_errors(scene, scene.boxes, t)
    monkeypatch.setattr(consistency, "NUMBA_AVAILABLE", False)
    reference = label_speed_errors(scene, scene.boxes, t)
    assert np.isfinite(reference).any()
    np.testing.assert_allclose(fused, reference, rtol=1e-12, atol=1e-12)
