"""Gate configuration, statistics-table reading and report rendering (no Great Expectations run)."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from drivetrack.gates import GateConfigError, GateInputError, card_summary, load_gate_config
from drivetrack.gates.report import GateReport, GateResult, plain, report_html
from drivetrack.gates.suites import build_specs
from drivetrack.gates.tables import read_gate_tables
from test_gates_fixtures import PAPER, clips_table_bytes, good_tables, make_output, write_output


def test_defaults_have_values_and_reasons():
    cfg = load_gate_config()
    for section in ("object", "segment", "release"):
        for key, entry in cfg[section].items():
            assert entry["reason"].strip(), f"{section}.{key} has no reason"
    paper = cfg["paper_speed_err_median_mps"]
    assert [paper[p] for p in ("p25", "p50", "p75", "p95", "p99")] == PAPER.tolist()
    # per-object bounds are looser than the release bounds (margin x paper)
    margin = cfg["release"]["speed_err_median_margin"]["value"]
    assert cfg["object"]["speed_err_p50_max_mps"]["value"] > margin * paper["p50"]
    assert cfg["object"]["speed_err_p95_max_mps"]["value"] > margin * paper["p95"]


def test_override_plain_value_keeps_reason_and_dict_replaces_it(tmp_path):
    cfg = load_gate_config({"segment": {"rejected_share_max": {"no_points": 0.5}},
                            "object": {"min_num_tracks": 5,
                                       "max_visible_outside_image": {"value": 2, "reason": "test"}}})
    assert cfg["object"]["min_num_tracks"]["value"] == 5
    shares = cfg["segment"]["rejected_share_max"]["value"]
    assert shares["no_points"] == 0.5 and shares["default"] == 0.9  # merged by name
    assert "overridden by dict" in cfg["object"]["min_num_tracks"]["reason"]
    assert cfg["object"]["max_visible_outside_image"] == {"value": 2, "reason": "test"}
    f = tmp_path / "g.yaml"
    f.write_text("release:\n  required_splits: [training, validation]\n")
    cfg = load_gate_config(str(f))
    assert cfg["release"]["required_splits"]["value"] == ["training", "validation"]
    assert cfg["source"]["override"] == str(f)


@pytest.mark.parametrize("override, words", [
    ({"objects": {}}, ["unknown section 'objects'"]),
    ({"object": {"min_num_trax": 3}}, ["unknown gate 'object.min_num_trax'", "min_num_tracks"]),
    ({"object": {"speed_err_mostly": 1.5}}, ["object.speed_err_mostly", "1.5"]),
    ({"object": {"require_files": "yes"}}, ["object.require_files", "'yes'"]),
    ({"segment": {"rejected_share_max": {"no_points": 1.5}}}, ["rejected_share_max.no_points", "1.5"]),
    ({"segment": {"rejected_share_max": {"default": None}}}, ["rejected_share_max.default", "None"]),
    ({"release": {"required_splits": "training"}}, ["release.required_splits", "list of strings"]),
    ({"version": 2}, ["version 2"]),
])
def test_bad_config_names_key_and_value(override, words):
    with pytest.raises(GateConfigError) as err:
        load_gate_config(override)
    for w in words:
        assert w in str(err.value)


def test_missing_config_file_is_named(tmp_path):
    with pytest.raises(GateConfigError, match="nope.yaml does not exist"):
        load_gate_config(str(tmp_path / "nope.yaml"))


def test_missing_table_and_column_are_named(tmp_path):
    with pytest.raises(GateInputError, match="does not exist"):
        read_gate_tables(str(tmp_path / "absent"), load_gate_config())
    objects, segments, rejections = good_tables()
    write_output(tmp_path, objects.drop(columns=["num_visible_outside_image"]), segments, rejections)
    with pytest.raises(GateInputError) as err:
        read_gate_tables(str(tmp_path), load_gate_config())
    assert "objects.parquet" in str(err.value) and "num_visible_outside_image" in str(err.value)
    (tmp_path / "stats" / "segments.parquet").unlink()
    write_output(tmp_path, objects, segments.iloc[:0].drop(columns=["status"]), rejections)
    with pytest.raises(GateInputError, match=r"segments\.parquet lacks column\(s\) \['status'\]"):
        read_gate_tables(str(tmp_path), load_gate_config())
    (tmp_path / "stats" / "rejections.parquet").unlink()
    write_output(tmp_path, objects, segments, rejections)
    (tmp_path / "stats" / "rejections.parquet").unlink()
    with pytest.raises(GateInputError, match=r"rejections\.parquet does not exist"):
        read_gate_tables(str(tmp_path), load_gate_config())
    # without the cross-check the rejections table is optional
    cfg = load_gate_config({"segment": {"check_rejections_table": False}})
    assert "rejections_mismatch" not in read_gate_tables(str(tmp_path), cfg).segments


def test_derived_columns(tmp_path):
    objects, segments, rejections = good_tables()
    objects.loc[0, "speed_err_p50"] = np.nan
    objects.loc[1, "speed_err_p99"] = -np.inf
    objects.loc[2, "file"] = str(tmp_path / objects.loc[2, "file"])  # absolute path form
    objects.loc[5, "file"] = (tmp_path / objects.loc[5, "file"]).as_uri()  # URL form
    segments.loc[0, ["num_object_clips_considered", "rejected_camera", "rejected_too_few_frames",
                     "rejected_no_visible_points"]] = [40, 10, 5, 20]
    segments["rejected_zz_custom"] = 0  # a reason the track stage does not know: judged last
    write_output(tmp_path, objects, segments, rejections)
    row = objects.loc[3]  # its clip is not in its clips table
    table = objects[objects["segment"] == row["segment"]]
    (tmp_path / row["file"]).write_bytes(clips_table_bytes(table, drop=(row["segment"], row["camera"], row["object_id"])))
    t = read_gate_tables(str(tmp_path), load_gate_config())
    assert t.objects["speed_err_num_nonfinite"].tolist()[:3] == [1, 1, 0]
    assert t.objects["file_exists"].tolist()[:6] == [True, True, True, False, True, True]
    # filters in the track stage's order; each rate is over the clips that reached the filter
    assert t.rejection_reasons == ["camera", "too_few_frames", "no_visible_points", "zz_custom"]
    row = t.segments.iloc[0]
    assert [row[f"reached_{r}"] for r in t.rejection_reasons] == [40, 30, 25, 5]
    assert row["rejected_share_camera"] == pytest.approx(0.25)
    assert row["rejected_share_too_few_frames"] == pytest.approx(5 / 30)
    assert row["rejected_share_no_visible_points"] == pytest.approx(0.8)
    assert np.isnan(row["rejected_share_zz_custom"])  # 5 clips reached it: fewer than 10
    for r in t.rejection_reasons:
        judged = t.segments[f"reached_{r}"] >= 10
        assert (t.segments[f"rejected_share_{r}"].notna() == judged).all()
    seg0 = rejections["segment"] == segments.loc[0, "segment"]
    expected = sum(abs(segments.loc[0, f"rejected_{r}"] - (seg0 & (rejections["reason"] == r)).sum())
                   for r in ("camera", "too_few_frames", "no_visible_points"))
    assert t.segments["rejections_mismatch"].iloc[0] == expected > 0
    assert (t.segments["rejections_mismatch"].iloc[1:] == 0).all()
    assert t.splits.set_index("split")["num_clips_on_disk"].to_dict() == {"training": 5, "validation": 6}
    assert t.splits["num_tracks"].sum() == objects["num_tracks"].sum()


def test_release_bounds_are_margin_times_paper(tmp_path):
    make_output(tmp_path)
    cfg = load_gate_config({"release": {"speed_err_median_margin": 1.5}})
    specs = {s.gate: s for s in build_specs(cfg, read_gate_tables(str(tmp_path), cfg))}
    for p, paper in zip(("p25", "p50", "p75", "p95", "p99"), PAPER):
        assert specs[f"release.speed_err_median.{p}"].kwargs["max_value"] == pytest.approx(1.5 * paper)
    assert {"segment.rejected_share.camera", "segment.rejected_share.no_visible_points"} <= set(specs)
    assert specs["segment.rejected_share.camera"].kwargs["max_value"] == 1.0
    assert specs["segment.rejected_share.no_visible_points"].kwargs["max_value"] == 0.9


def test_importing_gates_and_cli_does_not_import_great_expectations():
    code = ("import sys, drivetrack.gates, drivetrack.commands.gates, drivetrack.cli;"
            "drivetrack.cli.build_parser();"
            "assert 'great_expectations' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_plain_makes_numpy_and_nonfinite_json_safe():
    value = {"a": np.bool_(True), "b": np.float32(1.5), "c": [np.nan, np.inf, -np.inf],
             "d": np.arange(2), "e": (np.int64(3),)}
    out = plain(value)
    assert out == {"a": True, "b": 1.5, "c": ["NaN", "Infinity", "-Infinity"], "d": [0, 1], "e": [3]}
    assert type(out["a"]) is bool
    json.dumps(out, allow_nan=False)


def _report(success: bool) -> GateReport:
    failing = [{"segment": "s<1>", "camera": "FRONT", "object_id": "7", "speed_err_p50": 3.0}]
    results = [
        GateResult("object.speed_err_p50_max", "object", "objects", "ExpectColumnValuesToBeBetween",
                   ["speed_err_p50"], success, "1 of 3 rows outside", {"min_value": 0.0, "max_value": 0.75},
                   "why", 3, 0 if success else 1, [] if success else failing),
        GateResult("release.speed_err_median.p50", "release", "objects", "ExpectColumnMedianToBeBetween",
                   ["speed_err_p50"], True, 0.13, {"min_value": 0.0, "max_value": 0.252}, "why"),
    ]
    cfg = load_gate_config()
    return GateReport(success, "/out", results, cfg, "ab" * 32, "1.x", "2026-01-01T00:00:00Z", {})


def test_card_summary_and_html_from_report_or_dict():
    bad = _report(False)
    text = card_summary(bad.to_dict(), accepted_reason="known door artefacts")
    assert "FAILED" in text and "object.speed_err_p50_max" in text
    assert "s<1>/FRONT/7" in text and "known door artefacts" in text
    assert "| p50 | 0.13 | <= 0.252 | 0.126 |" in text
    good = card_summary(_report(True))
    assert "passed" in good and "Failed gates" not in good
    page = report_html(bad)
    assert "s&lt;1&gt;" in page and "http" not in page.split("</style>")[0]
    assert "<script" not in page and "<link" not in page
