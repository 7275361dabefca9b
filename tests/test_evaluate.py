"""Evaluation against exact synthetic truth, and scoring of a tracker's predictions against a release.

Uses the session's shared synthetic source and annotation (tests/conftest.py: small preset, two
segments, 30 frames); everything else here is cheap array work on copies of those files.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from drivetrack.evaluation import (METRIC_KEYS, Clip, TruthIndex, evaluate_annotations, evaluate_clips,
                                   evaluate_tracks, find_annotation_files, read_clip, score_clip,
                                   score_predictions)
from drivetrack.outputs import parse_clip_name

# Measured on the shared fixture (seed 7, small preset, 30 frames, default config, nearest
# depth): purity 1.0, OA 0.93, AJ 0.90, delta_avg 0.99, median pixel error 0.3 px. The thresholds
# leave a margin for small changes of the track stage; a real regression falls well below them.
MIN_PURITY = 0.995
MIN_OCCLUSION_ACCURACY = 0.88
MIN_AVERAGE_JACCARD = 0.82
MIN_DELTA_AVG = 0.95
MAX_MEDIAN_PIXEL_ERROR = 0.6


def _npz(path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as archive:
        return {k: archive[k] for k in archive.files}


def _copy_annotations(src: str, dst: Path) -> Path:
    """Copy the clip files (and stats) of an annotation folder, keeping relative paths."""
    for file in find_annotation_files(src):
        target = dst / file.relpath
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(file.url, target)
    if (Path(src) / "stats").is_dir():
        shutil.copytree(Path(src) / "stats", dst / "stats")
    return dst


@pytest.fixture(scope="module")
def truth_eval(annotated_output, synth_source):
    return evaluate_annotations(annotated_output, synth_source)


def test_finds_clip_files_and_skips_tapvid3d(annotated_output, synth_segments):
    files = find_annotation_files(annotated_output)
    assert files, "the fixture annotation has clip files"
    assert {f.segment for f in files} <= set(synth_segments)
    assert all("tapvid3d" not in f.relpath.split("/")[:-1] for f in files)
    assert all(f.split == "training" for f in files)
    assert find_annotation_files(annotated_output, split="validation") == []


def test_parse_clip_name_with_underscores():
    assert parse_clip_name("waymo_123_400_000_FRONT_LEFT_a_b-c.npz") == ("123_400_000", "FRONT_LEFT", "a_b-c")
    # a segment name containing a camera name is resolved by the known segments
    assert parse_clip_name("waymo_x_FRONT_y_FRONT_RIGHT_obj.npz", ["x_FRONT_y"]) == ("x_FRONT_y", "FRONT_RIGHT", "obj")
    with pytest.raises(ValueError, match="not a clip file name"):
        parse_clip_name("waymo_seg_BACK_obj.npz")


def test_exact_truth_as_annotation_scores_perfectly(synth_source, synth_segments):
    """Tracks that ARE the truth (of every hit of one object) score AJ = OA = 1 and zero error."""
    index = TruthIndex.load(synth_source, "training", synth_segments[0])
    hits = index.truth.hits
    camera = index.truth.camera_axis("FRONT")
    counts = np.bincount(hits["object_index"][hits["visible"][:, camera].any(axis=1)])
    k = int(np.argmax(counts))
    frames = np.arange(5, 29)
    rows = index.object_hits(k, frames)[::7]
    ts = index.timestamps_micros[frames]
    clip = Clip(segment=synth_segments[0], camera="FRONT", object_id=str(index.object_ids[k]), split="training",
                timestamps_micros=ts, tracks=hits["pixels"][rows[:, None], camera, frames[None]],
                visibles=hits["visible"][rows[:, None], camera, frames[None]],
                query_frames=np.searchsorted(frames, hits["frame"][rows]),
                lidar_sources=np.stack([hits["laser"][rows], hits["return_index"][rows], hits["row"][rows],
                                        hits["col"][rows]], axis=-1))
    result_rows, errors = score_clip(clip, index)
    for row in result_rows:
        assert row["num_matched"] == rows.size and row["purity"] == 1.0
        assert row["occlusion_accuracy"] == 1.0 and row["average_jaccard"] == 1.0
        assert row["average_pts_within_thresh"] == 1.0
        assert row["num_queries"] > 0
    assert errors.size > 0 and np.nanmax(errors) == 0.0
    assert result_rows[0]["num_hits_tracked"] == rows.size
    assert result_rows[0]["recall"] == pytest.approx(rows.size / index.object_hits(k, frames).size)


def test_annotations_reach_measured_accuracy_on_noise_free_scene(truth_eval):
    s = truth_eval.summary
    assert s["num_clips"] >= 4 and s["num_segments"] == 2
    assert s["purity"] >= MIN_PURITY
    assert s["num_matched"] + s["num_unmatched"] == s["num_tracks"]
    assert 0 < s["recall"] <= 1 and 0 < s["recall_visible"] <= 1
    assert s["pixel_error_median"] <= MAX_MEDIAN_PIXEL_ERROR
    for mode in ("first", "strided"):
        m = s["modes"][mode]
        assert m["occlusion_accuracy"] >= MIN_OCCLUSION_ACCURACY, (mode, m)
        assert m["average_jaccard"] >= MIN_AVERAGE_JACCARD, (mode, m)
        assert m["average_pts_within_thresh"] >= MIN_DELTA_AVG, (mode, m)
    clips = truth_eval.clips
    assert set(clips["query_mode"]) == {"first", "strided"}
    assert len(clips) == 2 * s["num_clips"]
    assert set(METRIC_KEYS) <= set(clips.columns)
    assert clips["purity"].min() >= 0.98
    objects = truth_eval.objects
    assert len(objects) == 2 * s["num_objects"]
    assert (objects["num_clips"] >= 1).all()
    json.dumps(truth_eval.to_json())   # JSON-able (NaN -> None)


def test_in_memory_tracks_score_like_their_files(synth_source, synth_segments, annotated_output, truth_eval,
                                                 tmp_path):
    from drivetrack.annotate import AnnotateConfig, annotate_segment

    result = annotate_segment(synth_source, "training", synth_segments[1], str(tmp_path), AnnotateConfig(),
                              keep_tracks=True)
    assert result.status == "done", result.error
    memory = evaluate_tracks(result.tracks, synth_source)
    from_files = truth_eval.clips[truth_eval.clips["segment"] == synth_segments[1]]
    columns = ["camera", "object_id", "query_mode", "num_tracks", "purity", "average_jaccard",
               "occlusion_accuracy", "pixel_error_median"]
    a = memory.clips[columns].sort_values(columns[:3]).reset_index(drop=True)
    b = from_files[columns].sort_values(columns[:3]).reset_index(drop=True)
    assert len(a) > 0
    np.testing.assert_array_equal(a[columns[:4]].to_numpy(), b[columns[:4]].to_numpy())
    np.testing.assert_allclose(a[columns[4:]].to_numpy(float), b[columns[4:]].to_numpy(float), rtol=1e-6)


def test_corrupted_annotation_scores_lower(exported_output, synth_source, truth_eval, tmp_path):
    """Exported npz clips (the evaluation reads them like the tables) with one clip corrupted."""
    out = _copy_annotations(exported_output, tmp_path / "out")
    files = find_annotation_files(str(out))
    target = max(files, key=lambda f: (Path(f.url).stat().st_size, f.relpath))
    arrays = _npz(target.url)
    rng = np.random.default_rng(0)
    n = arrays["tracks"].shape[0]
    half = rng.permutation(n)[: n // 2]
    arrays["tracks"][half] += np.float32(6.0)                        # drift by 6 px in x
    arrays["visibles"][half] = ~arrays["visibles"][half]             # wrong occlusion
    ground = rng.permutation(n)[: n // 5]
    arrays["lidar_sources"][ground, 2] = 0                           # top beam row: no object there
    np.savez_compressed(target.url, **arrays)

    corrupted = evaluate_annotations(str(out), synth_source)
    key = ["camera", "object_id", "query_mode"]
    before = truth_eval.clips.set_index(["segment"] + key)
    after = corrupted.clips.set_index(["segment"] + key)
    for mode in ("first", "strided"):
        k = (target.segment, target.camera, target.object_id, mode)
        assert after.loc[k, "average_jaccard"] < before.loc[k, "average_jaccard"] - 0.2
        assert after.loc[k, "occlusion_accuracy"] < before.loc[k, "occlusion_accuracy"] - 0.2
        assert after.loc[k, "purity"] < before.loc[k, "purity"]
        assert after.loc[k, "num_unmatched"] > 0
    assert corrupted.summary["purity"] < truth_eval.summary["purity"]
    assert corrupted.summary["modes"]["first"]["average_jaccard"] < truth_eval.summary["modes"]["first"]["average_jaccard"]


def test_mismatched_segments_give_clear_errors(exported_output, synth_source, synth_segments, tmp_path):
    file = find_annotation_files(exported_output)[0]
    clip = read_clip(file)
    other = TruthIndex.load(synth_source, "training", [s for s in synth_segments if s != file.segment][0])
    with pytest.raises(ValueError, match=f"ground truth of segment '{other.truth.segment}'"):
        score_clip(clip, other)

    # a file claiming an unknown segment
    stray = tmp_path / "stray" / "training" / Path(file.relpath).name.replace(file.segment, "not_a_segment")
    stray.parent.mkdir(parents=True)
    shutil.copyfile(file.url, stray)
    with pytest.raises(FileNotFoundError, match="segment 'not_a_segment'.*no synthetic ground truth"):
        evaluate_annotations(str(tmp_path / "stray"), synth_source)

    # same segment name, timestamps of another run
    shifted = Clip(**{**clip.__dict__, "timestamps_micros": clip.timestamps_micros + 1})
    index = TruthIndex.load(synth_source, "training", file.segment)
    with pytest.raises(ValueError, match=r"timestamp \d+ \(clip frame 0\) is not a frame of ground-truth segment"):
        score_clip(shifted, index)
    with pytest.raises(ValueError, match="object 'no-such-object' is not an object of ground-truth segment"):
        score_clip(Clip(**{**clip.__dict__, "object_id": "no-such-object"}), index)
    bad = Clip(**{**clip.__dict__, "lidar_sources": clip.lidar_sources[:-1]})
    with pytest.raises(ValueError, match=r"lidar_sources has shape"):
        score_clip(bad, index)
    with pytest.raises(FileNotFoundError, match="no clips"):
        evaluate_annotations(str(tmp_path / "stray"), synth_source, split="validation")


def _write_predictions(src: str, dst: Path, transform=lambda arrays: arrays, key: str = "visibles") -> Path:
    for file in find_annotation_files(src):
        clip = read_clip(file)
        pred = transform({"tracks": clip.tracks.copy(), "visibles": clip.visibles.copy()})
        out = {"tracks": pred["tracks"]}
        out[key] = pred["visibles"] if key == "visibles" else ~pred["visibles"]
        target = dst / "nested" / file.name
        target.parent.mkdir(parents=True, exist_ok=True)
        np.savez(target, **out)
    return dst


def test_perfect_predictions_score_one(annotated_output, tmp_path):
    preds = _write_predictions(annotated_output, tmp_path / "pred", key="occluded")
    result = score_predictions(annotated_output, str(preds))
    for mode in ("first", "strided"):
        m = result.summary["modes"][mode]
        assert m["average_jaccard"] == 1.0 and m["occlusion_accuracy"] == 1.0
        assert m["average_pts_within_thresh"] == 1.0
    assert result.summary["pixel_error_median"] == 0.0
    assert (result.clips["average_jaccard"] == 1.0).all()
    resized = score_predictions(annotated_output, str(preds), resize_to=(256, 256), query_modes=("first",))
    assert resized.summary["modes"]["first"]["average_jaccard"] == 1.0
    assert resized.summary["resolution"] == "256x256"


def test_shifted_predictions_lose_the_fine_thresholds(annotated_output, tmp_path):
    def shift(arrays):
        arrays["tracks"][..., 0] += np.float32(3.0)                # 3 px in x: within 4, not within 2
        return arrays

    preds = _write_predictions(annotated_output, tmp_path / "pred", shift)
    m = score_predictions(annotated_output, str(preds)).summary["modes"]["first"]
    assert m["pts_within_1"] == 0.0 and m["pts_within_2"] == 0.0
    assert m["pts_within_4"] == 1.0 and m["occlusion_accuracy"] == 1.0
    assert m["average_jaccard"] == pytest.approx(0.6)


def test_bad_predictions_name_the_file(annotated_output, tmp_path):
    preds = _write_predictions(annotated_output, tmp_path / "pred")
    files = sorted((preds / "nested").glob("*.npz"))
    files[0].unlink()
    with pytest.raises(FileNotFoundError, match=r"has no file for 1 of \d+ clips"):
        score_predictions(annotated_output, str(preds))
    partial = score_predictions(annotated_output, str(preds), allow_missing=True)
    assert partial.summary["num_clips_missing"] == 1
    arrays = _npz(files[1])
    np.savez(files[1], tracks=arrays["tracks"][:-1], visibles=arrays["visibles"][:-1])
    with pytest.raises(ValueError, match=rf"{files[1].name}: tracks has shape"):
        score_predictions(annotated_output, str(preds), allow_missing=True)
    np.savez(files[1], tracks=arrays["tracks"])
    with pytest.raises(ValueError, match=rf"{files[1].name}: needs 'visibles' or 'occluded'"):
        score_predictions(annotated_output, str(preds), allow_missing=True)


def test_cli(annotated_output, synth_source, tmp_path, capsys):
    from drivetrack.cli import main

    out = tmp_path / "eval.json"
    assert main(["evaluate", annotated_output, "--truth", synth_source, "--json", "--out", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["summary"]["kind"] == "annotations_vs_truth"
    assert json.loads(out.read_text())["summary"]["num_clips"] == printed["summary"]["num_clips"]
    preds = _write_predictions(annotated_output, tmp_path / "pred")
    assert main(["evaluate", annotated_output, "--predictions", str(preds), "--out", str(tmp_path / "c.csv")]) == 0
    assert "predictions vs release" in capsys.readouterr().out
    assert (tmp_path / "c.csv").read_text().startswith("split,")
    assert main(["evaluate", annotated_output, "--truth", str(tmp_path / "nowhere")]) == 2
    assert "no synthetic ground truth" in capsys.readouterr().err
    assert main(["evaluate", annotated_output, "--predictions", str(preds), "--resize", "abc"]) == 2
    with pytest.raises(SystemExit):
        main(["evaluate", annotated_output])          # --truth or --predictions is required
