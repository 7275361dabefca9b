"""Evaluation: score point-track annotations against exact synthetic truth, and trackers against a release.

Two uses, one set of definitions (docs/evaluation.md):

1. **Annotations vs exact truth** (:func:`evaluate_annotations`, :func:`evaluate_tracks`,
   :func:`evaluate_clips`). Each annotated track names the LiDAR return that produced it
   (``query_frames`` = clip frame, ``lidar_sources`` = (laser, return, row, col)). The clip frame
   becomes a segment frame by matching the clip's ``timestamps_micros`` to the truth's, and the
   key (segment frame, laser, return, row, col) is looked up in the truth's ``lidar_hits``. A
   matched track is scored against that hit's exact ``pixels`` and ``visible`` in the clip's camera
   and frames, at the annotation's own resolution. Per clip:

   - TAP-Vid metrics (:func:`drivetrack.metrics.compute_tapvid_metrics`) in query modes ``first``
     and ``strided``, queries built from the *truth* (:func:`~drivetrack.metrics.queries_first`,
     :func:`~drivetrack.metrics.queries_strided`), over the matched tracks;
   - pixel error (median, mean; px) over frames where the truth is visible;
   - purity: share of the clip's tracks whose return truly lies on the annotated object (a return
     that is not in ``lidar_hits`` hit the ground or background: impure);
   - recall: share of the object's truth hits in the clip's frames that became tracks
     (``recall``: of all its hits, every laser and return; ``recall_visible``: of the hits visible
     in this camera in at least one clip frame, the ones the method is meant to keep).

2. **A tracker vs a release** (:func:`score_predictions`): the release's (or an annotation
   folder's) tracks and visibility are the ground truth, a tracker's npz per clip (same file
   names; ``tracks`` [N, T, 2] and ``visibles`` or ``occluded`` [N, T]) the prediction.

Results come as an :class:`Evaluation`: ``clips`` (one row per clip and query mode), ``objects``
(one row per (split, segment, object, query mode), metrics averaged over the object's clips) and
a JSON-able ``summary`` (metrics averaged over clips per query mode, as TAP-Vid averages over
videos; purity, recall and pixel errors pooled over all tracks).

Pixels (x, y), pixel i covers [i, i+1), as everywhere in drivetrack.
"""
from __future__ import annotations

import math
import posixpath
from dataclasses import dataclass, field
from typing import Iterable, Iterator

import numpy as np
import pandas as pd

from drivetrack.metrics import (QUERY_MODES, THRESHOLDS_PX, compute_tapvid_metrics, queries_first,
                                queries_strided, rescale_points)
from drivetrack.outputs import parse_clip_name
from drivetrack.waymo.schema import CameraName

__all__ = ["METRIC_KEYS", "Clip", "Evaluation", "AnnotationFile", "TruthIndex", "find_annotation_files",
           "read_clip", "clip_from_tracks", "score_clip", "evaluate_clips", "evaluate_tracks",
           "evaluate_annotations", "score_predictions", "tapvid_scores", "pixel_error_stats"]

#: TAP-Vid metric names, in table order.
METRIC_KEYS = (("occlusion_accuracy",) + tuple(f"pts_within_{d}" for d in THRESHOLDS_PX)
               + tuple(f"jaccard_{d}" for d in THRESHOLDS_PX) + ("average_jaccard", "average_pts_within_thresh"))

#: Default cap on the queries scored per clip and mode (evenly spaced subset beyond it): bounds the
#: [Q, T, 2] float64 temporaries of the metric (a full-size clip can have 10^5 tracks x 40 strides).
DEFAULT_MAX_QUERIES = 20_000

# bit layout of a LiDAR return key: frame | laser (3 bits) | return (2) | row (12) | col (13)
_COL_BITS, _ROW_BITS, _RETURN_BITS, _LASER_BITS = 13, 12, 2, 3


# ------------------------------------------------------------------------------------------------
# Inputs
# ------------------------------------------------------------------------------------------------

@dataclass
class Clip:
    """One annotated clip (N tracks, T frames) as the evaluation needs it.

    Attributes:
        segment, camera (``CameraName`` name, e.g. ``FRONT``), object_id, split.
        timestamps_micros: int64 [T], the clip's frame timestamps.
        tracks: float [N, T, 2], pixels (x, y).
        visibles: bool [N, T].
        query_frames: int [N], clip frame of the LiDAR return of each track.
        lidar_sources: int [N, 4], (laser, return 1|2, range-image row, col).
        file: where it was read from ("" when in memory), for error messages and tables.
    """
    segment: str
    camera: str
    object_id: str
    timestamps_micros: np.ndarray
    tracks: np.ndarray
    visibles: np.ndarray
    query_frames: np.ndarray
    lidar_sources: np.ndarray
    split: str = ""
    file: str = ""

    @property
    def where(self) -> str:
        return (f"{self.file} " if self.file else "") + \
            f"(segment {self.segment!r}, camera {self.camera}, object {self.object_id!r})"

    def check(self) -> None:
        """Raise ValueError naming the clip and the array when shapes or ranges disagree."""
        n, t = self.visibles.shape if self.visibles.ndim == 2 else (-1, -1)
        if self.visibles.ndim != 2:
            raise ValueError(f"{self.where}: visibles must be [N, T], got shape {self.visibles.shape}")
        for name, array, shape in (("tracks", self.tracks, (n, t, 2)),
                                   ("timestamps_micros", self.timestamps_micros, (t,)),
                                   ("query_frames", self.query_frames, (n,)),
                                   ("lidar_sources", self.lidar_sources, (n, 4))):
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
    """A DriveTrack-layout clip file found under an annotation or release folder."""
    url: str
    relpath: str
    split: str
    segment: str
    camera: str
    object_id: str


def _fs(url: str, storage_options: dict | None = None):
    import fsspec

    fs, path = fsspec.core.url_to_fs(str(url), **(storage_options or {}))
    return fs, path.rstrip("/")


def _url(fs, path: str) -> str:
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
    """Every ``waymo_*.npz`` clip under ``root`` (any depth), except TAPVid-3D copies.

    The split is the name of the folder holding the file (``OUT/tracks/{split}/`` or
    ``OUT/{split}/``); ``split`` keeps only that split. Sorted by relative path.
    """
    fs, base = _fs(root, storage_options)
    if not fs.isdir(base):
        raise FileNotFoundError(f"annotation folder {root} does not exist")
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
        out.append(AnnotationFile(_url(fs, path), rel, file_split, segment, camera, object_id))
    return out


#: dtype kinds accepted per role of an array (numpy ``dtype.kind``): pixel coordinates, 0/1
#: flags (visibility, occlusion), integer indices. Anything else (object, string, complex,
#: structured, datetime) is refused from the header, before the data is read.
_PIXELS = ("fiu", "a real number type")
_FLAGS = ("biuf", "bool (or 0/1 numbers)")
_INTEGERS = ("iu", "an integer type")

_CLIP_SPEC = {"visibles": (_FLAGS, ("N", "T")), "tracks": (_PIXELS, ("N", "T", 2)),
              "timestamps_micros": (_INTEGERS, ("T",)), "query_frames": (_INTEGERS, ("N",)),
              "lidar_sources": (_INTEGERS, ("N", 4))}


def _load_npz(url: str, spec: dict[str, tuple[tuple[str, str], tuple]], optional: tuple[str, ...] = (),
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


def _flags(array: np.ndarray, url: str, name: str) -> np.ndarray:
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
    """The arrays of one DriveTrack-layout clip file (``video`` is not read)."""
    arrays = _load_npz(file.url, _CLIP_SPEC, storage_options=storage_options)
    clip = Clip(segment=file.segment, camera=file.camera, object_id=file.object_id, split=file.split,
                file=file.relpath, timestamps_micros=arrays["timestamps_micros"].astype(np.int64),
                tracks=arrays["tracks"], visibles=_flags(arrays["visibles"], file.url, "visibles"),
                query_frames=arrays["query_frames"].astype(np.int64),
                lidar_sources=arrays["lidar_sources"].astype(np.int64))
    clip.check()
    return clip


# ------------------------------------------------------------------------------------------------
# Matching tracks to the truth
# ------------------------------------------------------------------------------------------------

def _return_keys(frame: np.ndarray, laser: np.ndarray, return_index: np.ndarray, row: np.ndarray,
                 col: np.ndarray, where: str) -> np.ndarray:
    """int64 [N] keys of LiDAR returns (see the bit layout above); raises on out-of-range fields."""
    fields = (("frame", frame, 1 << 30), ("laser", laser, 1 << _LASER_BITS),
              ("return", return_index, 1 << _RETURN_BITS), ("row", row, 1 << _ROW_BITS),
              ("col", col, 1 << _COL_BITS))
    for name, value, limit in fields:
        value = np.asarray(value)
        if value.size and (value.min() < 0 or value.max() >= limit):
            bad = int(value[(value < 0) | (value >= limit)][0])
            raise ValueError(f"{where}: LiDAR {name} value {bad} outside [0, {limit})")
    key = np.asarray(frame, np.int64)
    for value, bits in ((laser, _LASER_BITS), (return_index, _RETURN_BITS), (row, _ROW_BITS), (col, _COL_BITS)):
        key = (key << bits) | np.asarray(value, np.int64)
    return key


class TruthIndex:
    """The exact truth of one synthetic segment, indexed for matching tracks to LiDAR hits.

    Attributes:
        truth: the :class:`drivetrack.synth.GroundTruth`.
        timestamps_micros: int64 [T_seg].
        object_ids: str [K].
    """

    def __init__(self, truth):
        self.truth = truth
        hits = truth.hits
        self.timestamps_micros = np.asarray(truth.objects["timestamps_micros"], dtype=np.int64)
        self.object_ids = np.asarray(truth.objects["object_id"]).astype(str)
        keys = _return_keys(hits["frame"], hits["laser"], hits["return_index"], hits["row"], hits["col"],
                            f"ground truth {truth.url}")
        self._order = np.argsort(keys, kind="stable")
        self._sorted = keys[self._order]
        self._object_index = np.asarray(hits["object_index"], dtype=np.int64)
        self._frame = np.asarray(hits["frame"], dtype=np.int64)

    @classmethod
    def load(cls, root: str, split: str, segment: str) -> "TruthIndex":
        from drivetrack.synth import load_ground_truth
        from drivetrack.synth.ground_truth import ground_truth_url

        try:
            truth = load_ground_truth(root, split, segment)
        except FileNotFoundError as error:
            raise FileNotFoundError(f"segment {segment!r} (split {split!r}) has no synthetic ground truth under "
                                    f"{ground_truth_url(root, split, segment)} ({error}); is the truth root the "
                                    f"synthetic source these annotations were made from?") from None
        return cls(truth)

    def segment_frames(self, timestamps_micros: np.ndarray, where: str) -> np.ndarray:
        """int64 [T]: segment frame of each clip timestamp; raises if one is not a truth frame."""
        ts = np.asarray(timestamps_micros, dtype=np.int64)
        pos = np.clip(np.searchsorted(self.timestamps_micros, ts), 0, max(self.timestamps_micros.size - 1, 0))
        bad = np.flatnonzero(self.timestamps_micros[pos] != ts) if self.timestamps_micros.size else np.arange(ts.size)
        if bad.size:
            raise ValueError(f"{where}: timestamp {int(ts[bad[0]])} (clip frame {int(bad[0])}) is not a frame of "
                             f"ground-truth segment {self.truth.segment!r} ({self.timestamps_micros.size} frames, "
                             f"{int(self.timestamps_micros[0]) if self.timestamps_micros.size else '-'}.."
                             f"{int(self.timestamps_micros[-1]) if self.timestamps_micros.size else '-'}); "
                             f"annotation and truth come from different segments or runs")
        return pos.astype(np.int64)

    def match(self, frame: np.ndarray, lidar_sources: np.ndarray, where: str) -> np.ndarray:
        """int64 [N]: truth hit of each (segment frame [N], (laser, return, row, col) [N, 4]), -1 if none."""
        sources = np.asarray(lidar_sources, dtype=np.int64).reshape(-1, 4)
        keys = _return_keys(frame, sources[:, 0], sources[:, 1], sources[:, 2], sources[:, 3], where)
        pos = np.searchsorted(self._sorted, keys)
        pos_clipped = np.minimum(pos, max(self._sorted.size - 1, 0))
        found = (pos < self._sorted.size) & (self._sorted[pos_clipped] == keys) if self._sorted.size \
            else np.zeros(keys.size, bool)
        return np.where(found, self._order[pos_clipped] if self._sorted.size else -1, -1).astype(np.int64)

    def object_index(self, object_id: str, where: str) -> int:
        found = np.flatnonzero(self.object_ids == object_id)
        if found.size == 0:
            raise ValueError(f"{where}: object {object_id!r} is not an object of ground-truth segment "
                             f"{self.truth.segment!r} ({self.object_ids.size} objects)")
        return int(found[0])

    def object_hits(self, object_index: int, frames: np.ndarray) -> np.ndarray:
        """int64 [H]: truth hits of object ``object_index`` at segment frames ``frames``."""
        return np.flatnonzero((self._object_index == object_index) & np.isin(self._frame, frames))


# ------------------------------------------------------------------------------------------------
# Scoring
# ------------------------------------------------------------------------------------------------

def _subsample(count: int, limit: int | None) -> np.ndarray:
    if limit is None or count <= limit:
        return np.arange(count)
    return np.unique(np.linspace(0, count - 1, limit).round().astype(np.int64))


def pixel_error_stats(errors: np.ndarray) -> dict[str, float]:
    """Median, mean and p95 (px) of pixel errors, a non-finite error counting as +inf.

    A prediction that is NaN or inf where the truth is visible is infinitely wrong, never
    "no error": it sorts above every finite error, so the median and p95 become inf once that
    share of errors is non-finite, and the mean is inf as soon as one is. NaN when ``errors`` is
    empty. ``errors``: float [E].
    """
    errors = np.asarray(errors, dtype=np.float64).reshape(-1)
    if errors.size == 0:
        return {"pixel_error_median": math.nan, "pixel_error_mean": math.nan, "pixel_error_p95": math.nan}
    ordered = np.sort(np.where(np.isfinite(errors), errors, np.inf))

    def quantile(q: float) -> float:                       # numpy's "linear" method, inf-safe
        position = q * (ordered.size - 1)
        low, frac = int(math.floor(position)), position - math.floor(position)
        if frac == 0 or math.isinf(ordered[low + 1]):
            return float(ordered[low]) if frac == 0 else math.inf
        return float(ordered[low] + (ordered[low + 1] - ordered[low]) * frac)

    mean = math.inf if math.isinf(ordered[-1]) else float(np.mean(ordered))
    return {"pixel_error_median": quantile(0.5), "pixel_error_mean": mean, "pixel_error_p95": quantile(0.95)}


def tapvid_scores(gt_tracks: np.ndarray, gt_visibles: np.ndarray, pred_tracks: np.ndarray,
                  pred_visibles: np.ndarray, query_mode: str, stride: int = 5,
                  max_queries: int | None = DEFAULT_MAX_QUERIES) -> dict[str, float]:
    """TAP-Vid metrics of one clip, queries from the truth.

    Args:
        gt_tracks, pred_tracks: float [N, T, 2] pixels (x, y).
        gt_visibles, pred_visibles: bool [N, T].
        query_mode: ``first`` (each track's first visible truth point) or ``strided`` (every
            visible truth point at frames 0, stride, ...; the track's one prediction is scored
            against each of its queries).
        max_queries: score an evenly spaced subset of at most this many queries (None = all).
    Returns:
        ``{metric: float}`` for :data:`METRIC_KEYS` (NaN when no query exists) plus
        ``num_queries`` and ``num_queries_scored``.
    """
    if query_mode == "first":
        queries, index = queries_first(gt_visibles, gt_tracks)
    elif query_mode == "strided":
        queries, index = queries_strided(gt_visibles, gt_tracks, stride)
    else:
        raise ValueError(f"unknown query_mode {query_mode!r}; expected one of {QUERY_MODES}")
    out: dict[str, float] = {"num_queries": int(index.size)}
    keep = _subsample(index.size, max_queries)
    out["num_queries_scored"] = int(keep.size)
    if keep.size == 0:
        return {**{k: math.nan for k in METRIC_KEYS}, **out}
    queries, index = queries[keep], index[keep]
    metrics = compute_tapvid_metrics(queries[None], ~np.asarray(gt_visibles, bool)[index][None],
                                     np.asarray(gt_tracks)[index][None], ~np.asarray(pred_visibles, bool)[index][None],
                                     np.asarray(pred_tracks)[index][None], query_mode)
    return {**{k: float(metrics[k][0]) for k in METRIC_KEYS}, **out}


def _errors_at_visible(pred_tracks: np.ndarray, gt_tracks: np.ndarray,
                       gt_visibles: np.ndarray) -> tuple[np.ndarray, int]:
    """(float64 [E] distance at every truth-visible point, +inf where the prediction is not
    finite; count of those non-finite predictions)."""
    pred = pred_tracks[gt_visibles]
    with np.errstate(invalid="ignore", over="ignore"):
        errors = np.linalg.norm(pred - gt_tracks[gt_visibles], axis=-1)
    bad = ~np.isfinite(pred).all(axis=-1)
    errors[bad | ~np.isfinite(errors)] = np.inf
    return errors, int(bad.sum())


def score_clip(clip: Clip, index: TruthIndex, query_modes: tuple[str, ...] = QUERY_MODES, stride: int = 5,
               max_queries: int | None = DEFAULT_MAX_QUERIES) -> tuple[list[dict], np.ndarray]:
    """Score one annotated clip against the exact truth of its segment.

    Returns ``(rows, errors)``: one dict per query mode (identity, counts, purity, recall, pixel
    error and TAP-Vid metrics; see the module docstring) and float64 [E] the pixel error of every
    matched track at every frame where the truth sees it (+inf where the track is not finite).
    """
    clip.check()
    where = clip.where
    if clip.segment != index.truth.segment:
        raise ValueError(f"{where}: scored against the ground truth of segment {index.truth.segment!r}")
    frames = index.segment_frames(clip.timestamps_micros, where)
    try:
        camera_axis = index.truth.camera_axis(clip.camera)
    except KeyError as error:
        raise ValueError(f"{where}: {error.args[0]}") from None
    object_k = index.object_index(clip.object_id, where)
    n, t = clip.visibles.shape
    hit = index.match(frames[clip.query_frames], clip.lidar_sources, where)
    matched = hit >= 0
    hits = index.truth.hits
    on_object = np.zeros(n, dtype=bool)
    on_object[matched] = hits["object_index"][hit[matched]] == object_k

    hm = hit[matched]
    gt_tracks = hits["pixels"][hm[:, None], camera_axis, frames[None, :]].astype(np.float64)       # [M, T, 2]
    gt_visibles = hits["visible"][hm[:, None], camera_axis, frames[None, :]]                      # [M, T]
    pred_tracks = np.asarray(clip.tracks[matched], dtype=np.float64)
    pred_visibles = clip.visibles[matched]
    errors, nonfinite = _errors_at_visible(pred_tracks, gt_tracks, gt_visibles)

    object_hits = index.object_hits(object_k, frames)
    visible_hits = object_hits[hits["visible"][object_hits[:, None], camera_axis, frames[None, :]].any(axis=1)] \
        if object_hits.size else object_hits
    tracked = np.unique(hit[on_object])
    base = {
        "split": clip.split, "segment": clip.segment, "camera": clip.camera, "object_id": clip.object_id,
        "file": clip.file, "num_frames": int(t), "num_tracks": int(n), "num_matched": int(matched.sum()),
        "num_on_object": int(on_object.sum()), "num_unmatched": int((~matched).sum()),
        "num_other_object": int((matched & ~on_object).sum()),
        "purity": float(on_object.mean()) if n else math.nan,
        "num_object_hits": int(object_hits.size), "num_object_hits_visible": int(visible_hits.size),
        "num_hits_tracked": int(tracked.size), "num_visible_hits_tracked": int(np.isin(visible_hits, tracked).sum()),
        "recall": float(tracked.size / object_hits.size) if object_hits.size else math.nan,
        "recall_visible": (float(np.isin(visible_hits, tracked).sum() / visible_hits.size)
                           if visible_hits.size else math.nan),
        "num_gt_visible_points": int(gt_visibles.sum()),
        "num_pred_visible_points": int(pred_visibles.sum()),
        **pixel_error_stats(errors),
        "num_nonfinite_at_visible": nonfinite,
    }
    rows = [{**base, "query_mode": mode,
             **tapvid_scores(gt_tracks, gt_visibles, pred_tracks, pred_visibles, mode, stride, max_queries)}
            for mode in query_modes]
    return rows, errors


@dataclass
class Evaluation:
    """Result of an evaluation.

    Attributes:
        clips: one row per (clip, query mode).
        objects: one row per (split, segment, object_id, query mode): TAP-Vid metrics and pixel
            errors averaged over the object's clips (cameras), counts summed, purity/recall pooled.
        summary: JSON-able dict: ``kind``, counts, pooled purity/recall/pixel errors, and per
            query mode the metrics averaged over clips (``modes``).
    """
    clips: pd.DataFrame
    objects: pd.DataFrame
    summary: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        """Summary plus the per-object and per-clip tables as lists of records (NaN -> None)."""
        def records(frame: pd.DataFrame) -> list[dict]:
            return [{k: _jsonable(v) for k, v in row.items()} for row in frame.to_dict("records")]

        return {"summary": _jsonable(self.summary), "objects": records(self.objects), "clips": records(self.clips)}


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return None if not math.isfinite(float(value)) else float(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


_SUM_COLUMNS = ("num_frames", "num_tracks", "num_matched", "num_on_object", "num_unmatched", "num_other_object",
                "num_object_hits", "num_object_hits_visible", "num_hits_tracked", "num_visible_hits_tracked",
                "num_gt_visible_points", "num_pred_visible_points", "num_nonfinite_at_visible", "num_queries",
                "num_queries_scored")
_MEAN_COLUMNS = METRIC_KEYS + ("pixel_error_median", "pixel_error_mean", "pixel_error_p95")


def _aggregate(clips: pd.DataFrame) -> pd.DataFrame:
    keys = ["split", "segment", "object_id", "query_mode"]
    if clips.empty:
        return pd.DataFrame(columns=keys)
    sums = [c for c in _SUM_COLUMNS if c in clips.columns]
    means = [c for c in _MEAN_COLUMNS if c in clips.columns]
    grouped = clips.groupby(keys, sort=True, dropna=False)
    out = grouped[sums].sum().join(grouped[means].mean())
    out.insert(0, "num_clips", grouped.size())
    out.insert(1, "cameras", grouped["camera"].agg(lambda c: ",".join(sorted(set(c)))))
    if {"num_on_object", "num_tracks"} <= set(out.columns):
        out["purity"] = _pooled(out["num_on_object"], out["num_tracks"])
        out["recall"] = _pooled(out["num_hits_tracked"], out["num_object_hits"])
        out["recall_visible"] = _pooled(out["num_visible_hits_tracked"], out["num_object_hits_visible"])
    return out.reset_index()


def _pooled(numerator, denominator):
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(np.asarray(denominator) > 0, np.asarray(numerator, float) / np.asarray(denominator, float),
                        np.nan)


def _summary(kind: str, clips: pd.DataFrame, errors: list[np.ndarray], extra: dict) -> dict:
    first = clips.drop_duplicates(["split", "segment", "camera", "object_id"]) if not clips.empty else clips
    summary = {"kind": kind, **extra, "num_clips": int(len(first)),
               "num_objects": int(first[["split", "segment", "object_id"]].drop_duplicates().shape[0]) if len(first) else 0,
               "num_segments": int(first[["split", "segment"]].drop_duplicates().shape[0]) if len(first) else 0,
               "num_tracks": int(first["num_tracks"].sum()) if len(first) else 0}
    if "num_on_object" in first.columns:
        for name in ("num_matched", "num_on_object", "num_unmatched", "num_other_object", "num_object_hits",
                     "num_hits_tracked", "num_object_hits_visible", "num_visible_hits_tracked"):
            summary[name] = int(first[name].sum()) if len(first) else 0
        summary["purity"] = float(_pooled(summary["num_on_object"], summary["num_tracks"]))
        summary["recall"] = float(_pooled(summary["num_hits_tracked"], summary["num_object_hits"]))
        summary["recall_visible"] = float(_pooled(summary["num_visible_hits_tracked"],
                                                  summary["num_object_hits_visible"]))
    summary.update(pixel_error_stats(np.concatenate(errors) if errors else np.zeros(0)))
    # non-finite predictions at truth-visible points: errors, in the headline as well as per clip
    nonfinite = first["num_nonfinite_at_visible"] if "num_nonfinite_at_visible" in first.columns else None
    summary["num_gt_visible_points"] = int(first["num_gt_visible_points"].sum()) if len(first) else 0
    summary["num_nonfinite_at_visible"] = int(nonfinite.sum()) if nonfinite is not None else 0
    summary["num_clips_nonfinite"] = int((nonfinite > 0).sum()) if nonfinite is not None else 0
    modes = {}
    for mode, part in (clips.groupby("query_mode", sort=False) if not clips.empty else []):
        modes[mode] = {"num_queries": int(part["num_queries"].sum()),
                       **{k: float(part[k].mean()) for k in METRIC_KEYS}}
    summary["modes"] = modes
    return summary


def evaluate_clips(clips: Iterable[Clip], truth_root: str, query_modes: tuple[str, ...] = QUERY_MODES,
                   stride: int = 5, max_queries: int | None = DEFAULT_MAX_QUERIES,
                   default_split: str = "training", truths: dict | None = None) -> Evaluation:
    """Score clips against the synthetic truth under ``truth_root`` (see the module docstring).

    The truth of a segment is loaded when its first clip arrives and released when a clip of
    another segment comes (feed clips grouped by segment to load each truth once). A caller that
    scores the same segments repeatedly may pass ``truths``, a dict kept across calls:
    ``(split, segment) -> TruthIndex`` (filled here; never released).
    """
    rows: list[dict] = []
    errors: list[np.ndarray] = []
    current: tuple[str, str] | None = None
    index: TruthIndex | None = None
    for clip in clips:
        key = (clip.split or default_split, clip.segment)
        if key != current:
            index = None                      # release the previous truth first
            if truths is not None and key in truths:
                index = truths[key]
            else:
                index = TruthIndex.load(truth_root, *key)
                if truths is not None:
                    truths[key] = index
            current = key
        clip_rows, clip_errors = score_clip(clip, index, query_modes, stride, max_queries)
        rows.extend(clip_rows)
        errors.append(clip_errors.astype(np.float32))
    frame = pd.DataFrame(rows)
    return Evaluation(frame, _aggregate(frame),
                      _summary("annotations_vs_truth", frame, errors, {"truth": str(truth_root),
                                                                       "query_modes": list(query_modes),
                                                                       "stride": stride}))


def evaluate_tracks(tracks: Iterable, truth_root: str, **kwargs) -> Evaluation:
    """:func:`evaluate_clips` of in-memory ``ObjectTracks`` (rejected / empty clips skipped)."""
    clips = (clip_from_tracks(t) for t in tracks if getattr(t, "rejection", None) is None and t.num_tracks > 0)
    return evaluate_clips(clips, truth_root, **kwargs)


def evaluate_annotations(out_url: str, truth_root: str, split: str | None = None,
                         query_modes: tuple[str, ...] = QUERY_MODES, stride: int = 5,
                         max_queries: int | None = DEFAULT_MAX_QUERIES,
                         storage_options: dict | None = None) -> Evaluation:
    """Score every clip file of an annotation folder against the synthetic truth of its segment."""
    files = find_annotation_files(out_url, split, storage_options)
    if not files:
        raise FileNotFoundError(f"no annotation files waymo_*.npz under {out_url}"
                                + (f" for split {split!r}" if split else ""))
    files.sort(key=lambda f: (f.split, f.segment, f.relpath))
    result = evaluate_clips((read_clip(f, storage_options) for f in files), truth_root, query_modes, stride,
                            max_queries, default_split=split or "training")
    result.summary["annotations"] = str(out_url)
    return result


def _prediction_index(predictions_url: str, storage_options: dict | None) -> dict[str, str]:
    fs, base = _fs(predictions_url, storage_options)
    if not fs.isdir(base):
        raise FileNotFoundError(f"predictions folder {predictions_url} does not exist")
    by_name: dict[str, str] = {}
    for path in sorted(fs.glob(f"{base}/**/*.npz")):
        rel = path[len(base):].lstrip("/")
        name = posixpath.basename(rel)
        if "tapvid3d" in rel.split("/")[:-1]:
            continue
        if name in by_name:
            raise ValueError(f"predictions folder {predictions_url}: {name} appears twice "
                             f"({by_name[name]} and {_url(fs, path)})")
        by_name[name] = _url(fs, path)
    return by_name


_TRUTH_SPEC = {"visibles": (_FLAGS, ("N", "T")), "tracks": (_PIXELS, ("N", "T", 2))}
_PREDICTION_SPEC = {"tracks": (_PIXELS, ("N", "T", 2)), "visibles": (_FLAGS, ("N", "T")),
                    "occluded": (_FLAGS, ("N", "T"))}


def _read_truth(file: AnnotationFile, storage_options: dict | None) -> tuple[np.ndarray, np.ndarray]:
    """(tracks float64 [N, T, 2], visibles bool [N, T]) of a release clip used as ground truth."""
    arrays = _load_npz(file.url, _TRUTH_SPEC, storage_options=storage_options)
    tracks = arrays["tracks"].astype(np.float64)
    visibles = _flags(arrays["visibles"], file.url, "visibles")
    bad = visibles & ~np.isfinite(tracks).all(axis=-1)
    if bad.any():
        n, t = (int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"{file.url}: ground-truth tracks are not finite at {int(bad.sum()):,} visible points "
                         f"(first: track {n}, frame {t}: {tracks[n, t].tolist()}); the clip cannot be a reference")
    return tracks, visibles


def _read_prediction(url: str, shape: tuple[int, int], truth_file: str,
                     storage_options: dict | None) -> tuple[np.ndarray, np.ndarray]:
    """(tracks [N, T, 2], visibles bool [N, T]) of one prediction file, shapes checked against the
    ground-truth clip's (N, T) from the npy headers before any data is read."""
    n, t = shape
    arrays = _load_npz(url, _PREDICTION_SPEC, optional=("visibles", "occluded"), storage_options=storage_options,
                       dims={"N": n, "T": t}, dims_from=f"the ground-truth clip {truth_file}")
    if "visibles" not in arrays and "occluded" not in arrays:
        raise ValueError(f"{url}: needs 'visibles' or 'occluded' [N, T] = {(n, t)}; has {sorted(arrays)}")
    visibles = _flags(arrays["visibles"], url, "visibles") if "visibles" in arrays else None
    if "occluded" in arrays:
        occluded = _flags(arrays["occluded"], url, "occluded")
        if visibles is not None and (visibles == occluded).any():
            n_bad, t_bad = (int(i) for i in np.argwhere(visibles == occluded)[0])
            raise ValueError(f"{url}: has both 'visibles' and 'occluded' and they disagree (track {n_bad}, frame "
                             f"{t_bad}: visible {bool(visibles[n_bad, t_bad])}, occluded "
                             f"{bool(occluded[n_bad, t_bad])}); keep one")
        visibles = ~occluded if visibles is None else visibles
    return arrays["tracks"], visibles


def _video_size(url: str, storage_options: dict | None) -> tuple[int, int]:
    """(width, height) of a clip file's ``video`` [T, H, W, 3], from the npy header only."""
    from drivetrack.storage import NpzReader

    with NpzReader(url, url, storage_options) as npz:
        if "video" not in npz:
            raise ValueError(f"{url}: has no 'video' array to take the image size from; pass image_size")
        shape = npz.header("video").shape
    if len(shape) != 4 or shape[1] < 1 or shape[2] < 1:
        raise ValueError(f"{url}: video has shape {shape}, expected (T, H, W, 3) to take the image size from")
    return int(shape[2]), int(shape[1])


def score_predictions(release_or_out_url: str, predictions_url: str, split: str | None = None,
                      query_modes: tuple[str, ...] = QUERY_MODES, stride: int = 5,
                      max_queries: int | None = DEFAULT_MAX_QUERIES, resize_to: tuple[int, int] | None = None,
                      allow_missing: bool = False, storage_options: dict | None = None) -> Evaluation:
    """Score a tracker's predictions against a release (or annotation folder) as ground truth.

    Args:
        release_or_out_url: folder holding ``waymo_*.npz`` clips (any depth; TAPVid-3D copies skipped).
        predictions_url: folder of npz files with the *same file names* (any depth), each with
            ``tracks`` float [N, T, 2] pixels (x, y) at the clip's resolution and ``visibles``
            (or ``occluded``) bool (or 0/1) [N, T], track n answering the query of ground-truth
            track n. Each file's npy headers are checked (dtype, shape = the ground-truth clip's
            N and T, declared size) before its data is read; NaN or any value other than 0/1
            in a flag array is an error; a non-finite predicted position where the truth is
            visible is a miss and an infinite pixel error, counted per clip and in the summary
            (``num_nonfinite_at_visible``, ``num_clips_nonfinite``).
        resize_to: (width, height) to rescale both to before scoring (TAP-Vid uses 256 x 256);
            None scores at the clip's own resolution.
        allow_missing: skip clips without a prediction (counted in the summary) instead of raising.
    """
    files = find_annotation_files(release_or_out_url, split, storage_options)
    if not files:
        raise FileNotFoundError(f"no clip files waymo_*.npz under {release_or_out_url}"
                                + (f" for split {split!r}" if split else ""))
    predictions = _prediction_index(predictions_url, storage_options)
    names = [posixpath.basename(f.relpath) for f in files]
    missing = [n for n in names if n not in predictions]
    if missing and not allow_missing:
        raise FileNotFoundError(f"predictions folder {predictions_url} has no file for {len(missing)} of "
                                f"{len(files)} clips, e.g. {missing[:3]}")
    rows: list[dict] = []
    errors: list[np.ndarray] = []
    for file, name in zip(files, names):
        if name not in predictions:
            continue
        gt_tracks, gt_visibles = _read_truth(file, storage_options)
        pred_tracks, pred_visibles = _read_prediction(predictions[name], gt_visibles.shape, file.relpath,
                                                      storage_options)
        pred_tracks = pred_tracks.astype(np.float64)
        if resize_to is not None:
            size = _video_size(file.url, storage_options)
            gt_tracks = rescale_points(gt_tracks, size, resize_to)
            with np.errstate(over="ignore", invalid="ignore"):
                pred_tracks = rescale_points(pred_tracks, size, resize_to)
        clip_errors, nonfinite = _errors_at_visible(pred_tracks, gt_tracks, gt_visibles)
        errors.append(clip_errors.astype(np.float32))
        base = {"split": file.split, "segment": file.segment, "camera": file.camera, "object_id": file.object_id,
                "file": file.relpath, "num_frames": int(gt_visibles.shape[1]), "num_tracks": int(gt_visibles.shape[0]),
                "num_gt_visible_points": int(gt_visibles.sum()), "num_pred_visible_points": int(pred_visibles.sum()),
                **pixel_error_stats(clip_errors), "num_nonfinite_at_visible": nonfinite}
        for mode in query_modes:
            rows.append({**base, "query_mode": mode,
                         **tapvid_scores(gt_tracks, gt_visibles, pred_tracks, pred_visibles, mode, stride,
                                         max_queries)})
    frame = pd.DataFrame(rows)
    summary = _summary("predictions_vs_release", frame, errors,
                       {"ground_truth": str(release_or_out_url), "predictions": str(predictions_url),
                        "query_modes": list(query_modes), "stride": stride,
                        "resolution": "native" if resize_to is None else f"{resize_to[0]}x{resize_to[1]}",
                        "num_clips_missing": len(missing)})
    return Evaluation(frame, _aggregate(frame), summary)


def iter_clips(files: Iterable[AnnotationFile], storage_options: dict | None = None) -> Iterator[Clip]:
    """Read clip files one at a time (for streaming into :func:`evaluate_clips`)."""
    for file in files:
        yield read_clip(file, storage_options)
