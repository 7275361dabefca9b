"""Release layout v2: the columns of the clips and frames tables, as Arrow schemas and as Hugging
Face ``datasets`` features (file names and paths live in :mod:`drivetrack.outputs`).

``frames/{split}/{segment}_{CAMERA}.parquet`` (:data:`FRAMES_SCHEMA`), one row per frame that a
clip of the camera uses, sorted by ``frame``; each frame once, however many clips use it:

    segment, camera          string
    frame                    int32, the frame's index in the segment (what clips refer to)
    timestamp_micros         int64, the camera image's timestamp
    image                    struct {bytes: binary, path: string}: the source JPEG bytes exactly as
                             Waymo stored them (never decoded and re-encoded); ``path`` is null.
                             Declared as the ``datasets`` ``Image`` feature.

``clips/{split}/{segment}.parquet`` (:data:`CLIPS_SCHEMA`), one row and one row group per clip
(N tracks, T frames; the lists are flat, row-major, in the shapes given):

    clip                     string, ``waymo_{segment}_{CAMERA}_{object_id}`` (the npz file stem)
    split, segment, camera, object_id, object_type   string
    num_tracks, num_frames   int32 (N, T)
    frames                   int32 [T], frame indices into the frames table of (segment, camera)
    timestamps_micros        int64 [T]
    tracks                   float32 [N, T, 2], pixels (x, y), pixel i covers [i, i+1)
    visibles                 bool [N, T]
    query_frames             int32 [N], clip frame of the LiDAR return that produced the track
    lidar_sources            int32 [N, 4], (laser_name, return 1|2, range-image row, col)
    points_box               float64 [N, 3], metres: each track's point in its box's frame
    vehicle_from_box         float64 [T, 4, 4]: the box pose in each frame's vehicle frame; with
                             ``points_box`` it gives ``points3d`` float32 [N, T, 3] (metres,
                             vehicle frame of each frame) = float32(R_t p + t_t), exactly the
                             values the npz writers store (:func:`drivetrack.compact.read.points3d_from_box`)
    query_pixels             float32 [N, 2], the TAPVid-3D query pixel of each track
    width, height            int32, image size in pixels
    intrinsics               float64 [9], f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3 (Waymo's
                             pinhole + Brown-Conrady model)
    camera_from_vehicle      float64 [T, 4, 4], Waymo camera frame from each frame's vehicle frame
    world_from_vehicle       float64 [T, 4, 4]
    occlusion_margin         float32 [N, T] or empty: each decision's distance from flipping,
                             signed (>= 0 visible), in units of the ambiguity thresholds; NaN
                             outside the image (docs/visibility.md). Written only by runs with
                             ``TrackConfig.occlusion_margins`` (an empty list otherwise); tables
                             written before the column existed lack it and read as empty
                             (:data:`OPTIONAL_COLUMNS`).

Float lists are written with Parquet's BYTE_STREAM_SPLIT encoding and zstd.
"""
from __future__ import annotations

import pyarrow as pa

__all__ = ["FRAMES_SCHEMA", "CLIPS_SCHEMA", "OPTIONAL_COLUMNS", "FLOAT_COLUMNS", "INTRINSICS", "CLIPS_FEATURES", "FRAMES_FEATURES",
           "COLUMN_DESCRIPTIONS", "ZSTD_LEVEL", "parquet_options"]

#: The ``intrinsics`` list, in order (attributes of :class:`drivetrack.camera.model.CameraModel`).
INTRINSICS = ("f_u", "f_v", "c_u", "c_v", "k1", "k2", "p1", "p2", "k3")

_IMAGE = pa.struct([("bytes", pa.binary()), ("path", pa.string())])

FRAMES_SCHEMA = pa.schema([
    ("segment", pa.string()), ("camera", pa.string()), ("frame", pa.int32()),
    ("timestamp_micros", pa.int64()), ("image", _IMAGE),
])

CLIPS_SCHEMA = pa.schema([
    ("clip", pa.string()), ("split", pa.string()), ("segment", pa.string()), ("camera", pa.string()),
    ("object_id", pa.string()), ("object_type", pa.string()),
    ("num_tracks", pa.int32()), ("num_frames", pa.int32()),
    ("frames", pa.list_(pa.int32())), ("timestamps_micros", pa.list_(pa.int64())),
    ("tracks", pa.list_(pa.float32())), ("visibles", pa.list_(pa.bool_())),
    ("query_frames", pa.list_(pa.int32())), ("lidar_sources", pa.list_(pa.int32())),
    ("points_box", pa.list_(pa.float64())), ("vehicle_from_box", pa.list_(pa.float64())),
    ("query_pixels", pa.list_(pa.float32())),
    ("width", pa.int32()), ("height", pa.int32()), ("intrinsics", pa.list_(pa.float64())),
    ("camera_from_vehicle", pa.list_(pa.float64())), ("world_from_vehicle", pa.list_(pa.float64())),
    ("occlusion_margin", pa.list_(pa.float32())),
])

#: Columns of :data:`CLIPS_SCHEMA` a table may lack (added after layout v2's first releases; a
#: missing one reads as empty).
OPTIONAL_COLUMNS = ("occlusion_margin",)

#: Float list columns (BYTE_STREAM_SPLIT encoded).
FLOAT_COLUMNS = tuple(f.name for f in CLIPS_SCHEMA if pa.types.is_list(f.type)
                      and pa.types.is_floating(f.type.value_type))

ZSTD_LEVEL = 3


def parquet_options(schema: pa.Schema) -> dict:
    """``pyarrow.parquet.ParquetWriter`` keyword arguments of a v2 table: zstd, BYTE_STREAM_SPLIT for
    float lists (Parquet names their leaf ``{column}.list.element``), dictionaries for strings only."""
    floats = [f"{f.name}.list.element" for f in schema if pa.types.is_list(f.type)
              and pa.types.is_floating(f.type.value_type)]
    strings = [f.name for f in schema if pa.types.is_string(f.type)]
    return {"compression": "zstd", "compression_level": ZSTD_LEVEL, "use_dictionary": strings,
            "use_byte_stream_split": floats or False, "write_statistics": False}


def _feature(t: pa.DataType):
    """The ``dataset_info`` YAML feature of an Arrow type (``datasets`` 4/5 spelling)."""
    if pa.types.is_list(t):
        return {"list": _feature(t.value_type)}
    names = {pa.string(): "string", pa.int32(): "int32", pa.int64(): "int64", pa.float32(): "float32",
             pa.float64(): "float64", pa.bool_(): "bool", pa.binary(): "binary"}
    return names[t]


def _features(schema: pa.Schema) -> list[dict]:
    out = []
    for f in schema:
        if f.type == _IMAGE:
            out.append({"name": f.name, "dtype": "image"})
            continue
        feature = _feature(f.type)
        out.append({"name": f.name, **(feature if isinstance(feature, dict) else {"dtype": feature})})
    return out


#: ``dataset_info.features`` of the ``clips`` and ``frames`` configs of the dataset card.
CLIPS_FEATURES = _features(CLIPS_SCHEMA)
FRAMES_FEATURES = _features(FRAMES_SCHEMA)

#: Column -> one-line description (the Croissant fields and docs/formats.md say the same).
COLUMN_DESCRIPTIONS = {
    "clip": "Clip id waymo_{segment}_{CAMERA}_{object_id} (the stem of the exported npz files).",
    "split": "Waymo split of the segment.",
    "segment": "Waymo segment (context name).",
    "camera": "Waymo camera name (FRONT, FRONT_LEFT, ...).",
    "object_id": "Waymo object id of the tracked object.",
    "object_type": "Waymo box type of the object (VEHICLE, PEDESTRIAN, ...).",
    "num_tracks": "N, the number of point tracks of the clip.",
    "num_frames": "T, the number of frames of the clip.",
    "frames": "int32 [T]: each clip frame's index in the segment (the frame column of the frames table).",
    "timestamps_micros": "int64 [T]: camera image timestamps, microseconds.",
    "tracks": "float32 [N, T, 2] flattened: pixel (x, y) of each track in each frame; pixel i covers [i, i+1).",
    "visibles": "bool [N, T] flattened: the point is visible (not occluded, inside the image).",
    "query_frames": "int32 [N]: clip frame of the LiDAR return that produced each track.",
    "lidar_sources": "int32 [N, 4] flattened: (laser_name, return 1|2, range-image row, col) of each track's return.",
    "points_box": "float64 [N, 3] flattened: each track's point in its box's frame, metres.",
    "vehicle_from_box": "float64 [T, 4, 4] flattened: box pose in each frame's vehicle frame; points3d = R p + t.",
    "query_pixels": "float32 [N, 2] flattened: TAPVid-3D query pixel of each track.",
    "width": "Image width, pixels.",
    "height": "Image height, pixels.",
    "intrinsics": "float64 [9]: f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3 (pinhole + Brown-Conrady).",
    "camera_from_vehicle": "float64 [T, 4, 4] flattened: Waymo camera frame from each frame's vehicle frame.",
    "world_from_vehicle": "float64 [T, 4, 4] flattened: world frame from each frame's vehicle frame.",
    "occlusion_margin": ("float32 [N, T] flattened, or empty when the run did not keep it: each visibility "
                         "decision's signed distance from flipping (>= 0 visible) in units of the ambiguity "
                         "thresholds (0.1 m of depth, 5 degrees of normal); NaN outside the image."),
    "frame": "Index of the frame in the segment.",
    "timestamp_micros": "Camera image timestamp, microseconds.",
    "image": "The camera image: the source JPEG bytes exactly as Waymo stored them.",
}
