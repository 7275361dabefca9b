"""Hostile input and faults for ``annotate`` and the Waymo reader (issue 13 items 2, 6 and 7).

- Crashed workers: a real ``SIGKILL`` of a real worker process (``drivetrack.faults``) fails only
  its own segment after one retry in a fresh process; OUT never keeps ``.partial-*`` files or the
  clip files of a failed segment.
- Bad numbers in the source: non-finite or non-rigid transforms, non-finite intrinsics, box
  geometry and per-pixel poses are errors naming file, segment, component, column and value;
  NaN/inf ranges are data, dropped and counted.
- Names that would become paths (segment ids, split, object ids) are refused before any path is
  built.
"""
from __future__ import annotations

import json
import math
import os
import signal
from pathlib import Path

import numpy as np
import pytest

from _waymo_parquet import expect_format_error, SEGMENT, TIMESTAMPS, flat, rigid, tiny_segment, write_component
from drivetrack.names import InvalidNameError
from drivetrack.waymo import reader
from drivetrack.waymo.summary import segment_summary
from drivetrack.waymo.reader import WaymoFormatError

SPLIT = "training"
VP = "[VehiclePoseComponent].world_from_vehicle.transform"
CC = "[CameraCalibrationComponent]."
CI = "[CameraImageComponent]."
LC = "[LiDARCalibrationComponent]."
LB = "[LiDARBoxComponent]."
LP = "[LiDARPoseComponent].range_image_return1.values"
R1 = "[LiDARComponent].range_image_return1.values"


def _expect(exc_info, component: str, column: str, *fragments: str):
    expect_format_error(exc_info, SPLIT, component, column, *fragments)


def _load(root, **kw):
    return reader.load_scene(str(root), SPLIT, SEGMENT, cameras=(1, 2), **kw)


def _rewrite(root, component: str, edit) -> None:
    """Read ``component`` of the tiny segment, let ``edit(columns)`` change it, write it back."""
    table = reader.read_component(str(root), SPLIT, component, SEGMENT)
    cols = {n: table[n].to_pylist() for n in table.column_names}
    edit(cols)
    write_component(root, SPLIT, component, SEGMENT, cols)


# --------------------------------------------------------------------------------------------
# Item 7: bad numbers at the reader


def test_inf_in_vehicle_pose_is_an_error(tmp_path):
    tiny_segment(tmp_path)

    def edit(cols):
        cols[VP][1][3] = math.inf
    _rewrite(tmp_path, "vehicle_pose", edit)
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "vehicle_pose", VP, "infinite value in a transform", "inf", f"{TIMESTAMPS[1]}")


def test_inf_in_camera_image_pose_is_an_error(tmp_path):
    tiny_segment(tmp_path)

    def edit(cols):
        cols[CI + "pose.transform"][2][11] = -math.inf
    _rewrite(tmp_path, "camera_image", edit)
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "camera_image", CI + "pose.transform", "infinite value in a transform",
            "key.camera_name")


@pytest.mark.parametrize("component, column, row", [
    ("vehicle_pose", VP, 2),
    ("camera_calibration", CC + "extrinsic.transform", 0),
    ("camera_image", CI + "pose.transform", 4),
    ("lidar_calibration", LC + "extrinsic.transform", 1),
])
@pytest.mark.parametrize("damage", ["scaled x5", "sheared", "reflection", "last row"])
def test_transform_that_is_not_rigid_is_an_error(tmp_path, component, column, row, damage):
    tiny_segment(tmp_path)

    def edit(cols):
        m = np.asarray(cols[column][row], np.float64).reshape(4, 4)
        if damage == "scaled x5":
            m[:3, :3] *= 5.0
        elif damage == "sheared":
            m[0, 1] += 1e-3
        elif damage == "reflection":
            m[:3, 2] *= -1.0
        else:
            m[3] = [0.0, 0.0, 0.1, 1.0]
        cols[column][row] = flat(m)
    _rewrite(tmp_path, component, edit)
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, component, column, "transform is not rigid", "det(R)", "1e-06")


def test_rigid_tolerance_accepts_float32_rotations_and_refuses_1e_5(tmp_path):
    """Real data writes float32 rotations as doubles (|R^T R - I| ~ 1e-7): not an error; a
    rotation scaled by 1 + 1e-5 is."""
    tiny_segment(tmp_path)
    rounded = rigid(0.37, [1.5, 0.0, 2.0]).astype(np.float32).astype(np.float64)

    def edit(cols):
        cols[CC + "extrinsic.transform"][0] = flat(rounded)
    _rewrite(tmp_path, "camera_calibration", edit)
    scene = _load(tmp_path)
    np.testing.assert_array_equal(scene.cameras[1].model.vehicle_from_camera, rounded)

    def scale(cols):
        m = rounded.copy()
        m[:3, :3] *= 1.0 + 1e-5
        cols[CC + "extrinsic.transform"][0] = flat(m)
    _rewrite(tmp_path, "camera_calibration", scale)
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "camera_calibration", CC + "extrinsic.transform", "transform is not rigid")


@pytest.mark.parametrize("column, value", [("intrinsic.f_u", math.inf), ("intrinsic.p1", math.nan),
                                           ("intrinsic.c_u", math.nan), ("intrinsic.k1", math.inf)])
def test_non_finite_intrinsic_is_an_error(tmp_path, column, value):
    tiny_segment(tmp_path)

    def edit(cols):
        cols[CC + column][1] = value
    _rewrite(tmp_path, "camera_calibration", edit)
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "camera_calibration", CC + column, "found")


@pytest.mark.parametrize("column, value, problem", [
    ("box.center.y", math.inf, "infinite"), ("box.size.z", -math.inf, "infinite"),
    ("box.heading", math.inf, "infinite"), ("box.size.x", -0.5, "negative box size"),
    ("speed.x", math.inf, "infinite value")])
def test_bad_box_numbers_are_errors(tmp_path, column, value, problem):
    tiny_segment(tmp_path)

    def edit(cols):
        cols[LB + column][2] = value
    _rewrite(tmp_path, "lidar_box", edit)
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "lidar_box", LB + "box." if column.startswith("box.") else LB + column, problem,
            "ped_b")


def test_inf_in_a_number_column_is_an_error(tmp_path):
    tiny_segment(tmp_path)

    def edit(cols):
        cols[CI + "velocity.linear_velocity.x"][0] = math.inf
    _rewrite(tmp_path, "camera_image", edit)
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "camera_image", CI + "velocity.linear_velocity.x", "infinite value", "inf")


def _pixel_index(row: int, col: int, channel: int, width: int = 8, channels: int = 6) -> int:
    return (row * width + col) * channels + channel


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_non_finite_per_pixel_pose_at_a_return_is_an_error(tmp_path, value):
    """Decision (docs/waymo-v2.md): a pose is checked where a return uses it. NaN/inf at a pixel
    without a return is never read (accepted, points unchanged); at a return it is an error."""
    tiny_segment(tmp_path)
    clean = _load(tmp_path)

    def unused(cols):   # pixel (0, 0) of frame 0 has no return in either return (range -1 / 0)
        cols[LP][0][_pixel_index(0, 0, 0)] = value
    _rewrite(tmp_path, "lidar_pose", unused)
    scene = _load(tmp_path)
    np.testing.assert_array_equal(scene.lidar.points_vehicle, clean.lidar.points_vehicle)
    assert np.isfinite(scene.lidar.points_vehicle).all()

    def edit(cols):   # pixel (0, 1) of frame 0 has a return (tests/_waymo_parquet.top_range)
        cols[LP][0][_pixel_index(0, 1, 3)] = value
    _rewrite(tmp_path, "lidar_pose", edit)
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "lidar_pose", LP, "per-pixel pose", "row 0", "col 1", f"{TIMESTAMPS[0]}")


def test_nan_and_inf_ranges_are_dropped_and_counted(tmp_path):
    tiny_segment(tmp_path)
    clean = _load(tmp_path)
    assert clean.source_stats["lidar_nonfinite_ranges"] == 0

    def edit(cols):   # two returns of TOP (laser 1) frame 0 become NaN and inf, one more NaN
        for pixel, value in (((0, 1), math.nan), ((1, 1), math.inf), ((2, 3), math.nan)):
            cols[R1][0][_pixel_index(*pixel, 0, channels=4)] = value
    _rewrite(tmp_path, "lidar", edit)
    scene = _load(tmp_path)
    assert scene.source_stats["lidar_nonfinite_ranges"] == 3
    assert np.isfinite(scene.lidar.points_vehicle).all()
    assert len(scene.lidar.points_vehicle) == len(clean.lidar.points_vehicle) - 3
    summary = segment_summary(str(tmp_path), SPLIT, SEGMENT)
    assert summary["lasers"]["TOP"]["nonfinite_return1"] == 3
    assert summary["lasers"]["TOP"]["nonfinite_return2"] == 0

    from drivetrack.cli import main

    assert main(["info", str(tmp_path), "--json"]) == 0


def test_annotate_fails_the_segment_with_a_non_rigid_pose(tmp_path, capsys):
    """End to end: ``drivetrack annotate`` reports the reader's error and exits non-zero."""
    from drivetrack.cli import main

    src = tmp_path / "src"
    tiny_segment(src)

    def edit(cols):
        m = np.asarray(cols[VP][0], np.float64).reshape(4, 4)
        m[:3, :3] *= 5.0
        cols[VP][0] = flat(m)
    _rewrite(src, "vehicle_pose", edit)
    out = tmp_path / "out"
    assert main(["annotate", str(src), "--out", str(out), "--no-refine-poses"]) == 1
    run = json.loads((out / "run.json").read_text())
    (segment,) = run["segments"]
    assert segment["status"] == "failed" and "transform is not rigid" in segment["error"]
    assert VP in segment["error"] and "vehicle_pose" in segment["error"]


# --------------------------------------------------------------------------------------------
# Item 2: names read from source data that become paths


@pytest.mark.parametrize("object_id", ["a/../../x", "car\n", "../evil", "a b", ".hidden", ""])
def test_object_id_that_cannot_be_a_file_name_is_refused(tmp_path, object_id):
    tiny_segment(tmp_path)

    def edit(cols):
        cols["key.laser_object_id"] = [object_id if v == "ped_b" else v
                                       for v in cols["key.laser_object_id"]]
    _rewrite(tmp_path, "lidar_box", edit)
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    _expect(e, "lidar_box", "key.laser_object_id", "object id cannot be part of a file name",
            repr(object_id), f"{TIMESTAMPS[1]}")


@pytest.mark.parametrize("segment", ["../x", "a/../b", "seg\n", ".seg", "a/b"])
def test_segment_or_split_name_is_refused_before_any_path_is_built(tmp_path, segment):
    from drivetrack.annotate import AnnotateConfig, annotate

    with pytest.raises(InvalidNameError, match="segment name"):
        reader.load_scene(str(tmp_path), SPLIT, segment)
    with pytest.raises(InvalidNameError, match="segment name"):
        segment_summary(str(tmp_path), SPLIT, segment)
    with pytest.raises(InvalidNameError, match="segment name"):
        annotate(str(tmp_path), SPLIT, [segment], str(tmp_path / "out"), AnnotateConfig())
    with pytest.raises(InvalidNameError, match="split name"):
        annotate(str(tmp_path), segment, ["ok"], str(tmp_path / "out"), AnnotateConfig())
    assert not (tmp_path / "out").exists()


def test_annotate_command_refuses_a_bad_segment_argument(tmp_path, capsys):
    from drivetrack.cli import main

    tiny_segment(tmp_path / "src")
    out = tmp_path / "out"
    assert main(["annotate", str(tmp_path / "src"), "--out", str(out), "--segment", "../../x"]) == 2
    assert "segment name '../../x'" in capsys.readouterr().err
    assert not out.exists()


def test_listing_a_segment_file_whose_name_is_no_segment_id_is_an_error(tmp_path):
    tiny_segment(tmp_path)
    bad = tmp_path / SPLIT / "lidar_box" / "evil\nname.parquet"
    bad.write_bytes((tmp_path / SPLIT / "lidar_box" / f"{SEGMENT}.parquet").read_bytes())
    with pytest.raises(InvalidNameError) as e:
        reader.list_segments(str(tmp_path), SPLIT)
    assert "'evil\\nname'" in str(e.value) and "lidar_box" in str(e.value)


# --------------------------------------------------------------------------------------------
# Item 6: a crashed worker fails only its own segment


def _fast_config():
    from drivetrack.annotate import AnnotateConfig
    from drivetrack.tracks import TrackConfig

    return AnnotateConfig(refine_poses=False, track=TrackConfig(
        cameras=("FRONT",), lasers=("TOP",), depth_lasers=("TOP",), returns=(1,),
        max_tracks_per_object=16))


def _files(out: Path) -> list[str]:
    return sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())


def _plant_leftovers(out: Path, segment: str) -> list[Path]:
    """What an earlier killed run leaves: temporary files and clips of ``segment``."""
    planted = [out / "tracks" / SPLIT / ".partial-abc123.npz",
               out / "tapvid3d" / "validation" / ".partial-def456.npz",
               out / "clips" / SPLIT / ".partial-abc.parquet",
               out / "frames" / SPLIT / f"{segment}_FRONT_LEFT.parquet",
               out / "stats" / ".partial-0.parquet",
               out / "tracks" / SPLIT / f"waymo_{segment}_FRONT_from-an-earlier-run.npz"]
    for path in planted:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"left by a killed run")
    return planted


def test_worker_killed_twice_fails_only_its_segment(synth_source, synth_segments, tmp_path,
                                                    monkeypatch):
    from drivetrack.annotate import annotate

    victim, other = synth_segments
    out = tmp_path / "out"
    planted = _plant_leftovers(out, victim)
    monkeypatch.setenv("DRIVETRACK_TEST_KILL_SEGMENT", victim)
    monkeypatch.setenv("DRIVETRACK_TEST_KILL_AT", "2")   # after its frames table is in OUT
    seen = []
    results = annotate(synth_source, SPLIT, [victim, other], str(out), _fast_config(), workers=2,
                       on_result=seen.append)
    by = {r.segment: r for r in results}
    assert by[other].status == "done" and by[other].files and by[other].attempts == 1
    failed = by[victim]
    assert failed.status == "failed" and failed.stage == "worker" and failed.attempts == 2
    assert victim in failed.error and "SIGKILL" in failed.error
    assert failed.worker_deaths == ["killed by signal SIGKILL"] * 2
    assert sorted(r.segment for r in seen) == sorted([victim, other])

    files = _files(out)
    assert not [f for f in files if Path(f).name.startswith(".partial-")], files
    assert not [f for f in files if victim in f], files
    assert not any(p.exists() for p in planted)
    import pyarrow.parquet as pq

    for url in by[other].files:   # the other segment's tables are all there and whole
        pq.read_table(url[len("file://"):] if url.startswith("file://") else url)
    run = json.loads((out / "run.json").read_text())
    status = {s["segment"]: (s["status"], s["stage"], s["num_files"]) for s in run["segments"]}
    assert status[victim] == ("failed", "worker", 0)
    assert status[other] == ("done", "", len(by[other].files))
    import pandas as pd

    segments = pd.read_parquet(out / "stats" / "segments.parquet")
    row = segments.set_index("segment").loc[victim]
    assert row["status"] == "failed" and "SIGKILL" in row["error"]
    objects = pd.read_parquet(out / "stats" / "objects.parquet")
    assert set(objects["segment"]) == {other}


def test_worker_killed_once_is_retried_in_a_fresh_process(synth_source, synth_segments, tmp_path,
                                                          monkeypatch):
    from drivetrack.annotate import annotate

    victim, other = synth_segments
    out = tmp_path / "out"
    marker = tmp_path / "killed-once"
    monkeypatch.setenv("DRIVETRACK_TEST_KILL_SEGMENT", victim)
    monkeypatch.setenv("DRIVETRACK_TEST_KILL_ONCE", str(marker))
    results = annotate(synth_source, SPLIT, [victim, other], str(out), _fast_config(), workers=2)
    assert marker.exists()   # the first attempt really was killed
    by = {r.segment: r for r in results}
    assert [by[s].status for s in (victim, other)] == ["done", "done"], [r.error for r in results]
    assert by[victim].attempts == 2 and by[victim].worker_deaths == ["killed by signal SIGKILL"]
    assert by[other].attempts == 1
    files = _files(out)
    assert not [f for f in files if Path(f).name.startswith(".partial-")], files
    written = sorted(str(Path(u.split("://", 1)[-1]).relative_to(out)) for r in results for u in r.files)
    assert [f for f in files if f.startswith(("clips/", "frames/"))] == written
    run = json.loads((out / "run.json").read_text())
    assert {s["segment"]: s["attempts"] for s in run["segments"]} == {victim: 2, other: 1}


def test_kill_point_never_kills_the_calling_process(monkeypatch):
    """The fault hook only fires inside a worker started by annotate (safety of the test hook)."""
    from drivetrack import faults

    monkeypatch.setenv("DRIVETRACK_TEST_KILL_SEGMENT", "x")
    faults.kill_point("x")   # still alive
    assert os.getpid() > 0 and signal.SIGKILL


# --------------------------------------------------------------------------------------------
# lidar_camera_synced_box (issue 16): read when present, joined on key, bad values named

SB = "[LiDARCameraSyncedBoxComponent]."


def _synced(root, rows=None) -> None:
    """The tiny segment's lidar_box rows as synced boxes, each moved 0.1 m along x, plus ``rows``
    (dicts of column -> value) appended."""
    ts = TIMESTAMPS
    cols = {"key.frame_timestamp_micros": [ts[0], ts[1], ts[1], ts[2]],
            "key.laser_object_id": ["car_a", "car_a", "ped_b", "car_a"],
            SB + "most_visible_camera_name": [1, 2, 1, 0],
            SB + "camera_synced_box.center.x": [10.1, 11.1, 5.1, 12.1],
            SB + "camera_synced_box.center.y": [1.0, 1.0, -2.0, 1.0],
            SB + "camera_synced_box.center.z": [0.8] * 4, SB + "camera_synced_box.size.x": [4.0] * 4,
            SB + "camera_synced_box.size.y": [2.0] * 4, SB + "camera_synced_box.size.z": [1.6] * 4,
            SB + "camera_synced_box.heading": [0.0] * 4}
    for row in rows or []:
        for name in cols:
            cols[name].append(row.get(name, cols[name][-1]))
    write_component(root, SPLIT, "lidar_camera_synced_box", SEGMENT, cols)


def test_synced_boxes_are_read_as_shifts_from_their_labels(tmp_path):
    tiny_segment(tmp_path)
    assert _load(tmp_path).boxes.synced_shift is None          # the component is optional
    _synced(tmp_path, [{"key.laser_object_id": "gone", SB + "camera_synced_box.center.x": 3.0}])
    scene = _load(tmp_path)
    boxes = scene.boxes
    np.testing.assert_allclose(boxes.synced_shift, np.tile([0.1, 0.0, 0.0], (4, 1)), atol=1e-12)
    order = {(int(f), str(o)): i for i, (f, o) in enumerate(zip(boxes.frame, boxes.object_id))}
    assert boxes.synced_camera[order[(1, "car_a")]] == 2 and boxes.synced_camera[order[(2, "car_a")]] == 0
    assert scene.source_stats["synced_boxes"] == 4 and scene.source_stats["synced_boxes_unmatched"] == 1
    # a refined box keeps its shift: boxes.select carries the columns
    assert boxes.select(np.array([0, 1])).synced_shift.shape == (2, 3)


@pytest.mark.parametrize("column, value, problem", [
    ("camera_synced_box.center.y", math.nan, "synced box centre"),
    ("camera_synced_box.center.x", math.inf, "infinite"),
    ("most_visible_camera_name", 9, "unknown camera name")])
def test_bad_synced_boxes_are_errors(tmp_path, column, value, problem):
    tiny_segment(tmp_path)
    _synced(tmp_path)

    def edit(cols):
        cols[SB + column][2] = value
    _rewrite(tmp_path, "lidar_camera_synced_box", edit)
    with pytest.raises(WaymoFormatError) as e:
        _load(tmp_path)
    expected_column = SB + ("camera_synced_box.center.x" if column.startswith("camera_synced_box") else column)
    _expect(e, "lidar_camera_synced_box", expected_column, problem)
