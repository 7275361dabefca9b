"""Release gates run with Great Expectations on statistics tables written by the tests.

One module-scoped fixture runs the gates once per folder (good data and one folder per defect);
the tests then check the verdicts, the named expectations, the failing objects/segments and the
artefacts under OUT/validation/.
"""
from __future__ import annotations

import json
import re

import fsspec
import pandas as pd
import pytest

from drivetrack.cli import main as cli_main
from drivetrack.gates import card_summary, run_gates
from test_gates_fixtures import (EMPTY_SEGMENT, NAN_SPEED, NOISY, NONFINITE, OUTSIDE, REFINE_WORSE, apply_defect,
                                 clips_table_bytes, good_tables, make_output, write_output)

SPEED_MEDIANS = {f"release.speed_err_median.{p}" for p in ("p25", "p50", "p75", "p95", "p99")}


def _inconsistent(root):
    """Segment-level defects: a failed segment, a filter rejecting 36 of the 39 clips it examined,
    a rejections table that disagrees with the counts, and a clip missing from its clips table."""
    objects, segments, rejections = good_tables()
    segments.loc[segments["segment"] == "seg_b1", "status"] = "failed"
    b0 = segments["segment"] == "seg_b0"
    segments.loc[b0, ["num_object_clips_considered", "rejected_camera", "rejected_too_few_frames",
                      "rejected_no_visible_points"]] = [40, 0, 1, 36]
    rejections = pd.concat([
        rejections[rejections["segment"] != "seg_b0"],
        pd.DataFrame([dict(segment="seg_b0", camera="FRONT", object_id=f"o{i}",
                           reason="no_visible_points" if i else "too_few_frames") for i in range(37)])])
    a0 = segments["segment"] == "seg_a0"
    segments.loc[a0, "rejected_camera"] += 1  # one more than rejections.parquet lists
    write_output(root, objects, segments, rejections)
    row = objects.loc[4]
    table = objects[objects["file"] == row["file"]]
    (root / row["file"]).write_bytes(clips_table_bytes(table, drop=(row["segment"], row["camera"], row["object_id"])))
    return root


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    out = {}
    for name in ("good", "label_noise", "corrupt_tracks", "empty_segment", "nan_speed_err", "refine_worse"):
        root = tmp_path_factory.mktemp(name)
        make_output(root, None if name == "good" else name)
        docs = name in ("good", "label_noise")  # Data Docs cost ~2 s per run: build them twice
        out[name] = (root, run_gates(str(root), data_docs=docs))
    root = _inconsistent(tmp_path_factory.mktemp("inconsistent"))
    out["inconsistent"] = (root, run_gates(str(root), data_docs=False))
    return out


def _failed(report):
    return {f.gate for f in report.failures}


def _objects(result):
    return {(r["segment"], r["camera"], r["object_id"]) for r in result.failing}


def _failure(report, gate):
    return next(f for f in report.failures if f.gate == gate)


def test_good_release_passes_and_writes_its_report(reports):
    root, report = reports["good"]
    assert report.success and report.failures == [], [f.gate for f in report.failures]
    levels = {r.level for r in report.results}
    assert levels == {"object", "segment", "release"}
    val = root / "validation"
    saved = json.loads((val / "gates.json").read_text())  # strict JSON
    assert saved == json.loads(json.dumps(report.to_dict(), allow_nan=False))
    assert saved["success"] is True and saved["failures"] == []
    assert {p.name for p in (val / "gx_results").iterdir()} == {
        "drivetrack_object_objects.json", "drivetrack_segment_segments.json",
        "drivetrack_release_objects.json", "drivetrack_release_splits.json"}
    # the Waymo 'validation' split's clips (clips/validation/) are untouched by the gate run
    assert len(list((root / "clips" / "validation").glob("*.parquet"))) == 2
    assert "passed" in card_summary(report)


def test_reports_render_offline(reports):
    root, report = reports["label_noise"]
    docs = root / "validation" / "data_docs"
    pages = list(docs.rglob("*.html"))
    assert len(pages) >= 9  # index + 4 suites + 4 validation results
    for page in pages:
        text = page.read_text()
        loaded = re.findall(r"<(?:script|link|img)[^>]*(?:src|href)=\"(https?://[^\"]*)\"", text)
        assert loaded == [], (page, loaded)
        assert "<style>" in text
    index = (docs / "index.html").read_text()
    assert "drivetrack-offline-index" in index
    for page in docs.glob("validations/*/*/*/*.html"):
        assert page.relative_to(docs).as_posix() in index
    results = next(docs.glob("validations/drivetrack_object_objects/*/*/*.html")).read_text()
    assert "speed_err_p50" in results
    html = (root / "validation" / "report.html").read_text()
    assert "<script" not in html and "<link" not in html and "http" not in html.split("<body>")[0]
    assert "object.speed_err_p50_max" in html and "seg_a0" in html and "obj_1" in html


def test_label_noise_blocks_naming_speed_error_and_objects(reports):
    _, report = reports["label_noise"]
    assert not report.success
    assert _failed(report) == {"object.speed_err_p50_max", "object.speed_err_p95_max"} | SPEED_MEDIANS
    for gate in ("object.speed_err_p50_max", "object.speed_err_p95_max"):
        f = _failure(report, gate)
        assert f.level == "object" and f.expectation == "ExpectColumnValuesToBeBetween"
        assert _objects(f) == set(NOISY) and f.num_failing == len(NOISY)
        assert all(r[f.columns[0]] > f.expected["max_value"] for r in f.failing)
    f = _failure(report, "release.speed_err_median.p50")
    assert f.expectation == "ExpectColumnMedianToBeBetween" and f.level == "release"
    assert f.observed > 1.0 and f.expected["max_value"] == pytest.approx(2 * 0.1260)
    assert _objects(f) == set(NOISY)  # the objects that pull the median over the bound
    d = report.to_dict()
    assert d["success"] is False and len(d["failures"]) == 7
    json.dumps(d, allow_nan=False)
    card = card_summary(d)
    assert "object.speed_err_p50_max" in card and "seg_a0/FRONT/obj_0" in card


def test_corrupt_tracks_fail_nonfinite_and_outside_image(reports):
    _, report = reports["corrupt_tracks"]
    assert _failed(report) == {"object.no_nonfinite_visible", "object.visible_inside_image"}
    f = _failure(report, "object.no_nonfinite_visible")
    assert _objects(f) == {NONFINITE} and f.failing[0]["num_nonfinite_visible"] == 7
    f = _failure(report, "object.visible_inside_image")
    assert _objects(f) == {OUTSIDE} and f.failing[0]["num_visible_outside_image"] == 12
    assert f.expected == {"min_value": 0, "max_value": 0}


def test_empty_segment_fails_segment_gate(reports):
    _, report = reports["empty_segment"]
    assert _failed(report) == {"segment.min_object_clips_annotated"}
    f = _failure(report, "segment.min_object_clips_annotated")
    assert f.level == "segment"
    assert f.failing == [{"num_object_clips_annotated": 0, "split": "training", "segment": EMPTY_SEGMENT}]


def test_nan_speed_error_fails_finite_gate(reports):
    _, report = reports["nan_speed_err"]
    assert _failed(report) == {"object.speed_err_finite"}
    f = _failure(report, "object.speed_err_finite")
    assert _objects(f) == {NAN_SPEED}
    assert f.failing[0]["speed_err_p75"] == "NaN" and f.failing[0]["speed_err_p99"] == "Infinity"


def test_inconsistent_statistics_fail_segment_and_file_gates(reports):
    _, report = reports["inconsistent"]
    assert _failed(report) == {"segment.status", "segment.rejected_share.no_visible_points",
                               "segment.rejections_table_agrees", "object.file_exists",
                               "release.split_files_agree"}
    segs = lambda gate: {r["segment"] for r in _failure(report, gate).failing}  # noqa: E731
    assert segs("segment.status") == {"seg_b1"}
    assert segs("segment.rejected_share.no_visible_points") == {"seg_b0"}
    row = _failure(report, "segment.rejected_share.no_visible_points").failing[0]
    assert row["rejected_share_no_visible_points"] == pytest.approx(36 / 39)
    assert row["reached_no_visible_points"] == 39 and row["rejected_no_visible_points"] == 36
    assert segs("segment.rejections_table_agrees") == {"seg_a0"}
    assert _objects(_failure(report, "object.file_exists")) == {("seg_a1", "FRONT", "obj_1")}
    assert _failure(report, "release.split_files_agree").failing == [
        {"num_object_clips": 6, "num_clips_on_disk": 5, "split": "training"}]


def test_cli_exit_codes_and_config_override(tmp_path, capsys):
    make_output(tmp_path)
    cfg = tmp_path / "gates-override.yaml"
    cfg.write_text("release:\n  required_splits: [training, testing]\n")
    assert cli_main(["gates", str(tmp_path), "--config", str(cfg), "--no-data-docs"]) == 1
    out = capsys.readouterr().out
    assert "FAILED release.required_splits" in out and "testing" in out
    saved = json.loads((tmp_path / "validation" / "gates.json").read_text())
    assert saved["config"]["source"]["override"] == str(cfg)
    assert cli_main(["gates", str(tmp_path / "missing")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_gates_over_an_fsspec_url():
    fs = fsspec.filesystem("memory")
    objects, segments, rejections = apply_defect(*good_tables(seed=3), "corrupt_tracks")
    root = "memory://gates-test/out"
    fs.makedirs(root, exist_ok=True)
    for name, df in (("objects", objects), ("segments", segments), ("rejections", rejections)):
        with fs.open(f"{root}/stats/{name}.parquet", "wb") as fh:
            df.to_parquet(fh, index=False)
    for f, rows in objects.groupby("file"):
        fs.pipe(f"{root}/{f}", clips_table_bytes(rows))
    report = run_gates(root, data_docs=False)
    assert _failed(report) == {"object.no_nonfinite_visible", "object.visible_inside_image"}
    saved = json.loads(fs.cat(f"{root}/validation/gates.json"))
    assert saved["success"] is False and fs.exists(f"{root}/validation/report.html")
    fs.rm("memory://gates-test", recursive=True)


def test_refinement_fallbacks_beyond_tolerance_fail_the_refine_gate(tmp_path):
    """Objects whose pose refinement was untrustworthy are counted; beyond 5% the gate fails
    and names them. Without refine columns (refinement off) the gate is not built at all."""
    objects, segments, rejections = good_tables(seed=3)
    objects = objects.copy()
    objects["refine_reason"] = "refined"
    objects.loc[objects.index[:2], "refine_reason"] = "too_few_points"          # normal outcome
    bad = objects.index[-3:]
    objects.loc[bad, "refine_reason"] = "large_residual"
    for column in ("refine_residual_label_m", "refine_residual_m", "refine_translation_max_m"):
        objects[column] = 0.01
    root = write_output(tmp_path / "out", objects, segments, rejections)
    report = run_gates(str(root), data_docs=False)
    failed = {f.gate: f for f in report.failures}
    assert "object.refine_trusted" in failed, sorted(failed)
    named = json.dumps(report.to_dict())
    assert all(str(objects.loc[i, "object_id"]) in named for i in bad)

    plain = write_output(tmp_path / "plain", *good_tables(seed=3))
    assert "object.refine_trusted" not in {r.gate for r in run_gates(str(plain), data_docs=False).results}


def test_refined_poses_less_consistent_than_labels_block(reports):
    """Speed consistency is checked for the refined poses and against the labels' own."""
    _, good = reports["good"]
    assert "object.refine_speed_err_not_worse" in {r.gate for r in good.results}
    _, report = reports["refine_worse"]
    assert not report.success
    assert _failed(report) == {"object.refine_speed_err_not_worse"}, _failed(report)
    failure = _failure(report, "object.refine_speed_err_not_worse")
    assert _objects(failure) == {tuple(k) for k in REFINE_WORSE}
    row = failure.failing[0]
    assert row["speed_err_p50"] > row["label_speed_err_p50"] + 0.25   # the context columns are shown


def test_older_tables_without_label_columns_skip_the_refinement_gate(tmp_path):
    objects, segments, rejections = good_tables()
    objects = objects.drop(columns=[c for c in objects.columns if c.startswith("label_")])
    report = run_gates(str(write_output(tmp_path, objects, segments, rejections)), data_docs=False)
    assert report.success
    assert "object.refine_speed_err_not_worse" not in {r.gate for r in report.results}


def test_clips_with_mostly_ambiguous_occlusion_fail_the_ambiguity_gate(tmp_path):
    """A clip whose occlusion decisions were mostly close to flipping (issue 15) is named by
    object.ambiguous_occlusion; tables without the column (older outputs) skip the gate."""
    objects, segments, rejections = good_tables(seed=4)
    objects = objects.copy()
    cells = objects["num_tracks"] * objects["num_frames"]
    objects["num_ambiguous_occlusion"] = (0.02 * cells).astype(int)
    objects.loc[objects.index[0], "num_ambiguous_occlusion"] = int(0.35 * cells.iloc[0])   # a car just ahead
    bad = objects.index[-2:]
    objects.loc[bad, "num_ambiguous_occlusion"] = (0.6 * cells[bad]).astype(int)
    objects["ambiguous_occlusion_fraction"] = objects["num_ambiguous_occlusion"] / cells
    report = run_gates(str(write_output(tmp_path / "out", objects, segments, rejections)), data_docs=False)
    assert _failed(report) == {"object.ambiguous_occlusion"}, _failed(report)
    assert _objects(_failure(report, "object.ambiguous_occlusion")) == {
        tuple(objects.loc[i, ["segment", "camera", "object_id"]]) for i in bad}

    plain = good_tables(seed=4)[0].drop(columns=["num_ambiguous_occlusion", "ambiguous_occlusion_fraction"],
                                        errors="ignore")
    report = run_gates(str(write_output(tmp_path / "plain", plain, segments, rejections)), data_docs=False)
    assert report.success and "object.ambiguous_occlusion" not in {r.gate for r in report.results}
