"""Read release layout v2 (:mod:`drivetrack.compact.layout`): clips one row group at a time, frames
only when asked for.

:func:`load_clip` is the loader for users: ``drivetrack.load_clip(release_or_out, clip)`` gives a
clip's video (decoded lazily, a frame at a time), tracks and visibility. :func:`iter_clips` yields
:class:`StoredClip` s, which carry the attributes the npz writers of
:mod:`drivetrack.tracks.writers` read from a freshly tracked clip, so ``drivetrack export`` feeds
the very same writer functions from the tables.

Errors name the file, the clip and the frame: a clips table that is not a readable Parquet file
(truncated, corrupt), a missing column, or a frame reference without its row in the frames table.
"""
from __future__ import annotations

import posixpath
from dataclasses import dataclass, field
from typing import Iterator

import fsspec
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from drivetrack.compact.layout import CLIPS_SCHEMA, FRAMES_SCHEMA, INTRINSICS, OPTIONAL_COLUMNS
from drivetrack.outputs import CLIPS, TABLE_FOLDERS, frames_table_path, parse_clip_name, parse_table_path

__all__ = ["CompactFormatError", "Intrinsics", "StoredClip", "StoredSource", "ClipData", "LazyVideo", "points3d_from_box",
           "clips_tables", "open_table", "clip_ids", "iter_clips", "read_clip", "load_clip", "FrameStore",
           "check_frame_references"]


class CompactFormatError(ValueError):
    """A v2 table is missing, unreadable, lacks a column or refers to a frame it does not have."""


@dataclass(frozen=True)
class Intrinsics:
    """A clip's camera intrinsics (the attribute names of :class:`drivetrack.camera.model.CameraModel`)."""
    f_u: float
    f_v: float
    c_u: float
    c_v: float
    k1: float
    k2: float
    p1: float
    p2: float
    k3: float
    width: int
    height: int


class StoredSource:
    """Stand-in for :class:`drivetrack.tracks.core.TrackSource` over stored arrays: the same chunk
    generators, slicing ``tracks`` float32 [N, T, 2] and ``points3d`` float32 [N, T, 3]."""

    def __init__(self, clip: "StoredClip"):
        self.clip = clip

    def point_chunks(self, points: int | None = None, what: tuple[str, ...] = ("tracks", "points3d")):
        from drivetrack.tracks.core import points_per_chunk

        n = self.clip.num_tracks
        step = points or points_per_chunk(self.clip.num_frames)
        xy = self.clip.tracks if "tracks" in what else None
        xyz = self.clip.points3d if "points3d" in what else None
        for start in range(0, n, step):
            yield (None if xy is None else xy[start:start + step],
                   None if xyz is None else xyz[start:start + step])

    def frame_chunks(self, frames: int | None = None):
        from drivetrack.tracks.core import frames_per_chunk

        xyz = self.clip.points3d
        step = frames or frames_per_chunk(self.clip.num_tracks)
        for start in range(0, self.clip.num_frames, step):
            yield np.ascontiguousarray(np.swapaxes(xyz[:, start:start + step], 0, 1))


class FrameStore:
    """The frames tables of one output folder or release, read whole one (segment, camera) at a time
    and kept until another one is asked for (clips of a segment are read in order)."""

    def __init__(self, root_url: str, storage_options: dict | None = None):
        self.fs, self.root = fsspec.core.url_to_fs(root_url, **(storage_options or {}))
        self.root = self.root.rstrip("/")
        self._key = None
        self._frames: dict[int, int] = {}
        self._table = None

    def _load(self, split: str, segment: str, camera: str) -> str:
        rel = frames_table_path(split, segment, camera)
        if self._key != rel:
            table = open_table(self.fs, f"{self.root}/{rel}", rel, FRAMES_SCHEMA).read(
                columns=["frame", "timestamp_micros", "image"])
            self._table = table
            self._frames = {f: i for i, f in enumerate(table.column("frame").to_pylist())}
            self._key = rel
        return rel

    def rows(self, split: str, segment: str, camera: str, frames, where: str) -> list[int]:
        """Row of each of ``frames`` in the frames table; CompactFormatError naming the table, the
        clip (``where``) and the first missing frame."""
        rel = self._load(split, segment, camera)
        missing = [int(f) for f in frames if int(f) not in self._frames]
        if missing:
            raise CompactFormatError(f"{rel}: {where} refers to frame {missing[0]}, which the frames table "
                                     f"does not hold ({len(missing)} missing frame reference(s))")
        return [self._frames[int(f)] for f in frames]

    def jpeg(self, split: str, segment: str, camera: str, frames, where: str) -> list[bytes]:
        """The source JPEG bytes of ``frames``, in order."""
        rows = self.rows(split, segment, camera, frames, where)
        images = self._table.column("image")
        return [images[r]["bytes"].as_py() for r in rows]


@dataclass
class StoredClip:
    """One clip read from a clips table (N tracks, T frames; see :mod:`drivetrack.compact.layout`).

    Attributes mirror :class:`drivetrack.tracks.core.ObjectTracks` where the writers read them:
    ``frames`` int64 [T], ``timestamps_micros`` int64 [T], ``visibles`` bool [N, T],
    ``query_frames`` int32 [N], ``lidar_sources`` int32 [N, 4], ``query_pixels`` float32 [N, 2],
    ``tracks`` float32 [N, T, 2], ``points_box`` float64 [N, 3], ``vehicle_from_box`` float64
    [T, 4, 4], ``points3d`` float32 [N, T, 3] (computed from those two on first access),
    ``camera_model`` (:class:`Intrinsics`), ``camera_from_vehicle`` / ``world_from_vehicle``
    float64 [T, 4, 4], ``jpeg`` the T source JPEGs (read from the frames table on first access),
    ``occlusion_margin`` float32 [N, T] or None (the run did not keep the margins; docs/visibility.md).
    """
    clip: str
    file: str
    split: str
    segment: str
    camera_name: str
    object_id: str
    object_type_name: str
    frames: np.ndarray
    timestamps_micros: np.ndarray
    tracks: np.ndarray
    visibles: np.ndarray
    query_frames: np.ndarray
    lidar_sources: np.ndarray
    points_box: np.ndarray
    vehicle_from_box: np.ndarray
    query_pixels: np.ndarray
    camera_model: Intrinsics
    camera_from_vehicle: np.ndarray
    world_from_vehicle: np.ndarray
    occlusion_margin: np.ndarray | None = field(default=None, repr=False)
    frame_store: FrameStore | None = field(default=None, repr=False)
    _jpeg: list | None = field(default=None, repr=False)
    _points3d: np.ndarray | None = field(default=None, repr=False)

    @property
    def points3d(self) -> np.ndarray:
        """float32 [N, T, 3], metres, vehicle frame of each frame (:func:`points3d_from_box`)."""
        if self._points3d is None:
            self._points3d = points3d_from_box(self.points_box, self.vehicle_from_box)
        return self._points3d

    @property
    def num_tracks(self) -> int:
        return int(self.tracks.shape[0])

    @property
    def num_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def where(self) -> str:
        return f"clip {self.clip}"

    @property
    def source(self) -> StoredSource:
        return StoredSource(self)

    @property
    def jpeg(self) -> list[bytes]:
        if self._jpeg is None:
            if self.frame_store is None:
                raise CompactFormatError(f"{self.file}: {self.where} was read without its frames tables")
            self._jpeg = self.frame_store.jpeg(self.split, self.segment, self.camera_name, self.frames, self.where)
        return self._jpeg


def points3d_from_box(points_box: np.ndarray, vehicle_from_box: np.ndarray) -> np.ndarray:
    """float32 [N, T, 3]: box-frame points float64 [N, 3] through the box poses float64 [T, 4, 4],
    computed as the track stage computes ``points3d`` (float64, then rounded to float32)."""
    from drivetrack.tracks.core import _carry

    return np.ascontiguousarray(np.swapaxes(_carry(vehicle_from_box, points_box), 0, 1).astype(np.float32))


def open_table(fs, path: str, rel: str, schema: pa.Schema) -> pq.ParquetFile:
    """Open a v2 table; CompactFormatError naming ``rel`` when it is missing, not a readable Parquet
    file (truncated, corrupt) or lacks a column of ``schema``."""
    try:
        handle = fs.open(path, "rb")
        table = pq.ParquetFile(handle)
    except FileNotFoundError:
        raise CompactFormatError(f"{rel}: no such table") from None
    except (pa.ArrowException, OSError, ValueError) as error:
        raise CompactFormatError(f"{rel}: not a readable Parquet table (truncated or corrupt?): {error}") from error
    missing = [f.name for f in schema if f.name not in table.schema_arrow.names and f.name not in OPTIONAL_COLUMNS]
    if missing:
        raise CompactFormatError(f"{rel}: missing column(s) {missing} of the v2 layout "
                                 f"(docs/formats.md)")
    return table


def clips_tables(root_url: str, storage_options: dict | None = None) -> list[str]:
    """Relative paths of every clips table (``clips/{split}/{segment}.parquet``) under ``root_url``."""
    fs, root = fsspec.core.url_to_fs(root_url, **(storage_options or {}))
    root = root.rstrip("/")
    found = fs.glob(f"{root}/{TABLE_FOLDERS[CLIPS]}/*/*.parquet")
    rels = sorted(p[len(root):].lstrip("/") for p in found)
    return [r for r in rels if (parsed := parse_table_path(r)) and parsed[0] == CLIPS]


def clip_ids(fs, path: str, rel: str) -> list[str]:
    """The ``clip`` column of a clips table, in row order."""
    table = open_table(fs, path, rel, CLIPS_SCHEMA)
    return table.read(columns=["clip"]).column("clip").to_pylist()


def _row_groups_of(table: pq.ParquetFile) -> list[tuple[int, int]]:
    """(row group, row within it) of each row of a table."""
    out = []
    for g in range(table.metadata.num_row_groups):
        out.extend((g, r) for r in range(table.metadata.row_group(g).num_rows))
    return out


def _array(column, dtype, shape, rel: str, clip: str, name: str) -> np.ndarray:
    flat = column.values.to_numpy(zero_copy_only=False) if column is not None else None
    if flat is None:
        raise CompactFormatError(f"{rel}: clip {clip} column {name!r} is null")
    want = int(np.prod(shape))
    if flat.size != want:
        raise CompactFormatError(f"{rel}: clip {clip} column {name!r} holds {flat.size} values, "
                                 f"expected {want} for shape {list(shape)}")
    return flat.astype(dtype, copy=False).reshape(shape)


def _stored_clip(row: pa.Table, rel: str, frame_store: FrameStore | None) -> StoredClip:
    get = {name: row.column(name).combine_chunks() for name in row.column_names}
    scalar = {k: get[k][0].as_py() for k in ("clip", "split", "segment", "camera", "object_id", "object_type",
                                               "num_tracks", "num_frames", "width", "height")}
    clip, n, t = scalar["clip"], scalar["num_tracks"], scalar["num_frames"]

    def arr(name, dtype, shape):
        value = get[name]
        return _array(None if value.is_null().to_numpy(zero_copy_only=False)[0] else value, dtype, shape,
                      rel, clip, name)

    margin = None
    if "occlusion_margin" in get and not get["occlusion_margin"].is_null().to_numpy(zero_copy_only=False)[0] \
            and len(get["occlusion_margin"].values):
        margin = arr("occlusion_margin", np.float32, (n, t))
    intrinsics = arr("intrinsics", np.float64, (len(INTRINSICS),))
    model = Intrinsics(*(float(v) for v in intrinsics), width=int(scalar["width"]), height=int(scalar["height"]))
    return StoredClip(
        clip=clip, file=rel, split=scalar["split"], segment=scalar["segment"], camera_name=scalar["camera"],
        object_id=scalar["object_id"], object_type_name=scalar["object_type"],
        frames=arr("frames", np.int64, (t,)), timestamps_micros=arr("timestamps_micros", np.int64, (t,)),
        tracks=arr("tracks", np.float32, (n, t, 2)), visibles=arr("visibles", bool, (n, t)),
        query_frames=arr("query_frames", np.int32, (n,)), lidar_sources=arr("lidar_sources", np.int32, (n, 4)),
        points_box=arr("points_box", np.float64, (n, 3)),
        vehicle_from_box=arr("vehicle_from_box", np.float64, (t, 4, 4)), query_pixels=arr("query_pixels", np.float32, (n, 2)), camera_model=model,
        camera_from_vehicle=arr("camera_from_vehicle", np.float64, (t, 4, 4)),
        world_from_vehicle=arr("world_from_vehicle", np.float64, (t, 4, 4)), occlusion_margin=margin,
        frame_store=frame_store)


def iter_clips(root_url: str, clips: set[str] | None = None, storage_options: dict | None = None,
               columns: list[str] | None = None) -> Iterator[StoredClip]:
    """Yield every clip (or those named in ``clips``) under ``root_url``, one row group read at a time,
    in table order. Frames are read only when a clip's ``jpeg`` is asked for."""
    fs, root = fsspec.core.url_to_fs(root_url, **(storage_options or {}))
    root = root.rstrip("/")
    frame_store = FrameStore(root_url, storage_options)
    for rel in clips_tables(root_url, storage_options):
        path = f"{root}/{rel}"
        table = open_table(fs, path, rel, CLIPS_SCHEMA)
        ids = table.read(columns=["clip"]).column("clip").to_pylist()
        for (group, index), clip in zip(_row_groups_of(table), ids):
            if clips is not None and clip not in clips:
                continue
            try:
                rows = table.read_row_group(group)
            except (pa.ArrowException, OSError) as error:
                raise CompactFormatError(f"{rel}: clip {clip}: row group {group} cannot be read "
                                         f"(truncated or corrupt?): {error}") from error
            yield _stored_clip(rows.slice(index, 1), rel, frame_store)


def read_clip(root_url: str, clip: str, storage_options: dict | None = None) -> StoredClip:
    """The clip ``clip`` (``waymo_{segment}_{CAMERA}_{object_id}``, an npz file name works too) of an
    output folder or release; FileNotFoundError naming the folder when it holds no such clip."""
    stem = posixpath.basename(clip)
    stem = stem[:-4] if stem.endswith(".npz") else stem
    segment, _, _ = parse_clip_name(stem)
    fs, root = fsspec.core.url_to_fs(root_url, **(storage_options or {}))
    root = root.rstrip("/")
    # the table of the clip's segment first (a segment name holding a camera name parses shorter)
    candidates = sorted(fs.glob(f"{root}/{TABLE_FOLDERS[CLIPS]}/*/*.parquet"),
                        key=lambda p: (posixpath.basename(p) != f"{segment}.parquet", p))
    for path in candidates:
        rel = path[len(root):].lstrip("/")
        if stem in clip_ids(fs, path, rel):
            return next(iter_clips_in(fs, path, rel, {stem}, FrameStore(root_url, storage_options)))
    raise FileNotFoundError(f"{root_url}: no clip {stem} in any clips table ({TABLE_FOLDERS[CLIPS]}/*/*.parquet)")


def iter_clips_in(fs, path: str, rel: str, clips: set[str], frame_store: FrameStore) -> Iterator[StoredClip]:
    """The clips named in ``clips`` of one clips table."""
    table = open_table(fs, path, rel, CLIPS_SCHEMA)
    ids = table.read(columns=["clip"]).column("clip").to_pylist()
    for (group, index), clip in zip(_row_groups_of(table), ids):
        if clip in clips:
            yield _stored_clip(table.read_row_group(group).slice(index, 1), rel, frame_store)


class LazyVideo:
    """uint8 [T, H, W, 3] RGB frames of a clip, each decoded from its JPEG when indexed.

    ``len(video)``, ``video[i]`` (one frame), ``for frame in video``, ``video.shape`` and
    ``np.asarray(video)`` (all frames, decoded now)."""

    def __init__(self, clip: StoredClip):
        self._clip = clip

    @property
    def shape(self) -> tuple[int, int, int, int]:
        m = self._clip.camera_model
        return (self._clip.num_frames, m.height, m.width, 3)

    def __len__(self) -> int:
        return self._clip.num_frames

    def __getitem__(self, i: int) -> np.ndarray:
        import cv2

        t = self._clip.num_frames
        if not -t <= i < t:
            raise IndexError(f"{self._clip.where}: frame {i} out of range (T = {t})")
        data = self._clip.jpeg[i]
        bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise CompactFormatError(f"{self._clip.where} clip frame {i}: image is not a decodable JPEG")
        return np.ascontiguousarray(bgr[..., ::-1])

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    def __array__(self, dtype=None, copy=None):
        video = np.stack(list(self)) if len(self) else np.zeros(self.shape, np.uint8)
        return video if dtype is None else video.astype(dtype)


@dataclass
class ClipData:
    """What :func:`load_clip` returns: ``video`` (:class:`LazyVideo`, uint8 [T, H, W, 3] RGB decoded
    a frame at a time), ``tracks`` float32 [N, T, 2] pixels, ``visibles`` bool [N, T],
    ``query_frames`` int32 [N], ``timestamps_micros`` int64 [T], ``clip`` (the
    :class:`StoredClip` with every stored column), and ``occlusion_margin`` float32 [N, T] (None
    unless the run kept the margins; docs/visibility.md)."""
    video: LazyVideo
    tracks: np.ndarray
    visibles: np.ndarray
    query_frames: np.ndarray
    timestamps_micros: np.ndarray
    clip: StoredClip
    occlusion_margin: np.ndarray | None = None


def load_clip(release_or_out: str, clip: str, storage_options: dict | None = None) -> ClipData:
    """One clip of a release (``STORE/NAME/VERSION``) or an annotation output folder: its video
    (decoded lazily), tracks and visibility. ``clip`` is the clip id
    ``waymo_{segment}_{CAMERA}_{object_id}`` (the ``clip`` column of the clips table)."""
    stored = read_clip(release_or_out, clip, storage_options)
    stored.frame_store.rows(stored.split, stored.segment, stored.camera_name, stored.frames, stored.where)
    return ClipData(video=LazyVideo(stored), tracks=stored.tracks, visibles=stored.visibles,
                    query_frames=stored.query_frames, timestamps_micros=stored.timestamps_micros, clip=stored,
                    occlusion_margin=stored.occlusion_margin)


def check_frame_references(fs, root: str, rels: list[str]) -> list[str]:
    """Problems with the frame references of the clips tables ``rels`` (relative to ``root``, a
    path of ``fs``): every frame a clip lists must be a row of its (segment, camera) frames table.
    Each problem names the table, the clip and the frame."""
    problems = []
    known: dict[str, set[int] | None] = {}
    for rel in rels:
        try:
            table = open_table(fs, f"{root}/{rel}", rel, CLIPS_SCHEMA).read(
                columns=["clip", "split", "segment", "camera", "frames"])
        except CompactFormatError as error:
            problems.append(str(error))
            continue
        for clip, split, segment, camera, frames in zip(*(table.column(c).to_pylist() for c in table.column_names)):
            frames_rel = frames_table_path(split, segment, camera)
            if frames_rel not in known:
                try:
                    known[frames_rel] = set(open_table(fs, f"{root}/{frames_rel}", frames_rel, FRAMES_SCHEMA)
                                            .read(columns=["frame"]).column("frame").to_pylist())
                except CompactFormatError as error:
                    problems.append(f"{error} (needed by clip {clip} of {rel})")
                    known[frames_rel] = None
            have = known[frames_rel]
            if have is None:
                continue
            missing = [f for f in frames if f not in have]
            if missing:
                problems.append(f"{rel}: clip {clip} refers to frame {missing[0]} of {frames_rel}, which that "
                                f"table does not hold ({len(missing)} missing frame reference(s))")
    return problems

