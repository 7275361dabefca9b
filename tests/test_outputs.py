"""drivetrack.outputs: where clip files live (tracks/{split}/, tapvid3d/{split}/)."""
import pytest

from drivetrack.outputs import (DRIVETRACK, OBJECT_COLUMNS, REJECTION_COLUMNS, SEGMENT_COLUMNS, TAPVID3D,
                                RejectionReason, SegmentStatus, clip_glob, clip_path, clips_of, is_clip_name,
                                parse_clip_name, parse_clip_path, splits_of)


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


def test_one_clip_name_parser_for_evaluation_and_show():
    from drivetrack import show
    from drivetrack.evaluation.clips import Clip as EvaluationClip

    assert show.parse_clip_name is parse_clip_name and show.Clip is EvaluationClip
    assert parse_clip_name("a/b/waymo_1_2_FRONT_LEFT_x_y.npz") == ("1_2", "FRONT_LEFT", "x_y")
    assert parse_clip_name("waymo_s_FRONT_x_SIDE_LEFT_o", ["s_FRONT_x"]) == ("s_FRONT_x", "SIDE_LEFT", "o")
    with pytest.raises(ValueError, match="waymo_s_BACK_o.npz: not a clip file name"):
        parse_clip_name("waymo_s_BACK_o.npz")
    assert is_clip_name("x/waymo_s_FRONT_o.npz") and not is_clip_name("waymo_s_FRONT_o.png")
    assert is_clip_name("waymo_s_FRONT_a b.npz") and not is_clip_name("waymo_s_FRONT_a b.npz", strict_object_id=True)


def test_written_tables_hold_exactly_the_contract(annotated_output):
    """The files a run writes use the columns and categorical values outputs.py declares."""
    import pandas as pd

    objects = pd.read_parquet(f"{annotated_output}/stats/objects.parquet")
    segments = pd.read_parquet(f"{annotated_output}/stats/segments.parquet")
    rejections = pd.read_parquet(f"{annotated_output}/stats/rejections.parquet")
    assert list(objects.columns[:len(OBJECT_COLUMNS)]) == list(OBJECT_COLUMNS)
    assert list(segments.columns) == list(SEGMENT_COLUMNS)
    assert list(rejections.columns) == list(REJECTION_COLUMNS)
    assert set(segments["status"]) <= {s.value for s in SegmentStatus} - {SegmentStatus.RUNNING.value}
    assert len(rejections) and set(rejections["reason"]) <= {r.value for r in RejectionReason}
    assert all(type(v) is str for v in rejections["reason"])          # plain strings once read back


def test_gates_read_only_columns_the_writers_write():
    from drivetrack.gates import tables
    from drivetrack.outputs import LABEL_SPEED_ERR_COLUMNS

    assert set(tables.OBJECT_COLUMNS) <= set(OBJECT_COLUMNS)
    assert set(tables.LABEL_SPEED_ERR_COLUMNS) <= set(LABEL_SPEED_ERR_COLUMNS)
    assert set(tables.SEGMENT_COLUMNS) <= set(SEGMENT_COLUMNS)
    assert set(tables.REJECTION_COLUMNS) <= set(REJECTION_COLUMNS)
