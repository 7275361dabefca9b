"""drivetrack.outputs: where clip files live (tracks/{split}/, tapvid3d/{split}/)."""
import pytest

from drivetrack.outputs import (DRIVETRACK, TAPVID3D, clip_glob, clip_path, clips_of, parse_clip_path,
                               splits_of)


def test_paths_round_trip():
    path = clip_path(DRIVETRACK, "validation", "waymo_seg_FRONT_car")
    assert path == "tracks/validation/waymo_seg_FRONT_car.npz"
    assert parse_clip_path(path) == (DRIVETRACK, "validation")
    assert parse_clip_path(clip_path(TAPVID3D, "training", "waymo_x")) == (TAPVID3D, "training")
    assert clip_glob(TAPVID3D, "training") == "tapvid3d/training/waymo_*.npz"


def test_gate_reports_and_other_files_are_not_clips():
    paths = ["validation/gates.json", "validation/report.html", "stats/objects.parquet",
             "previews/training/waymo_a.png", "tracks/training/notes.npz", "tracks/training/waymo_a.npz",
             "tapvid3d/validation/waymo_b.npz", "tracks/waymo_c.npz"]
    assert [p for p in paths if parse_clip_path(p)] == ["tracks/training/waymo_a.npz",
                                                         "tapvid3d/validation/waymo_b.npz"]
    assert splits_of(paths) == ["training", "validation"]
    assert splits_of(paths, DRIVETRACK) == ["training"]
    assert clips_of(paths, TAPVID3D, "validation") == ["tapvid3d/validation/waymo_b.npz"]


@pytest.mark.parametrize("layout, split", [("nope", "training"), (DRIVETRACK, ""), (DRIVETRACK, "a/b")])
def test_bad_names_are_refused(layout, split):
    with pytest.raises(ValueError):
        clip_path(layout, split, "waymo_x")
