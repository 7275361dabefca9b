"""Finding and reading the clips to show (any folder layout; release internals skipped).

The clip type is :class:`drivetrack.evaluation.Clip` and names parse with
:func:`drivetrack.outputs.parse_clip_name`, shared with the evaluation. All storage goes through fsspec.
"""
from __future__ import annotations

import io
import posixpath
import zipfile

import fsspec
import numpy as np

from drivetrack.evaluation.clips import Clip, url_of
from drivetrack.outputs import is_clip_name, parse_clip_name

__all__ = ["SPLITS", "find_clips", "clip_num_tracks", "clip_stem_of", "select_clip", "load_clip", "parse_frames"]

SPLITS = ("training", "validation", "testing")
#: Folders whose ``waymo_*.npz`` are not DriveTrack clips (TAPVid-3D copies, release internals).
_NOT_CLIP_DIRS = {"tapvid3d", "_staging", "_txn", "previews"}


def fs_of(url: str):
    """(file system, path) of ``url`` (fsspec)."""
    return fsspec.core.url_to_fs(str(url))


#: Separates a clips table's URL from a clip id in the clip references :func:`find_clips` returns.
TABLE_CLIP_SEP = "#"


def find_clips(root: str) -> list[str]:
    """Sorted references of every clip under ``root``: ``{clips table URL}#{clip id}`` for each row of
    its clips tables (``clips/{split}/*.parquet``), or, when it has none, the URLs of every
    DriveTrack npz clip (``**/waymo_*.npz``).

    Works on an annotation output folder and on a release version folder, whatever the split
    folder layout (``{split}/`` or ``tracks/{split}/``); TAPVid-3D copies (a ``tapvid3d`` folder)
    and release internals (``_staging``, ``_txn``) are left out.
    """
    fs, path = fs_of(root)
    if not fs.isdir(path):
        raise FileNotFoundError(f"{root}: not a folder (pass a clip .npz file or a folder holding clips)")
    from drivetrack.evaluation.clips import find_annotation_files

    tables = [f for f in find_annotation_files(root) if f.clip]
    if tables:
        return sorted(f"{f.url}{TABLE_CLIP_SEP}{f.clip}" for f in tables)
    found = fs.glob(posixpath.join(path.rstrip("/"), "**", "waymo_*.npz"))
    base = path.rstrip("/")
    out = []
    for p in found:
        rel = p[len(base):].lstrip("/") if p.startswith(base) else p
        if set(rel.split("/")[:-1]) & _NOT_CLIP_DIRS or not is_clip_name(p, strict_object_id=True):
            continue
        out.append(url_of(fs, p))
    return sorted(out)


def _npy_header(fs, path: str, key: str) -> tuple[tuple[int, ...], np.dtype]:
    with fs.open(path, "rb") as f, zipfile.ZipFile(f) as zf:
        try:
            member = zf.open(f"{key}.npy")
        except KeyError:
            raise KeyError(f"{path}: no array {key!r} in the file (has {sorted(n[:-4] for n in zf.namelist())})") from None
        with member:
            version = np.lib.format.read_magic(member)
            shape, _, dtype = (np.lib.format.read_array_header_1_0(member) if version == (1, 0)
                               else np.lib.format.read_array_header_2_0(member))
    return tuple(int(s) for s in shape), dtype


def _split_ref(ref: str) -> tuple[str, str]:
    url, _, clip = str(ref).rpartition(TABLE_CLIP_SEP)
    return url, clip


def clip_stem_of(ref: str) -> str:
    """``waymo_{segment}_{CAMERA}_{object_id}`` of a clip reference (:func:`find_clips`) or npz URL."""
    if TABLE_CLIP_SEP in str(ref) and not str(ref).endswith(".npz"):
        return _split_ref(ref)[1]
    name = posixpath.basename(str(ref))
    return name[:-4] if name.endswith(".npz") else name


def clip_num_tracks(url: str) -> int:
    """N of a clip, read from the ``tracks`` array header only (no data is decompressed), or from
    the ``num_tracks`` column of its clips table."""
    if TABLE_CLIP_SEP in str(url):
        import pyarrow.parquet as pq

        table_url, clip = _split_ref(url)
        fs, path = fs_of(table_url)
        with fs.open(path, "rb") as f:
            t = pq.read_table(f, columns=["clip", "num_tracks"])
        return int(dict(zip(t.column("clip").to_pylist(), t.column("num_tracks").to_pylist()))[clip])
    fs, path = fs_of(url)
    return _npy_header(fs, path, "tracks")[0][0]


def select_clip(source: str, object_id: str | None = None, camera: str | None = None) -> str:
    """The clip to show: ``source`` itself if it is a file, else the clip under the folder
    ``source`` matching ``object_id`` / ``camera`` with the most tracks (ties: first by name)."""
    if TABLE_CLIP_SEP in str(source) and not str(source).endswith(".npz"):
        return str(source)   # a clip of a clips table, as find_clips names it
    fs, path = fs_of(source)
    if fs.isfile(path):
        return str(source)
    clips = find_clips(source)
    if not clips:
        raise FileNotFoundError(f"{source}: no clip (clips/*/*.parquet tables or waymo_*.npz files) under this folder")
    keep = []
    for url in clips:
        _, cam, obj = parse_clip_name(clip_stem_of(url))
        if (object_id is None or obj == object_id) and (camera is None or cam == camera.upper()):
            keep.append(url)
    if not keep:
        names = [clip_stem_of(u) for u in clips]
        have = sorted({f"{parse_clip_name(u)[2]} ({parse_clip_name(u)[1]})" for u in names})
        raise LookupError(f"{source}: no clip for object {object_id!r} camera {camera!r}; "
                          f"objects here: {', '.join(have[:20])}{' ...' if len(have) > 20 else ''}")
    counts = [clip_num_tracks(u) for u in keep]
    return keep[int(np.argmax(counts))]


def _load_table_clip(ref: str) -> Clip:
    """A clip of a clips table (``{table URL}#{clip id}``), its video decoded from the frames table."""
    from drivetrack.evaluation.clips import AnnotationFile, read_stored
    from drivetrack.outputs import parse_table_path

    table_url, clip = _split_ref(ref)
    parts = table_url.rstrip("/").split("/")
    rel = "/".join(parts[-3:])
    parsed = parse_table_path(rel)
    if not parsed:
        raise ValueError(f"{ref}: not a clip of a clips table clips/{{split}}/{{segment}}.parquet")
    segment, camera, object_id = parse_clip_name(clip, [parsed[2]])
    stored = read_stored(AnnotationFile(table_url, rel, parsed[1], segment, camera, object_id, clip))
    from drivetrack.compact.read import LazyVideo

    return Clip(url=str(ref), split=parsed[1], segment=segment, camera=camera, object_id=object_id,
                video=np.asarray(LazyVideo(stored)), tracks=stored.tracks, visibles=stored.visibles,
                timestamps_micros=stored.timestamps_micros, query_frames=stored.query_frames,
                lidar_sources=stored.lidar_sources)



def load_clip(url: str) -> Clip:
    """Read a DriveTrack clip (an npz file, or ``{clips table URL}#{clip id}`` from :func:`find_clips`);
    errors name the file and the offending key, shape or dtype."""
    if TABLE_CLIP_SEP in str(url) and not str(url).endswith(".npz"):
        return _load_table_clip(url)
    segment, camera, object_id = parse_clip_name(url)
    fs, path = fs_of(url)
    try:
        with fs.open(path, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        raise FileNotFoundError(f"{url}: no such clip file") from None
    try:
        z = np.load(io.BytesIO(data), allow_pickle=False)
    except (ValueError, zipfile.BadZipFile, OSError) as error:
        raise ValueError(f"{url}: not a readable .npz file ({error})") from error
    with z:
        missing = [k for k in ("video", "tracks", "visibles") if k not in z.files]
        if missing:
            raise KeyError(f"{url}: missing array(s) {missing}; a DriveTrack clip has video, tracks, visibles")
        arrays = {k: z[k] for k in z.files}
    video, tracks, visibles = arrays["video"], arrays["tracks"], arrays["visibles"]
    if video.dtype != np.uint8 or video.ndim != 4 or video.shape[-1] != 3:
        raise ValueError(f"{url}: video must be uint8 [T, H, W, 3], found {video.dtype} {video.shape}")
    t = video.shape[0]
    if tracks.ndim != 3 or tracks.shape[1:] != (t, 2):
        raise ValueError(f"{url}: tracks must be [N, {t}, 2] (T from video), found {tracks.shape}")
    if visibles.dtype != bool or visibles.shape != tracks.shape[:2]:
        raise ValueError(f"{url}: visibles must be bool {tracks.shape[:2]}, found {visibles.dtype} {visibles.shape}")
    split = posixpath.basename(posixpath.dirname(path))
    return Clip(url=str(url), split=split, segment=segment, camera=camera, object_id=object_id,
                video=video, tracks=tracks.astype(np.float32, copy=False), visibles=visibles,
                timestamps_micros=arrays.get("timestamps_micros"), query_frames=arrays.get("query_frames"),
                lidar_sources=arrays.get("lidar_sources"))


def parse_frames(spec: str | None, num_frames: int) -> np.ndarray:
    """int64 [F] clip frames of a Python-style slice ``"A:B"`` (or ``"A:B:S"``, or one index ``"A"``)."""
    if spec is None or spec.strip() in ("", ":"):
        return np.arange(num_frames)
    parts = spec.split(":")
    try:
        if len(parts) == 1:
            index = int(parts[0])
            frames = np.arange(num_frames)[[index]]
        elif len(parts) <= 3:
            bounds = [int(p) if p.strip() else None for p in parts]
            frames = np.arange(num_frames)[slice(*bounds)]
        else:
            raise ValueError("too many ':'")
    except (ValueError, IndexError) as error:
        raise ValueError(f"--frames {spec!r}: expected A:B (clip frames 0..{num_frames - 1}); {error}") from None
    if frames.size == 0:
        raise ValueError(f"--frames {spec!r} selects no frame of a {num_frames}-frame clip")
    return frames



def scene_frames(timestamps_all: np.ndarray, timestamps_clip: np.ndarray | None, where: str) -> np.ndarray:
    """int64 [T] segment frame index of each clip frame, matched on timestamps."""
    if timestamps_clip is None:
        raise ValueError(f"{where}: the clip has no timestamps_micros; cannot match its frames to the source")
    idx = np.clip(np.searchsorted(timestamps_all, timestamps_clip), 0, max(len(timestamps_all) - 1, 0))
    bad = timestamps_all[idx] != timestamps_clip if len(timestamps_all) else np.ones(len(timestamps_clip), bool)
    if np.any(bad):
        raise ValueError(f"{where}: clip timestamp(s) {timestamps_clip[bad][:3].tolist()} not found among the "
                         f"source's {len(timestamps_all)} frame timestamps (wrong --source or segment?)")
    return idx.astype(np.int64)

