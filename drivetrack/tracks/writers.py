"""Output writers for :class:`ObjectTracks` (formats documented in ``docs/formats.md``).

A registry (:data:`WRITERS`) maps a writer name to a function
``(out_root_url, split, tracks) -> url``; a new format is a new entry. All storage goes through
fsspec, files are written whole and then moved into place (a reader never sees half a file), and
every file is an ``np.savez_compressed`` archive that loads with ``np.load(allow_pickle=False)``.
"""
from __future__ import annotations

import re

import numpy as np

from drivetrack import storage
from drivetrack.geometry import invert_rigid
from drivetrack.layout import DRIVETRACK, TAPVID3D, clip_path
from drivetrack.tracks.core import ObjectTracks

__all__ = ["WRITERS", "clip_stem", "drivetrack_arrays", "tapvid3d_arrays", "write_npz",
           "write_object_outputs", "decode_video", "OPENCV_FROM_WAYMO_CAMERA"]

#: Deflate level of the npz members (1 = fastest; numpy's savez_compressed uses 6).
NPZ_COMPRESSLEVEL = 1

_SAFE = re.compile(r"^[A-Za-z0-9_.\-]+$")

#: Waymo camera frame (x forward, y left, z up) -> OpenCV camera frame (X right, Y down, Z forward):
#: X = -y, Y = -z, Z = x.
OPENCV_FROM_WAYMO_CAMERA = np.array([[0.0, -1.0, 0.0, 0.0],
                                     [0.0, 0.0, -1.0, 0.0],
                                     [1.0, 0.0, 0.0, 0.0],
                                     [0.0, 0.0, 0.0, 1.0]])


def clip_stem(tracks: ObjectTracks) -> str:
    """``waymo_{segment}_{CAMERA}_{object_id}`` (camera as its Waymo enum name)."""
    for what, value in (("segment", tracks.segment), ("object_id", tracks.object_id)):
        if not _SAFE.match(value):
            raise ValueError(f"{what} {value!r} (segment {tracks.segment!r}) has characters that cannot "
                             f"appear in an output file name; allowed: letters, digits, '_', '-', '.'")
    return f"waymo_{tracks.segment}_{tracks.camera_name}_{tracks.object_id}"


def decode_video(tracks: ObjectTracks) -> np.ndarray:
    """uint8 [T, H, W, 3] RGB frames of the clip, decoded from its JPEG bytes."""
    import cv2

    model = tracks.camera_model
    video = np.empty((tracks.num_frames, model.height, model.width, 3), dtype=np.uint8)
    for i, data in enumerate(tracks.jpeg):
        where = f"segment {tracks.segment!r} camera {tracks.camera_name} frame {int(tracks.frames[i])}"
        if data is None:
            raise ValueError(f"{where}: no camera image")
        bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"{where}: camera image is not a decodable JPEG")
        if bgr.shape[:2] != (model.height, model.width):
            raise ValueError(f"{where}: image is {bgr.shape[1]}x{bgr.shape[0]}, calibration says "
                             f"{model.width}x{model.height}")
        video[i] = bgr[..., ::-1]
    return video


def drivetrack_arrays(tracks: ObjectTracks) -> dict[str, np.ndarray]:
    """The DriveTrack-compatible arrays of one clip (N tracks, T frames)."""
    return {
        "video": decode_video(tracks),
        "tracks": tracks.tracks.astype(np.float32, copy=False),
        "visibles": tracks.visibles.astype(bool, copy=False),
        "timestamps_micros": tracks.timestamps_micros.astype(np.int64, copy=False),
        "query_frames": tracks.query_frames.astype(np.int32, copy=False),
        "lidar_sources": tracks.lidar_sources.astype(np.int32, copy=False),
        "points3d": tracks.points3d.astype(np.float32, copy=False),
    }


def _jpeg_array(tracks: ObjectTracks) -> np.ndarray:
    """[T] fixed-width bytes (``|S<max>``) of the clip's JPEGs: no objects, no pickle.

    numpy strips trailing NUL bytes from fixed-width items; a JPEG ends with the EOI marker
    (FF D9), so nothing is lost, and that is checked.
    """
    for i, data in enumerate(tracks.jpeg):
        if data is None or not bytes(data[:2]) == b"\xff\xd8" or bytes(data[-2:]) != b"\xff\xd9":
            raise ValueError(f"segment {tracks.segment!r} camera {tracks.camera_name} frame "
                             f"{int(tracks.frames[i])}: image is missing or not a complete JPEG "
                             f"(must start with FFD8 and end with FFD9)")
    return np.array([bytes(data) for data in tracks.jpeg], dtype=np.bytes_)


def tapvid3d_queries(tracks: ObjectTracks) -> np.ndarray:
    """float32 [N, 3] (pixel x, pixel y, clip frame) of each track's query.

    The query frame is the track's source frame (``query_frames``) when the point is visible
    there, else its first visible frame; x, y are the image pixel (with lens distortion) there.
    """
    n = tracks.num_tracks
    source = tracks.query_frames.astype(np.int64)
    at_source = tracks.visibles[np.arange(n), source]
    first_visible = np.argmax(tracks.visibles, axis=1)
    frame = np.where(at_source, source, first_visible)
    xy = tracks.tracks[np.arange(n), frame]
    return np.concatenate([xy, frame[:, None].astype(np.float32)], axis=-1).astype(np.float32)


def tapvid3d_arrays(tracks: ObjectTracks) -> dict[str, np.ndarray]:
    """The TAPVid-3D arrays of one clip (time-major; OpenCV camera frame; see docs/formats.md)."""
    model = tracks.camera_model
    opencv_from_vehicle = OPENCV_FROM_WAYMO_CAMERA @ tracks.camera_from_vehicle           # [T,4,4]
    points = np.swapaxes(tracks.points3d.astype(np.float64), 0, 1)                       # [T,N,3]
    xyz = np.einsum("tij,tnj->tni", opencv_from_vehicle[:, :3, :3], points) + opencv_from_vehicle[:, None, :3, 3]
    w2c = opencv_from_vehicle @ invert_rigid(tracks.world_from_vehicle)
    return {
        "images_jpeg_bytes": _jpeg_array(tracks),
        "tracks_XYZ": xyz.astype(np.float32),
        "visibility": np.ascontiguousarray(tracks.visibles.T),
        "queries_xyt": tapvid3d_queries(tracks),
        "fx_fy_cx_cy": np.array([model.f_u, model.f_v, model.c_u, model.c_v], dtype=np.float32),
        "extrinsics_w2c": w2c.astype(np.float32),
        "distortion_k1_k2_p1_p2_k3": np.array([model.k1, model.k2, model.p1, model.p2, model.k3],
                                              dtype=np.float32),
        "timestamps_micros": tracks.timestamps_micros.astype(np.int64),
    }


def write_npz(url: str, arrays: dict[str, np.ndarray], compresslevel: int = NPZ_COMPRESSLEVEL) -> str:
    """Write a clip's arrays as a compressed npz at ``url``: :func:`drivetrack.storage.write_npz`
    (atomic, deterministic bytes, no pickles) at the clips' deflate level."""
    return storage.write_npz(url, arrays, compresslevel)


def _drivetrack_writer(out_root_url: str, split: str, tracks: ObjectTracks) -> str:
    return write_npz(f"{out_root_url.rstrip('/')}/{clip_path(DRIVETRACK, split, clip_stem(tracks))}",
                     drivetrack_arrays(tracks))


def _tapvid3d_writer(out_root_url: str, split: str, tracks: ObjectTracks) -> str:
    return write_npz(f"{out_root_url.rstrip('/')}/{clip_path(TAPVID3D, split, clip_stem(tracks))}",
                     tapvid3d_arrays(tracks))


#: Writer name -> ``(out_root_url, split, tracks) -> written url``.
WRITERS = {"drivetrack": _drivetrack_writer, "tapvid3d": _tapvid3d_writer}


def write_object_outputs(out_root_url: str, split: str, tracks: ObjectTracks,
                         writers: tuple[str, ...] = ("drivetrack", "tapvid3d")) -> list[str]:
    """Write one clip with each named writer; returns the written URLs in ``writers`` order.

    Raises ValueError for a rejected clip (nothing to write) or an unknown writer name.
    """
    if tracks.rejection is not None or tracks.num_tracks == 0:
        raise ValueError(f"segment {tracks.segment!r} camera {tracks.camera_name} object "
                         f"{tracks.object_id!r}: clip was rejected ({tracks.rejection}); nothing to write")
    unknown = [w for w in writers if w not in WRITERS]
    if unknown:
        raise ValueError(f"unknown writers {unknown}; known: {sorted(WRITERS)}")
    return [WRITERS[name](out_root_url, split, tracks) for name in writers]
