"""Annotation clips as the evaluation and the viewer read them: finding, reading, checking.

- :class:`Clip`: one annotated clip (N tracks, T frames) in memory, the one type
  :mod:`drivetrack.evaluation` scores and :mod:`drivetrack.show` draws.
- :func:`find_annotation_files`: every clip of a folder: the rows of its v2 clips tables
  (``clips/{split}/*.parquet``, :mod:`drivetrack.compact`) or, when it has none, every
  DriveTrack-layout npz clip file (e.g. ``drivetrack export`` output), names parsed with
  :func:`drivetrack.outputs.parse_clip_name`.
- :func:`read_clip` / :func:`load_npz`: arrays checked from their npy headers before any data is
  read (dtype kind, shape, declared size), flags checked to be 0/1.

Pixels (x, y), pixel i covers [i, i+1), as everywhere in drivetrack.
"""
from __future__ import annotations

import posixpath
from dataclasses import dataclass
from typing import Iterable, Iterator

import numpy as np
import pandas as pd

from drivetrack.outputs import parse_clip_name
from drivetrack.waymo.schema import CameraName

__all__ = ["Clip", "AnnotationFile", "find_annotation_files", "read_clip", "iter_clips", "clip_from_tracks",
           "load_npz", "flags", "PIXELS", "FLAGS", "INTEGERS"]


@dataclass
class Clip:
    """One annotated clip (N tracks, T frames): what the evaluation scores and the viewer draws.

    Attributes:
        segment, camera (``CameraName`` name, e.g. ``FRONT``), object_id: from the file name
            (:func:`drivetrack.outputs.parse_clip_name`).
        tracks: float [N, T, 2], pixels (x, y); NaN only where not visible.
        visibles: bool [N, T].
        timestamps_micros: int64 [T], the clip's frame timestamps (None if the file has none).
        query_frames: int [N], clip frame of the LiDAR return of each track (None if absent).
        lidar_sources: int [N, 4], (laser, return 1|2, range-image row, col) (None if absent).
        split: the clip file's folder name ("" when unknown).
        file: relative path it was read from ("" when in memory), for error messages and tables.
        url: where it was read from ("" when in memory).
        video: uint8 [T, H, W, 3] RGB, when read (the viewer reads it, the evaluation does not).
    """
    segment: str
    camera: str
    object_id: str
    tracks: np.ndarray
    visibles: np.ndarray
    timestamps_micros: np.ndarray | None = None
    query_frames: np.ndarray | None = None
    lidar_sources: np.ndarray | None = None
    split: str = ""
    file: str = ""
    url: str = ""
    video: np.ndarray | None = None

    @property
    def where(self) -> str:
        source = self.file or self.url
        return (f"{source} " if source else "") + \
            f"(segment {self.segment!r}, camera {self.camera}, object {self.object_id!r})"

    @property
    def num_frames(self) -> int:
        return int(self.visibles.shape[1])

    @property
    def num_tracks(self) -> int:
        return int(self.tracks.shape[0])

    @property
    def title(self) -> str:
        return f"{self.segment} {self.camera} {self.object_id}"

    def check(self) -> None:
        """Raise ValueError naming the clip and the array when shapes or ranges disagree, or when an
        array the evaluation needs (timestamps_micros, query_frames, lidar_sources) is absent."""
        n, t = self.visibles.shape if self.visibles.ndim == 2 else (-1, -1)
        if self.visibles.ndim != 2:
            raise ValueError(f"{self.where}: visibles must be [N, T], got shape {self.visibles.shape}")
        for name, array, shape in (("tracks", self.tracks, (n, t, 2)),
                                   ("timestamps_micros", self.timestamps_micros, (t,)),
                                   ("query_frames", self.query_frames, (n,)),
                                   ("lidar_sources", self.lidar_sources, (n, 4))):
            if array is None:
                raise ValueError(f"{self.where}: has no {name}; expected shape {shape}")
            if array.shape != shape:
                raise ValueError(f"{self.where}: {name} has shape {array.shape}, expected {shape} "
                                 f"(from visibles {self.visibles.shape})")
        if n and (self.query_frames.min() < 0 or self.query_frames.max() >= t):
            bad = int(self.query_frames[(self.query_frames < 0) | (self.query_frames >= t)][0])
            raise ValueError(f"{self.where}: query_frames value {bad} outside the clip's {t} frames")


def clip_from_tracks(tracks, file: str = "") -> Clip:
    """A :class:`Clip` from an in-memory :class:`drivetrack.tracks.ObjectTracks` (no copy)."""
    return Clip(segment=tracks.segment, camera=CameraName(int(tracks.camera)).name, object_id=str(tracks.object_id),
                timestamps_micros=np.asarray(tracks.timestamps_micros, dtype=np.int64),
                tracks=tracks.tracks, visibles=np.asarray(tracks.visibles, dtype=bool),
                query_frames=np.asarray(tracks.query_frames, dtype=np.int64),
                lidar_sources=np.asarray(tracks.lidar_sources, dtype=np.int64), split=tracks.split, file=file)


@dataclass(frozen=True)
class AnnotationFile:
    """A clip found under an annotation or release folder: a DriveTrack-layout npz file, or (when
    ``clip`` is set) the row ``clip`` of the v2 clips table at ``url`` / ``relpath``."""
    url: str
    relpath: str
    split: str
    segment: str
    camera: str
    object_id: str
    clip: str = ""

    @property
    def name(self) -> str:
        """The clip's npz file name ``waymo_{segment}_{CAMERA}_{object_id}.npz`` (what predictions match)."""
        return f"{self.clip}.npz" if self.clip else self.relpath.rsplit("/", 1)[-1]

    @property
    def where(self) -> str:
        return f"{self.relpath} clip {self.clip}" if self.clip else self.url

    @property
    def where_relative(self) -> str:
        """Relative path (and clip id, for a clips table) for messages."""
        return f"{self.relpath} clip {self.clip}" if self.clip else self.relpath


def fs_of(url: str, storage_options: dict | None = None):
    import fsspec

    fs, path = fsspec.core.url_to_fs(str(url), **(storage_options or {}))
    return fs, path.rstrip("/")


def url_of(fs, path: str) -> str:
    protocol = fs.protocol if isinstance(fs.protocol, str) else fs.protocol[0]
    return path if protocol in ("file", "local") else f"{protocol}://{path}"


def _known_segments(fs, root: str) -> list[str]:
    """Segment names from ``stats/objects.parquet`` when the folder has it (else empty)."""
    path = f"{root}/stats/objects.parquet"
    if not fs.exists(path):
        return []
    with fs.open(path, "rb") as handle:
        table = pd.read_parquet(handle, columns=["segment"])
    return sorted(set(table["segment"].astype(str)))


def find_annotation_files(root: str, split: str | None = None,
                          storage_options: dict | None = None) -> list[AnnotationFile]:
    """Every clip under ``root``: the rows of its clips tables (``clips/{split}/*.parquet``), or,
    when it has none, every ``waymo_*.npz`` clip (any depth) except TAPVid-3D copies.

    The split of an npz file is the name of the folder holding it (``OUT/tracks/{split}/`` or
    ``OUT/{split}/``); ``split`` keeps only that split. Sorted by relative path (and table row).
    """
    fs, base = fs_of(root, storage_options)
    if not fs.isdir(base):
        raise FileNotFoundError(f"annotation folder {root} does not exist")
    tables = _table_clips(fs, base, split)
    if tables is not None:
        return tables
    segments = _known_segments(fs, base)
    out = []
    for path in sorted(fs.glob(f"{base}/**/waymo_*.npz")):
        rel = path[len(base):].lstrip("/")
        parts = rel.split("/")
        if "tapvid3d" in parts[:-1]:
            continue
        file_split = parts[-2] if len(parts) > 1 else ""
        if split is not None and file_split != split:
            continue
        segment, camera, object_id = parse_clip_name(parts[-1], segments)
        out.append(AnnotationFile(url_of(fs, path), rel, file_split, segment, camera, object_id))
    return out


def _table_clips(fs, base: str, split: str | None) -> list[AnnotationFile] | None:
    """The clips of the v2 clips tables under ``base`` (None when there are no clips tables)."""
    from drivetrack.compact.read import clip_ids
    from drivetrack.outputs import CLIPS, TABLE_FOLDERS, parse_table_path

    rels = sorted(p[len(base):].lstrip("/") for p in fs.glob(f"{base}/{TABLE_FOLDERS[CLIPS]}/*/*.parquet"))
    rels = [r for r in rels if (parsed := parse_table_path(r)) and parsed[0] == CLIPS]
    if not rels:
        return None
    out = []
    for rel in rels:
        _, table_split, segment, _ = parse_table_path(rel)
        if split is not None and table_split != split:
            continue
        path = f"{base}/{rel}"
        for clip in clip_ids(fs, path, rel):
            _, camera, object_id = parse_clip_name(clip, [segment])
            out.append(AnnotationFile(url_of(fs, path), rel, table_split, segment, camera, object_id, clip))
    return out


def read_stored(file: AnnotationFile, storage_options: dict | None = None):
    """The :class:`drivetrack.compact.read.StoredClip` of a clips-table clip."""
    from drivetrack.compact.read import FrameStore, iter_clips_in

    fs, path = fs_of(file.url, storage_options)
    root = path[:-len(file.relpath)].rstrip("/") if path.endswith(file.relpath) else posixpath.dirname(path)
    found = list(iter_clips_in(fs, path, file.relpath, {file.clip}, FrameStore(url_of(fs, root), storage_options)))
    if not found:
        raise ValueError(f"{file.relpath}: no clip {file.clip} in the table")
    return found[0]


#: dtype kinds accepted per role of an array (numpy ``dtype.kind``): pixel coordinates, 0/1
#: flags (visibility, occlusion), integer indices. Anything else (object, string, complex,
#: structured, datetime) is refused from the header, before the data is read.
PIXELS = ("fiu", "a real number type")
FLAGS = ("biuf", "bool (or 0/1 numbers)")
INTEGERS = ("iu", "an integer type")

_CLIP_SPEC = {"visibles": (FLAGS, ("N", "T")), "tracks": (PIXELS, ("N", "T", 2)),
              "timestamps_micros": (INTEGERS, ("T",)), "query_frames": (INTEGERS, ("N",)),
              "lidar_sources": (INTEGERS, ("N", 4))}


def load_npz(url: str, spec: dict[str, tuple[tuple[str, str], tuple]], optional: tuple[str, ...] = (),
              storage_options: dict | None = None, dims: dict[str, int] | None = None,
              dims_from: str = "") -> dict[str, np.ndarray]:
    """The arrays ``spec`` names, each checked from its npy header before its data is read.

    ``spec``: ``{name: ((dtype kinds, description), shape)}``, shape entries an int or a symbol
    (``"N"``, ``"T"``) that must take the same value in every array; ``dims`` pre-binds symbols
    (their origin ``dims_from`` goes into the error). Names in ``optional`` may be absent. Every
    refusal (missing array, object or other foreign dtype, wrong ndim or shape, a header that
    declares more data than the member holds) is a ValueError naming ``url`` and the array;
    other members (e.g. ``video``) are not touched.
    """
    from drivetrack.storage import NpzReader

    bound = dict(dims or {})
    with NpzReader(url, url, storage_options) as npz:
        missing = [k for k in spec if k not in npz and k not in optional]
        if missing:
            raise ValueError(f"{url}: missing array(s) {missing}; has {sorted(npz.files)}")
        present = [k for k in spec if k in npz]
        for name in present:
            (kinds, kind_text), pattern = spec[name]
            header = npz.header(name)
            if header.dtype.kind not in kinds:
                raise ValueError(f"{url}: {name} has dtype {header.dtype}; expected {kind_text}")
            expected = tuple(bound.get(d, d) if isinstance(d, str) else d for d in pattern)
            found = header.shape
            ok = len(found) == len(pattern) and all(
                e == f or (isinstance(e, str) and e not in bound) for e, f in zip(expected, found))
            if not ok:
                origin = f" (N tracks, T frames of {dims_from})" if dims_from and dims else ""
                symbolic = f"({', '.join(str(d) for d in pattern)}{',' if len(pattern) == 1 else ''})"
                known = "" if any(isinstance(e, str) for e in expected) else f" = {expected}"
                raise ValueError(f"{url}: {name} has shape {found}, expected {symbolic}{known}{origin}; "
                                 f"refused before reading its data")
            for symbol, value in zip(pattern, found):
                if isinstance(symbol, str):
                    bound.setdefault(symbol, value)
        return {name: npz.load(name) for name in present}


def flags(array: np.ndarray, url: str, name: str) -> np.ndarray:
    """bool of a 0/1 flag array; NaN or any other value is a ValueError naming file, array, place."""
    if array.dtype == bool:
        return array
    bad = ~((array == 0) | (array == 1))               # NaN compares unequal to both
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"{url}: {name} must hold only 0/1 (or bool); found {array[index]!r} at index {index} "
                         f"({int(bad.sum()):,} such values); refusing to guess what it means")
    return array.astype(bool)


def read_clip(file: AnnotationFile, storage_options: dict | None = None) -> Clip:
    """The arrays of one clip (``video`` is not read)."""
    if file.clip:
        stored = read_stored(file, storage_options)
        clip = Clip(segment=file.segment, camera=file.camera, object_id=file.object_id, split=file.split,
                    file=file.relpath, timestamps_micros=stored.timestamps_micros, tracks=stored.tracks,
                    visibles=stored.visibles, query_frames=stored.query_frames.astype(np.int64),
                    lidar_sources=stored.lidar_sources.astype(np.int64))
        clip.check()
        return clip
    arrays = load_npz(file.url, _CLIP_SPEC, storage_options=storage_options)
    clip = Clip(segment=file.segment, camera=file.camera, object_id=file.object_id, split=file.split,
                file=file.relpath, timestamps_micros=arrays["timestamps_micros"].astype(np.int64),
                tracks=arrays["tracks"], visibles=flags(arrays["visibles"], file.url, "visibles"),
                query_frames=arrays["query_frames"].astype(np.int64),
                lidar_sources=arrays["lidar_sources"].astype(np.int64))
    clip.check()
    return clip



def iter_clips(files: Iterable[AnnotationFile], storage_options: dict | None = None) -> Iterator[Clip]:
    """Read clip files one at a time (for streaming into :func:`evaluate_clips`)."""
    for file in files:
        yield read_clip(file, storage_options)
