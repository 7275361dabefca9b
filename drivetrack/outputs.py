"""The output contract: where clip files live, what they are called, and how their names parse.

One place that knows the file names, locations, table columns and categorical values of an
annotation output folder or a release; writers, gates, manifests and readers import them from here.
Release layout v2 (the tables :mod:`drivetrack.compact` writes and reads):

    clips/{split}/{segment}.parquet                 one row (and one row group) per clip
    frames/{split}/{segment}_{CAMERA}.parquet       one row per frame: the source JPEG, stored once

Exported clip files (``drivetrack export``; published only with the release option ``publish_npz``):

    tracks/{split}/waymo_{segment}_{CAMERA}_{object_id}.npz     DriveTrack-compatible clips
    tapvid3d/{split}/waymo_{segment}_{CAMERA}_{object_id}.npz   the same clips, TAPVid-3D layout

Split folders sit under a layout folder because Waymo has a split called ``validation`` and the
top-level ``validation/`` folder holds the gate reports. Paths here are relative, ``/``-separated.

Tables (``stats/{name}.parquet``, docs/formats.md): :data:`OBJECT_COLUMNS` (then the
``label_speed_err_p*`` and ``refine_*`` columns annotate adds), :data:`SEGMENT_COLUMNS`,
:data:`REJECTION_COLUMNS`. Categorical values are ``StrEnum``s whose values are the strings in
the files: :class:`SegmentStatus`, :class:`Stage`, :class:`RejectionReason`.
"""
from __future__ import annotations

import posixpath
import re
from enum import StrEnum
from typing import Iterable

from drivetrack.names import check_name, is_valid_name
from drivetrack.waymo.schema import CameraName

__all__ = ["LAYOUTS", "DRIVETRACK", "TAPVID3D", "CLIP_PREFIX", "CLIP_CAMERAS", "CLIP_NAME", "clip_path",
           "clip_glob", "clip_stem", "parse_clip_path", "parse_clip_name", "is_clip_name", "splits_of", "clips_of",
           "SegmentStatus", "Stage", "RejectionReason", "REJECTION_REASONS", "SPEED_PERCENTILES",
           "SPEED_ERR_COLUMNS", "LABEL_SPEED_ERR_COLUMNS", "OBJECT_COLUMNS", "SEGMENT_COLUMNS", "REJECTION_COLUMNS",
           "TABLES", "CLIPS", "FRAMES", "TABLE_FOLDERS", "clips_table_path", "frames_table_path",
           "parse_table_path", "table_glob", "is_data_file", "data_splits_of"]

DRIVETRACK = "drivetrack"
TAPVID3D = "tapvid3d"
#: layout name -> top-level folder
LAYOUTS = {DRIVETRACK: "tracks", TAPVID3D: "tapvid3d"}
CLIP_PREFIX = "waymo_"
#: Camera names a clip file name can carry (Waymo's enum names), longest first so that
#: ``FRONT_LEFT`` is tried before ``FRONT``.
CLIP_CAMERAS = tuple(sorted((c.name for c in CameraName if c.name != "UNKNOWN"), key=len, reverse=True))
_CAMERA_GROUP = "|".join(CLIP_CAMERAS)
#: A clip stem ``waymo_{segment}_{CAMERA}_{object_id}`` (file name without ``.npz``). The segment is
#: the shortest prefix followed by a camera name; ``object_id`` is everything after it.
CLIP_NAME = re.compile(rf"^{CLIP_PREFIX}(?P<segment>.+?)_(?P<camera>{_CAMERA_GROUP})_(?P<object_id>.+)$")
_CAMERA_OBJECT = re.compile(rf"^(?P<camera>{_CAMERA_GROUP})_(?P<object_id>.+)$")


#: The v2 tables: kind -> top-level folder (``clips/{split}/{segment}.parquet``,
#: ``frames/{split}/{segment}_{CAMERA}.parquet``).
CLIPS = "clips"
FRAMES = "frames"
TABLE_FOLDERS = {CLIPS: "clips", FRAMES: "frames"}
_FRAMES_NAME = re.compile(rf"^(?P<segment>.+)_(?P<camera>{_CAMERA_GROUP})$")


class SegmentStatus(StrEnum):
    """A segment's outcome (``status`` of ``stats/segments.parquet``, ``run.json``, ``SegmentResult``)."""
    RUNNING = "running"        # in memory while the segment runs; never written
    DONE = "done"
    FAILED = "failed"


class Stage(StrEnum):
    """The stage of a segment a failure happened in (``SegmentResult.stage``, the ``[stage]`` prefix of
    the ``error`` column, the keys of ``timings_s``), in pipeline order."""
    INGEST = "ingest"
    REFINE = "refine"
    PLAN = "plan"
    DEPTH = "depth"
    TRACKS = "tracks"
    WRITE = "write"
    WORKER = "worker"          # the worker process died (annotate with workers >= 2)


class RejectionReason(StrEnum):
    """Why a (segment, camera, object) clip was rejected, in the order the filters test them
    (``reason`` of ``stats/rejections.parquet``; ``rejected_{reason}`` columns of segments)."""
    CAMERA = "camera"                        # camera not in TrackConfig.cameras
    OBJECT_TYPE = "object_type"              # type not in TrackConfig.object_types
    NOT_IN_VIEW = "not_in_view"              # never in the camera's view
    LABEL_GAP = "label_gap"                  # in view in several runs separated by frames without a label
    IMAGE_GAP = "image_gap"                  # ... separated by frames without a camera image
    LEFT_AND_RETURNED = "left_and_returned"  # ... the object left the image and came back
    TOO_FEW_FRAMES = "too_few_frames"        # the run is shorter than min_frames
    TOO_FAR = "too_far"                      # never within max_camera_distance_m of the camera during the run
    NO_POINTS = "no_points"                  # no LiDAR return inside the box during the run
    NO_VISIBLE_POINTS = "no_visible_points"  # (track stage) no point visible in any frame after occlusion/filters


#: Every rejection reason, in the order they are tested.
REJECTION_REASONS = tuple(RejectionReason)

#: Percentiles of the per-track speed error written per object.
SPEED_PERCENTILES = (25, 50, 75, 95, 99)
SPEED_ERR_COLUMNS = tuple(f"speed_err_p{p}" for p in SPEED_PERCENTILES)
#: The same percentiles under the labelled poses (annotate adds them after :data:`OBJECT_COLUMNS`).
LABEL_SPEED_ERR_COLUMNS = tuple(f"label_speed_err_p{p}" for p in SPEED_PERCENTILES)

#: ``stats/objects.parquet``: one row per annotated clip, as the track stage writes it.
OBJECT_COLUMNS = (
    "split", "segment", "camera", "object_id", "object_type", "file", "num_tracks", "num_frames",
    "first_frame", "visible_fraction", "min_camera_distance_m", "box_speed_mean_mps",
    *SPEED_ERR_COLUMNS,
    "num_nonfinite_visible", "num_visible_outside_image", "num_candidates",
    "num_dropped_invisible", "num_dropped_speed", "projection",
    "time_model", "label_time", "time_residual_m", "num_unreliable_normals",
    "num_ambiguous_occlusion", "ambiguous_occlusion_fraction",
)
#: ``stats/segments.parquet``: one row per segment.
SEGMENT_COLUMNS = (
    "split", "segment", "status", "error", "num_frames", "num_objects_labelled",
    "num_object_clips_considered", "num_object_clips_annotated", "num_tracks",
    *(f"rejected_{r}" for r in REJECTION_REASONS),
    "label_time", "label_time_residual_frame_m", "label_time_residual_sweep_m", "num_synced_samples",
    "label_jitter_m", "depth_lookup_px",
)
#: ``stats/rejections.parquet``: one row per rejected clip.
REJECTION_COLUMNS = ("split", "segment", "camera", "object_id", "object_type", "reason", "detail")
#: table name -> its columns (``stats/{name}.parquet``).
TABLES = {"objects": OBJECT_COLUMNS, "segments": SEGMENT_COLUMNS, "rejections": REJECTION_COLUMNS}


def clip_path(layout: str, split: str, stem: str) -> str:
    """Relative path of clip ``stem`` (``waymo_{segment}_{CAMERA}_{object_id}``) of ``split``."""
    try:
        folder = LAYOUTS[layout]
    except KeyError:
        raise ValueError(f"unknown clip layout {layout!r}; known: {sorted(LAYOUTS)}") from None
    check_name("split", split, f"clip path of {stem!r}")
    return f"{folder}/{split}/{stem}.npz"


def clip_glob(layout: str, split: str) -> str:
    """Glob of ``layout``'s clip files of ``split`` (e.g. for Hugging Face ``data_files``)."""
    return f"{LAYOUTS[layout]}/{split}/{CLIP_PREFIX}*.npz"


def parse_clip_path(path: str) -> tuple[str, str] | None:
    """``(layout, split)`` of a relative clip path, or None when ``path`` is not a clip file."""
    parts = path.split("/")
    if len(parts) != 3 or not parts[2].startswith(CLIP_PREFIX) or not parts[2].endswith(".npz"):
        return None
    for layout, folder in LAYOUTS.items():
        if parts[0] == folder and parts[1]:
            return layout, parts[1]
    return None


def splits_of(paths, layout: str | None = None) -> list[str]:
    """Sorted splits that have clip files (of ``layout``, or of any layout) among ``paths``."""
    out = set()
    for path in paths:
        parsed = parse_clip_path(path)
        if parsed and (layout is None or parsed[0] == layout):
            out.add(parsed[1])
    return sorted(out)


def clips_of(paths, layout: str, split: str) -> list[str]:
    """Sorted clip paths of ``layout`` and ``split`` among ``paths``."""
    return sorted(p for p in paths if parse_clip_path(p) == (layout, split))


def clip_stem(segment: str, camera: str, object_id: str, where: str | None = None) -> str:
    """``waymo_{segment}_{CAMERA}_{object_id}``, each part checked with :func:`drivetrack.names.check_name`
    (full match) first; an :class:`~drivetrack.names.InvalidNameError` names the part, its value and ``where``."""
    check_name("segment", segment, where)
    check_name("camera", camera, where)
    check_name("object_id", object_id, where)
    return f"{CLIP_PREFIX}{segment}_{camera}_{object_id}"


def parse_clip_name(name: str, segments: Iterable[str] = ()) -> tuple[str, str, str]:
    """``(segment, CAMERA, object_id)`` of a clip file name or path ``waymo_{segment}_{CAMERA}_{object_id}[.npz]``.

    A segment from ``segments`` that prefixes the name wins (segment names could contain a camera
    name); otherwise the first camera name after ``waymo_`` splits the name. ValueError naming
    ``name`` when it is not a clip file name.
    """
    stem = posixpath.basename(str(name))
    stem = stem[:-4] if stem.endswith(".npz") else stem
    for segment in sorted(segments, key=len, reverse=True):
        head = f"{CLIP_PREFIX}{segment}_"
        if stem.startswith(head):
            match = _CAMERA_OBJECT.match(stem[len(head):])
            if match:
                return segment, match["camera"], match["object_id"]
    match = CLIP_NAME.match(stem)
    if not match:
        raise ValueError(f"{name}: not a clip file name waymo_{{segment}}_{{CAMERA}}_{{object_id}}.npz "
                         f"(CAMERA one of {list(CLIP_CAMERAS)})")
    return match["segment"], match["camera"], match["object_id"]


def is_clip_name(name: str, strict_object_id: bool = False) -> bool:
    """True when the base name of ``name`` is a clip file name ``waymo_{segment}_{CAMERA}_{object_id}.npz``.

    ``strict_object_id`` also requires the object id to be a valid ``object_id`` name
    (:mod:`drivetrack.names`), as every writer checks it.
    """
    stem = posixpath.basename(str(name))
    match = CLIP_NAME.match(stem[:-4]) if stem.endswith(".npz") else None
    return bool(match) and (not strict_object_id or is_valid_name("object_id", match["object_id"]))


def clips_table_path(split: str, segment: str) -> str:
    """Relative path of the clips table of ``segment``: ``clips/{split}/{segment}.parquet``."""
    check_name("split", split, f"clips table of segment {segment!r}")
    check_name("segment", segment, "clips table")
    return f"{TABLE_FOLDERS[CLIPS]}/{split}/{segment}.parquet"


def frames_table_path(split: str, segment: str, camera: str) -> str:
    """Relative path of the frames table of ``segment``'s ``camera`` (Waymo enum name):
    ``frames/{split}/{segment}_{CAMERA}.parquet``."""
    where = f"frames table of segment {segment!r}"
    check_name("split", split, where)
    check_name("segment", segment, where)
    check_name("camera", camera, where)
    return f"{TABLE_FOLDERS[FRAMES]}/{split}/{segment}_{camera}.parquet"


def table_glob(kind: str, split: str) -> str:
    """Glob of the ``kind`` (:data:`CLIPS` or :data:`FRAMES`) tables of ``split`` (Hugging Face ``data_files``)."""
    return f"{TABLE_FOLDERS[kind]}/{split}/*.parquet"


def parse_table_path(path: str) -> tuple[str, str, str, str | None] | None:
    """``(kind, split, segment, camera)`` of a relative v2 table path (``camera`` None for a clips
    table), or None when ``path`` is not one."""
    parts = path.split("/")
    if len(parts) != 3 or not parts[1] or not parts[2].endswith(".parquet") or len(parts[2]) <= 8:
        return None
    name = parts[2][:-len(".parquet")]
    if parts[0] == TABLE_FOLDERS[CLIPS]:
        return (CLIPS, parts[1], name, None) if is_valid_name("segment", name) else None
    if parts[0] == TABLE_FOLDERS[FRAMES]:
        match = _FRAMES_NAME.match(name)
        return (FRAMES, parts[1], match["segment"], match["camera"]) if match else None
    return None


def is_data_file(path: str) -> bool:
    """True for a clip data file of an output folder or release: a v2 table
    (:func:`parse_table_path`) or an exported npz clip (:func:`parse_clip_path`)."""
    return bool(parse_table_path(path) or parse_clip_path(path))


def data_splits_of(paths) -> list[str]:
    """Sorted splits that have clips tables (``clips/{split}/*.parquet``) or npz clips among ``paths``."""
    out = set(splits_of(paths))
    for path in paths:
        parsed = parse_table_path(path)
        if parsed and parsed[0] == CLIPS:
            out.add(parsed[1])
    return sorted(out)
