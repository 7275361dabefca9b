"""The npz writers of :class:`ObjectTracks` (formats documented in ``docs/formats.md``).

``drivetrack annotate`` writes release layout v2 (:mod:`drivetrack.compact.write`); these
writers make the field's npz formats, and ``drivetrack export`` feeds the same functions
(:func:`drivetrack_arrays`, :func:`tapvid3d_arrays`, :func:`write_npz`) a clip read back from the
tables (:class:`drivetrack.compact.read.StoredClip`, same attributes), so the files are identical.

A registry (:data:`WRITERS`) maps a writer name to a function
``(out_root_url, split, tracks) -> url``; a new format is a new entry. All storage goes through
fsspec, files are written whole and then moved into place (a reader never sees half a file), and
every file is an ``np.savez_compressed`` archive that loads with ``np.load(allow_pickle=False)``.

Nothing of size N x T beyond ``visibles`` is held: the video is decoded one frame at a time,
``tracks`` / ``points3d`` / ``tracks_XYZ`` are recomputed a chunk at a time by the clip's
:class:`drivetrack.tracks.core.TrackSource` while the member is written
(:class:`drivetrack.storage.StreamedArray`); the bytes are those of the whole arrays.
"""
from __future__ import annotations

import numpy as np

from drivetrack import faults, storage
from drivetrack.geometry import invert_rigid
from drivetrack.outputs import DRIVETRACK, TAPVID3D, clip_path
from drivetrack.outputs import clip_stem as outputs_clip_stem  # writers.clip_stem takes an ObjectTracks
from drivetrack.storage import StreamedArray
from drivetrack.tracks.core import ObjectTracks, frames_per_chunk

__all__ = ["WRITERS", "clip_stem", "drivetrack_arrays", "tapvid3d_arrays", "write_npz",
           "write_object_outputs", "decode_video", "video_stream", "OPENCV_FROM_WAYMO_CAMERA"]

#: Deflate level of the npz members (1 = fastest; numpy's savez_compressed uses 6).
NPZ_COMPRESSLEVEL = 1

#: Waymo camera frame (x forward, y left, z up) -> OpenCV camera frame (X right, Y down, Z forward):
#: X = -y, Y = -z, Z = x.
OPENCV_FROM_WAYMO_CAMERA = np.array([[0.0, -1.0, 0.0, 0.0],
                                     [0.0, 0.0, -1.0, 0.0],
                                     [1.0, 0.0, 0.0, 0.0],
                                     [0.0, 0.0, 0.0, 1.0]])


def clip_stem(tracks: ObjectTracks) -> str:
    """``waymo_{segment}_{CAMERA}_{object_id}`` (camera as its Waymo enum name).

    Each part is checked with :func:`drivetrack.names.check_name` (full match) first; an
    :class:`~drivetrack.names.InvalidNameError` names the part, its value and the segment.
    """
    where = f"segment {tracks.segment!r} camera {tracks.camera!r} object {tracks.object_id!r}"
    return outputs_clip_stem(tracks.segment, tracks.camera_name, tracks.object_id, where)


def _video_chunks(tracks: ObjectTracks):
    """Yield uint8 [1, H, W, 3] RGB frames of the clip, one decoded JPEG at a time."""
    import cv2

    model = tracks.camera_model
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
        yield np.ascontiguousarray(bgr[None, ..., ::-1])
        if i == 0:
            faults.kill_point(tracks.segment)   # test-only: a worker killed mid-write


def video_stream(tracks: ObjectTracks) -> StreamedArray:
    """uint8 [T, H, W, 3] RGB frames of the clip as a :class:`StreamedArray` (one frame decoded
    at a time while it is written). Errors name the segment, camera and frame."""
    model = tracks.camera_model
    return StreamedArray((tracks.num_frames, model.height, model.width, 3), np.uint8,
                         lambda: _video_chunks(tracks))


def decode_video(tracks: ObjectTracks) -> np.ndarray:
    """uint8 [T, H, W, 3] RGB frames of the clip, decoded from its JPEG bytes (whole, in memory;
    the writers use :func:`video_stream`)."""
    model = tracks.camera_model
    video = np.empty((tracks.num_frames, model.height, model.width, 3), dtype=np.uint8)
    for i, frame in enumerate(_video_chunks(tracks)):
        video[i] = frame[0]
    return video


def drivetrack_arrays(tracks: ObjectTracks) -> dict[str, np.ndarray | StreamedArray]:
    """The DriveTrack-compatible arrays of one clip (N tracks, T frames).

    ``video``, ``tracks`` and ``points3d`` are :class:`StreamedArray` s (decoded / computed a
    frame or a chunk of points at a time while written: :meth:`TrackSource.point_chunks`).
    ``occlusion_margin`` float16 [N, T] is added when the run kept it (docs/visibility.md).
    """
    n, t = tracks.num_tracks, tracks.num_frames
    source = tracks.source
    margin = getattr(tracks, "occlusion_margin", None)
    extra = {} if margin is None else {"occlusion_margin": np.asarray(margin).astype(np.float16, copy=False)}
    return {
        "video": video_stream(tracks),
        "tracks": StreamedArray((n, t, 2), np.float32,
                                lambda: (c[0] for c in source.point_chunks(what=("tracks",)))),
        "visibles": tracks.visibles.astype(bool, copy=False),
        "timestamps_micros": tracks.timestamps_micros.astype(np.int64, copy=False),
        "query_frames": tracks.query_frames.astype(np.int32, copy=False),
        "lidar_sources": tracks.lidar_sources.astype(np.int32, copy=False),
        "points3d": StreamedArray((n, t, 3), np.float32,
                                  lambda: (c[1] for c in source.point_chunks(what=("points3d",)))),
        **extra,
    }


def _jpeg_array(tracks: ObjectTracks) -> StreamedArray:
    """[T] fixed-width bytes (``|S<max>``) of the clip's JPEGs: no objects, no pickle; streamed
    a frame at a time (the JPEG bytes are not copied whole).

    numpy strips trailing NUL bytes from fixed-width items; a JPEG ends with the EOI marker
    (FF D9), so nothing is lost, and that is checked (before anything is written).
    """
    for i, data in enumerate(tracks.jpeg):
        if data is None or not bytes(data[:2]) == b"\xff\xd8" or bytes(data[-2:]) != b"\xff\xd9":
            raise ValueError(f"segment {tracks.segment!r} camera {tracks.camera_name} frame "
                             f"{int(tracks.frames[i])}: image is missing or not a complete JPEG "
                             f"(must start with FFD8 and end with FFD9)")
    dtype = np.dtype(f"S{max((len(data) for data in tracks.jpeg), default=1) or 1}")
    return StreamedArray((len(tracks.jpeg),), dtype,
                         lambda: (np.array([bytes(data)], dtype=dtype) for data in tracks.jpeg))


def tapvid3d_queries(tracks: ObjectTracks) -> np.ndarray:
    """float32 [N, 3] (pixel x, pixel y, clip frame) of each track's query.

    The query frame is the track's source frame (``query_frames``) when the point is visible
    there, else its first visible frame; x, y are the image pixel (with lens distortion) there
    (``ObjectTracks.query_pixels``, computed by the job: ``tracks`` is not needed).
    """
    n = tracks.num_tracks
    source = tracks.query_frames.astype(np.int64)
    at_source = tracks.visibles[np.arange(n), source]
    first_visible = np.argmax(tracks.visibles, axis=1)
    frame = np.where(at_source, source, first_visible)
    xy = tracks.query_pixels
    return np.concatenate([xy, frame[:, None].astype(np.float32)], axis=-1).astype(np.float32)


def _tracks_xyz_chunks(tracks: ObjectTracks, opencv_from_vehicle: np.ndarray):
    """float32 [F, N, 3] OpenCV-camera-frame points of consecutive frames (from ``points3d``)."""
    start = 0
    for points in tracks.source.frame_chunks():                                       # [F,N,3] float32
        transforms = opencv_from_vehicle[start:start + points.shape[0]]
        start += points.shape[0]
        xyz = np.einsum("tij,tnj->tni", transforms[:, :3, :3], points.astype(np.float64))
        del points
        xyz += transforms[:, None, :3, 3]
        yield xyz.astype(np.float32)


def _visibility_chunks(visibles: np.ndarray):
    """bool [F, N] time-major visibility of consecutive frames."""
    step = frames_per_chunk(visibles.shape[0])
    for start in range(0, visibles.shape[1], step):
        yield np.ascontiguousarray(visibles[:, start:start + step].T)


def tapvid3d_arrays(tracks: ObjectTracks) -> dict[str, np.ndarray | StreamedArray]:
    """The TAPVid-3D arrays of one clip (time-major; OpenCV camera frame; see docs/formats.md).

    ``images_jpeg_bytes``, ``tracks_XYZ`` and ``visibility`` are :class:`StreamedArray` s
    (a frame or a chunk of frames at a time: :meth:`TrackSource.frame_chunks`).
    """
    model = tracks.camera_model
    n, t = tracks.num_tracks, tracks.num_frames
    opencv_from_vehicle = OPENCV_FROM_WAYMO_CAMERA @ tracks.camera_from_vehicle           # [T,4,4]
    w2c = opencv_from_vehicle @ invert_rigid(tracks.world_from_vehicle)
    visibles = tracks.visibles
    return {
        "images_jpeg_bytes": _jpeg_array(tracks),
        "tracks_XYZ": StreamedArray((t, n, 3), np.float32, lambda: _tracks_xyz_chunks(tracks, opencv_from_vehicle)),
        "visibility": StreamedArray((t, n), bool, lambda: _visibility_chunks(visibles)),
        "queries_xyt": tapvid3d_queries(tracks),
        "fx_fy_cx_cy": np.array([model.f_u, model.f_v, model.c_u, model.c_v], dtype=np.float32),
        "extrinsics_w2c": w2c.astype(np.float32),
        "distortion_k1_k2_p1_p2_k3": np.array([model.k1, model.k2, model.p1, model.p2, model.k3],
                                              dtype=np.float32),
        "timestamps_micros": tracks.timestamps_micros.astype(np.int64),
    }


def write_npz(url: str, arrays: dict[str, np.ndarray | StreamedArray],
              compresslevel: int = NPZ_COMPRESSLEVEL) -> str:
    """Write a clip's arrays as a compressed npz at ``url``: :func:`drivetrack.storage.write_npz`
    (atomic, deterministic bytes, no pickles; :class:`StreamedArray` s streamed) at the clips'
    deflate level."""
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
