"""The gates as data: one :class:`GateSpec` per Great Expectations expectation, built from the config.

A spec names its gate (stable id such as ``object.speed_err_p50_max``), its level (object, segment,
release), the table it validates, the GX expectation class and its arguments, and the reason from
``infra/gates.yaml``. Nothing here imports Great Expectations: :mod:`drivetrack.gates.run` turns
specs into expectations. A new gate is a new entry in one of the ``*_specs`` builders.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from drivetrack.gates.config import PERCENTILES, gate_reason, gate_value
from drivetrack.gates.tables import (OBJECT_KEYS, REACHED_PREFIX, REFINE_SPEED_ERR_INCREASE, REJECTED_PREFIX,
                                     SEGMENT_KEYS, SHARE_PREFIX, SPEED_ERR_COLUMNS, SPLIT_KEYS, GateTables)
from drivetrack.refine.config import RefineReason

LEVELS = ("object", "segment", "release")


#: Outcomes of the pose refinement (drivetrack.refine) that are not a sign of trouble (plain str values).
TRUSTED_REFINE_OUTCOMES = tuple(reason.value for reason in (RefineReason.REFINED, RefineReason.LABELS_CONSISTENT,
                                                            RefineReason.STATIC, RefineReason.TOO_FEW_POINTS,
                                                            RefineReason.DISABLED))


@dataclass(frozen=True)
class GateSpec:
    """One gate = one expectation on one table.

    ``table`` is ``objects``, ``segments`` or ``splits``; ``expectation`` a class name of
    ``great_expectations.expectations``; ``kwargs`` its arguments (plain Python values).
    """

    gate: str
    level: str
    table: str
    expectation: str
    kwargs: dict[str, Any]
    reason: str
    keys: tuple[str, ...] = field(default=())
    context: tuple[str, ...] = field(default=())  # extra columns shown for failing rows

    @property
    def suite(self) -> str:
        """GX suite name: one suite per (level, table)."""
        return f"drivetrack_{self.level}_{self.table}"


def object_specs(cfg: dict, tables: GateTables) -> list[GateSpec]:
    v = lambda key: gate_value(cfg, "object", key)  # noqa: E731
    r = lambda key: gate_reason(cfg, "object", key)  # noqa: E731
    keys = OBJECT_KEYS
    specs = [
        GateSpec("object.keys_unique", "object", "objects", "ExpectCompoundColumnsToBeUnique",
                 {"column_list": list(keys)},
                 "Each (split, segment, camera, object_id) clip appears once in objects.parquet.",
                 keys),
        GateSpec("object.speed_err_finite", "object", "objects", "ExpectColumnValuesToBeBetween",
                 {"column": "speed_err_num_nonfinite", "min_value": 0, "max_value": 0},
                 "Every speed-error percentile (speed_err_p25..p99) of an object is a finite "
                 "number; NaN or infinity means the consistency check failed for the object.",
                 keys, SPEED_ERR_COLUMNS),
    ]
    for p in ("p50", "p95"):
        specs.append(GateSpec(
            f"object.speed_err_{p}_max", "object", "objects", "ExpectColumnValuesToBeBetween",
            {"column": f"speed_err_{p}", "min_value": 0.0, "max_value": float(v(f"speed_err_{p}_max_mps")),
             "mostly": float(v("speed_err_mostly"))},
            r(f"speed_err_{p}_max_mps") + " | mostly: " + r("speed_err_mostly"), keys,
            ("num_tracks", "box_speed_mean_mps")))
    for lo, hi in zip(PERCENTILES[:-1], PERCENTILES[1:]):
        specs.append(GateSpec(
            f"object.speed_err_ordered.{hi}_ge_{lo}", "object", "objects",
            "ExpectColumnPairValuesAToBeGreaterThanB",
            {"column_A": f"speed_err_{hi}", "column_B": f"speed_err_{lo}", "or_equal": True,
             "ignore_row_if": "either_value_is_missing"},
            "Percentiles of one object are non-decreasing; a violation means a corrupted "
            "statistics row.", keys))
    for col in ("num_tracks", "num_frames", "visible_fraction", "min_camera_distance_m",
                "num_nonfinite_visible", "num_visible_outside_image"):
        specs.append(GateSpec(f"object.not_null.{col}", "object", "objects",
                              "ExpectColumnValuesToNotBeNull", {"column": col},
                              f"Every object row states {col}.", keys))
    specs += [
        GateSpec("object.min_num_tracks", "object", "objects", "ExpectColumnValuesToBeBetween",
                 {"column": "num_tracks", "min_value": v("min_num_tracks")}, r("min_num_tracks"), keys),
        GateSpec("object.visible_fraction", "object", "objects", "ExpectColumnValuesToBeBetween",
                 {"column": "visible_fraction", "min_value": float(v("visible_fraction_min")),
                  "max_value": float(v("visible_fraction_max"))},
                 r("visible_fraction_min") + " | " + r("visible_fraction_max"), keys),
        GateSpec("object.no_nonfinite_visible", "object", "objects", "ExpectColumnValuesToBeBetween",
                 {"column": "num_nonfinite_visible", "min_value": 0,
                  "max_value": v("max_nonfinite_visible")}, r("max_nonfinite_visible"), keys),
        GateSpec("object.visible_inside_image", "object", "objects", "ExpectColumnValuesToBeBetween",
                 {"column": "num_visible_outside_image", "min_value": 0,
                  "max_value": v("max_visible_outside_image")}, r("max_visible_outside_image"), keys),
        GateSpec("object.min_num_frames", "object", "objects", "ExpectColumnValuesToBeBetween",
                 {"column": "num_frames", "min_value": v("min_num_frames")}, r("min_num_frames"), keys),
        GateSpec("object.max_min_camera_distance", "object", "objects",
                 "ExpectColumnValuesToBeBetween",
                 {"column": "min_camera_distance_m", "min_value": 0.0,
                  "max_value": float(v("max_min_camera_distance_m"))},
                 r("max_min_camera_distance_m"), keys),
    ]
    if "refine_reason" in tables.objects.columns:
        specs.append(GateSpec(
            "object.refine_trusted", "object", "objects", "ExpectColumnValuesToBeInSet",
            {"column": "refine_reason", "value_set": list(TRUSTED_REFINE_OUTCOMES),
             "mostly": float(v("refine_trusted_mostly"))},
            r("refine_trusted_mostly"), keys, ("refine_residual_label_m", "refine_residual_m",
                                               "refine_translation_max_m")))
    if REFINE_SPEED_ERR_INCREASE in tables.objects.columns:
        specs.append(GateSpec(
            "object.refine_speed_err_not_worse", "object", "objects", "ExpectColumnValuesToBeBetween",
            {"column": REFINE_SPEED_ERR_INCREASE, "max_value": float(v("refine_speed_err_increase_max_mps")),
             "mostly": float(v("speed_err_mostly"))},
            r("refine_speed_err_increase_max_mps") + " | mostly: " + r("speed_err_mostly"), keys,
            ("speed_err_p50", "label_speed_err_p50", "refine_reason")))
    if "ambiguous_occlusion_fraction" in tables.objects.columns:
        specs.append(GateSpec(
            "object.ambiguous_occlusion", "object", "objects", "ExpectColumnValuesToBeBetween",
            {"column": "ambiguous_occlusion_fraction", "min_value": 0.0,
             "max_value": float(v("ambiguous_occlusion_fraction_max"))},
            r("ambiguous_occlusion_fraction_max"), keys, ("num_ambiguous_occlusion", "num_tracks", "num_frames")))
    if v("require_files"):
        specs.append(GateSpec("object.file_exists", "object", "objects", "ExpectColumnValuesToBeInSet",
                              {"column": "file_exists", "value_set": [True]}, r("require_files"), keys))
    return specs


def segment_specs(cfg: dict, tables: GateTables) -> list[GateSpec]:
    v = lambda key: gate_value(cfg, "segment", key)  # noqa: E731
    r = lambda key: gate_reason(cfg, "segment", key)  # noqa: E731
    keys = SEGMENT_KEYS
    specs = [
        GateSpec("segment.keys_unique", "segment", "segments", "ExpectColumnValuesToBeUnique",
                 {"column": "segment"}, "Each segment appears once in segments.parquet.", keys),
        GateSpec("segment.status", "segment", "segments", "ExpectColumnValuesToBeInSet",
                 {"column": "status", "value_set": list(v("allowed_status"))}, r("allowed_status"), keys),
        GateSpec("segment.min_object_clips_annotated", "segment", "segments",
                 "ExpectColumnValuesToBeBetween",
                 {"column": "num_object_clips_annotated", "min_value": v("min_object_clips_annotated")},
                 r("min_object_clips_annotated"), keys),
        GateSpec("segment.objects_table_agrees", "segment", "segments",
                 "ExpectColumnPairValuesToBeEqual",
                 {"column_A": "num_object_clips_annotated", "column_B": "num_object_rows"},
                 "num_object_clips_annotated equals the rows of objects.parquet for the segment.",
                 keys),
    ]
    shares = v("rejected_share_max")
    for reason in tables.rejection_reasons:
        bound = float(shares.get(reason, shares["default"]))
        specs.append(GateSpec(
            f"segment.rejected_share.{reason}", "segment", "segments", "ExpectColumnValuesToBeBetween",
            {"column": SHARE_PREFIX + reason, "min_value": 0.0, "max_value": bound},
            f"Filter '{reason}' ({REJECTED_PREFIX}{reason}): " + r("rejected_share_max")
            + " | " + r("rejected_share_min_considered"), keys,
            (REJECTED_PREFIX + reason, REACHED_PREFIX + reason)))
    if v("check_rejections_table"):
        specs.append(GateSpec(
            "segment.rejections_table_agrees", "segment", "segments", "ExpectColumnValuesToBeBetween",
            {"column": "rejections_mismatch", "min_value": 0, "max_value": 0},
            r("check_rejections_table"), keys,
            tuple(REJECTED_PREFIX + x for x in tables.rejection_reasons)))
    return specs


def release_specs(cfg: dict, tables: GateTables) -> list[GateSpec]:
    v = lambda key: gate_value(cfg, "release", key)  # noqa: E731
    r = lambda key: gate_reason(cfg, "release", key)  # noqa: E731
    paper = cfg["paper_speed_err_median_mps"]
    margin = float(v("speed_err_median_margin"))
    specs = []
    for p in PERCENTILES:
        specs.append(GateSpec(
            f"release.speed_err_median.{p}", "release", "objects", "ExpectColumnMedianToBeBetween",
            {"column": f"speed_err_{p}", "min_value": float(v("speed_err_median_min_mps")),
             "max_value": round(margin * float(paper[p]), 6)},
            f"Median over objects of speed_err_{p} <= {margin} x paper {paper[p]} m/s. "
            + r("speed_err_median_margin"), OBJECT_KEYS))
    specs += [
        GateSpec("release.min_total_tracks", "release", "objects", "ExpectColumnSumToBeBetween",
                 {"column": "num_tracks", "min_value": v("min_total_tracks")}, r("min_total_tracks"),
                 OBJECT_KEYS),
        GateSpec("release.split_min_objects", "release", "splits", "ExpectColumnValuesToBeBetween",
                 {"column": "num_object_clips", "min_value": v("min_objects_per_split")},
                 r("min_objects_per_split"), SPLIT_KEYS),
        GateSpec("release.split_min_tracks", "release", "splits", "ExpectColumnValuesToBeBetween",
                 {"column": "num_tracks", "min_value": v("min_tracks_per_split")},
                 r("min_tracks_per_split"), SPLIT_KEYS),
    ]
    if v("required_splits"):
        specs.append(GateSpec("release.required_splits", "release", "splits",
                              "ExpectColumnDistinctValuesToContainSet",
                              {"column": "split", "value_set": list(v("required_splits"))},
                              r("required_splits"), SPLIT_KEYS))
    if v("check_split_files"):
        specs.append(GateSpec("release.split_files_agree", "release", "splits",
                              "ExpectColumnPairValuesToBeEqual",
                              {"column_A": "num_object_clips", "column_B": "num_clips_on_disk"},
                              r("check_split_files"), SPLIT_KEYS))
    return specs


#: Registry of spec builders, one per level (a new level is a new entry).
SPEC_BUILDERS = {"object": object_specs, "segment": segment_specs, "release": release_specs}


def build_specs(cfg: dict, tables: GateTables) -> list[GateSpec]:
    """All gates for this configuration and these tables, in report order."""
    specs = [s for level in LEVELS for s in SPEC_BUILDERS[level](cfg, tables)]
    names = [s.gate for s in specs]
    dupes = {n for n in names if names.count(n) > 1}
    if dupes:
        raise ValueError(f"duplicate gate ids {sorted(dupes)}")
    return specs
