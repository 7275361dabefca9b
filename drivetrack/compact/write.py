"""Write a segment's accepted clips as release layout v2 tables (:mod:`drivetrack.compact.layout`).

One frames table per camera (the JPEG bytes of every frame a clip of that camera uses, once) and
one clips table per segment (one row group per clip). ``tracks`` are computed a chunk of points
at a time by the clip's :class:`drivetrack.tracks.core.TrackSource`, the same values the npz
writers stream; ``points3d`` is stored as its box-frame points and box poses (3 numbers per track
instead of 3 per track and frame) and recomputed exactly on reading. Files are written whole and moved into place
(:func:`drivetrack.storage.atomic_local_path`); frames tables before the clips table that refers
to them.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from drivetrack import faults
from drivetrack.compact.layout import CLIPS_SCHEMA, FRAMES_SCHEMA, INTRINSICS, parquet_options
from drivetrack.outputs import clips_table_path, frames_table_path
from drivetrack.storage import atomic_local_path
from drivetrack.tracks.core import ObjectTracks

__all__ = ["write_segment_tables", "clip_row", "frames_rows"]


def _where(tracks: ObjectTracks) -> str:
    return f"segment {tracks.segment!r} camera {tracks.camera_name} object {tracks.object_id!r}"


def _check_jpeg(tracks: ObjectTracks, i: int, data) -> bytes:
    if data is None or bytes(data[:2]) != b"\xff\xd8" or bytes(data[-2:]) != b"\xff\xd9":
        raise ValueError(f"segment {tracks.segment!r} camera {tracks.camera_name} frame "
                         f"{int(tracks.frames[i])}: image is missing or not a complete JPEG "
                         f"(must start with FFD8 and end with FFD9)")
    return bytes(data)


def frames_rows(clips: list[ObjectTracks]) -> dict:
    """Columns of the frames table of clips of one camera: every frame any of them uses, once,
    sorted by frame index. ValueError when two clips disagree on a frame's timestamp or bytes."""
    frames: dict[int, tuple[int, bytes]] = {}
    for tracks in clips:
        for i, (frame, stamp) in enumerate(zip(tracks.frames.tolist(), tracks.timestamps_micros.tolist())):
            if frame in frames:
                if frames[frame][0] != stamp:
                    raise ValueError(f"{_where(tracks)} frame {frame}: timestamp {stamp} differs from "
                                     f"{frames[frame][0]} of another clip of the camera")
                continue
            frames[frame] = (int(stamp), _check_jpeg(tracks, i, tracks.jpeg[i]))
    order = sorted(frames)
    first = clips[0]
    return {"segment": [first.segment] * len(order), "camera": [first.camera_name] * len(order),
            "frame": order, "timestamp_micros": [frames[f][0] for f in order],
            "image": [{"bytes": frames[f][1], "path": None} for f in order]}


def _tracks(tracks: ObjectTracks) -> np.ndarray:
    """float32 [N, T, 2] tracks, computed a chunk of points at a time."""
    parts = [p[0] for p in tracks.source.point_chunks(what=("tracks",))]
    t = tracks.num_frames
    xy = np.concatenate(parts) if parts else np.zeros((0, t, 2), np.float32)
    if xy.shape != (tracks.num_tracks, t, 2):
        raise ValueError(f"{_where(tracks)}: the track source gave tracks of shape {xy.shape}, "
                         f"expected {(tracks.num_tracks, t, 2)}")
    return xy


def _box_points(tracks: ObjectTracks) -> tuple[np.ndarray, np.ndarray]:
    """(points_box float64 [N, 3], vehicle_from_box float64 [T, 4, 4]) of the clip's source: the
    kept points in output order, from which ``points3d`` is recomputed bit for bit."""
    source = tracks.source
    points = source.points_box
    if points.shape != (tracks.num_tracks, 3):
        raise ValueError(f"{_where(tracks)}: the track source holds {points.shape[0]} points for "
                         f"{tracks.num_tracks} tracks")
    return points, source.vehicle_from_box


def _flat(values: np.ndarray, dtype, value_type: pa.DataType) -> pa.Array:
    """A one-row list array of ``values`` flattened (no Python lists: Arrow reads the buffer)."""
    flat = np.ascontiguousarray(values, dtype=dtype).reshape(-1)
    return pa.ListArray.from_arrays(pa.array([0, flat.size], pa.int32()), pa.array(flat, value_type))


def clip_row(tracks: ObjectTracks, stem: str) -> pa.Table:
    """The one-row clips table of one accepted clip (:data:`CLIPS_SCHEMA`)."""
    xy = _tracks(tracks)
    points_box, vehicle_from_box = _box_points(tracks)
    model = tracks.camera_model
    scalars = {"clip": stem, "split": tracks.split, "segment": tracks.segment, "camera": tracks.camera_name,
               "object_id": tracks.object_id, "object_type": tracks.object_type_name,
               "num_tracks": tracks.num_tracks, "num_frames": tracks.num_frames,
               "width": int(model.width), "height": int(model.height)}
    lists = {
        "frames": _flat(tracks.frames, np.int32, pa.int32()),
        "timestamps_micros": _flat(tracks.timestamps_micros, np.int64, pa.int64()),
        "tracks": _flat(xy, np.float32, pa.float32()),
        "visibles": _flat(tracks.visibles, bool, pa.bool_()),
        "query_frames": _flat(tracks.query_frames, np.int32, pa.int32()),
        "lidar_sources": _flat(tracks.lidar_sources, np.int32, pa.int32()),
        "points_box": _flat(points_box, np.float64, pa.float64()),
        "vehicle_from_box": _flat(vehicle_from_box, np.float64, pa.float64()),
        "query_pixels": _flat(tracks.query_pixels, np.float32, pa.float32()),
        "intrinsics": _flat(np.array([getattr(model, k) for k in INTRINSICS], np.float64), np.float64, pa.float64()),
        "camera_from_vehicle": _flat(tracks.camera_from_vehicle, np.float64, pa.float64()),
        "world_from_vehicle": _flat(tracks.world_from_vehicle, np.float64, pa.float64()),
        # empty unless the run kept the margins (float16 values, exact in float32)
        "occlusion_margin": _flat(np.zeros(0) if tracks.occlusion_margin is None else tracks.occlusion_margin,
                                  np.float32, pa.float32()),
    }
    columns = [lists[f.name] if f.name in lists else pa.array([scalars[f.name]], f.type) for f in CLIPS_SCHEMA]
    return pa.Table.from_arrays(columns, schema=CLIPS_SCHEMA)


def _write_table(url: str, schema: pa.Schema, parts) -> str:
    """Write ``parts`` (tables of ``schema``), one row group each, atomically at ``url``."""
    with atomic_local_path(url, ".parquet") as tmp:
        with pq.ParquetWriter(tmp, schema, **parquet_options(schema)) as writer:
            for part in parts:
                writer.write_table(part, row_group_size=max(part.num_rows, 1))
    return url


def write_segment_tables(out_root_url: str, split: str,
                         clips: list[tuple[str, ObjectTracks]]) -> dict[tuple[int, str], list[str]]:
    """Write the frames tables and the clips table of one segment's accepted clips.

    ``clips``: ``(stem, tracks)`` of each accepted clip, in output order. Returns (camera value,
    object_id) -> ``[clips table URL, frames table URL]``. Nothing is written for no clips.
    """
    if not clips:
        return {}
    root = out_root_url.rstrip("/")
    by_camera: dict[int, list[ObjectTracks]] = {}
    for _, tracks in clips:
        by_camera.setdefault(tracks.camera, []).append(tracks)
    segment = clips[0][1].segment
    frames_urls = {}
    for camera, group in sorted(by_camera.items()):
        url = f"{root}/{frames_table_path(split, segment, group[0].camera_name)}"
        table = pa.Table.from_pydict(frames_rows(group), schema=FRAMES_SCHEMA)
        frames_urls[camera] = _write_table(url, FRAMES_SCHEMA, [table])
        faults.kill_point(segment)   # test-only: a worker killed mid-write (a table already in OUT)

    def rows():
        for stem, tracks in clips:
            yield clip_row(tracks, stem)
            faults.kill_point(segment)

    clips_url = _write_table(f"{root}/{clips_table_path(split, segment)}", CLIPS_SCHEMA, rows())
    return {(tracks.camera, tracks.object_id): [clips_url, frames_urls[tracks.camera]] for _, tracks in clips}
