"""The annotation pipeline: ingest -> depth -> tracks -> files and tables, one segment at a time.

Pure core (no Prefect): the ``drivetrack annotate`` command and the Prefect flows (``flows/``)
call these functions. Each stage is a separate function so that an orchestrator can place it
where it belongs (depth batches on GPU workers, object jobs fanned out on a cluster):

    scene = load_scene_for(source, split, segment, config)            # ingest
    plan = plan_segment(scene, config.track)                           # filters, object jobs
    batches = sparse_depth_batches(scene, config, plan)                # CPU, per (camera, frames)
    dense = [complete_depth_batch(b, config) for b in batches]         # the GPU-queue unit
    result = track_segment(scene, dense, config, plan)                 # per-object jobs
    write_segment_outputs(out, result)                                 # npz files + table rows

``annotate_segment`` runs them all for one segment and never raises for a bad segment: it returns
a failed :class:`SegmentResult` naming the error, so one bad segment never stops the others.

``annotate`` runs many segments; with ``workers >= 2`` each segment runs in its own worker process
(at most ``workers`` at once). A worker process that dies (a crash, the OOM killer, ``kill -9``)
fails only its own segment, after one retry in a fresh process. At the end of every run the
temporary ``.partial-*`` files in the output folder are removed (also those an earlier killed run
left), and so are the clip files of every segment recorded as failed.
"""
from __future__ import annotations

import hashlib
import json
import multiprocessing
import multiprocessing.connection
import os
import shutil
import signal
import tempfile
import time
import traceback
from collections import deque
from contextlib import ExitStack
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator

import fsspec
import numpy as np
import pandas as pd

from drivetrack import faults, parallel
from drivetrack.outputs import (LABEL_SPEED_ERR_COLUMNS, SPEED_ERR_COLUMNS, SPEED_PERCENTILES, TABLES,
                                SegmentStatus, Stage)
from drivetrack.names import check_name
from drivetrack.provenance import code_version_text, source_checksums
from drivetrack.scene import Scene
# The depth stage's pipeline unit, re-exported: `from drivetrack.annotate import DepthBatch,
# sparse_depth_batches, complete_depth_batch` is the documented pipeline API (docs/architecture.md).
from drivetrack.depth.stage import (DepthBatch, _depth_by_camera, complete_depth_batch, depth_jobs,
                                    sparse_depth_batch, sparse_depth_batches)
from drivetrack.storage import write_json
from drivetrack.tidy import remove_partial_files, remove_segment_clips
from drivetrack.tracks import (ObjectTracks, SegmentPlan, TrackConfig, object_stats, plan_segment,
                               prepare_segment, rejection_stats, run_object_job, segment_stats,
                               write_table)
from drivetrack.waymo.schema import LaserName

__all__ = ["AnnotateConfig", "DepthBatch", "SegmentResult", "load_scene_for", "sparse_depth_batches",
           "complete_depth_batch", "refine_scene", "track_segment", "segment_tables", "write_segment_outputs", "write_tables",
           "write_run_json", "run_segment_stages", "STAGES", "annotate_segment", "annotate",
           "remove_partial_files", "remove_segment_clips", "MAX_ATTEMPTS"]

#: A segment whose worker process dies is run again in a fresh process, at most this many times
#: in all; a deterministic failure (an error the segment reports) is not retried.
MAX_ATTEMPTS = 2

#: Prefix of the temporary files :func:`drivetrack.storage.atomic_local_path` writes beside a
#: local output file before moving it into place.

#: Pose refinement (drivetrack.refine) runs unless the configuration turns it off; per object it
#: keeps the labels wherever registration does not clearly improve on them (docs/refinement.md).
REFINE_BY_DEFAULT = True

#: Frames per depth batch when annotate computes the maps in its own process (``depth_fn`` not
#: given): at most this many, however large ``depth_batch`` (the GPU queue's unit) is. Four keeps
#: two threads busy to the end of a segment's ~50 maps and holds fewer 1920x1280 maps at once.
IN_PROCESS_DEPTH_BATCH = 4


@dataclass(frozen=True)
class AnnotateConfig:
    """Everything that decides the annotation of a segment (built once at the entry point).

    Attributes:
        track: the depth and track stage configuration (:class:`drivetrack.tracks.TrackConfig`).
        refine_poses: refine each object's per-frame pose from its own LiDAR before tracking
            (``drivetrack.refine``); falls back to the labels per object when untrustworthy.
    """
    track: TrackConfig = field(default_factory=TrackConfig)
    refine_poses: bool = REFINE_BY_DEFAULT
    refine_options: dict = field(default_factory=dict)

    def __post_init__(self):
        from drivetrack.refine import RefineConfig

        object.__setattr__(self, "refine_options", dict(self.refine_options))
        try:
            RefineConfig(**self.refine_options)
        except TypeError as error:
            raise ValueError(f"annotation config: refine_options: {error}") from None

    @property
    def depth_method(self) -> str:
        return self.track.depth_completer

    def refine_config(self):
        """The :class:`drivetrack.refine.RefineConfig` of ``refine_options``."""
        from drivetrack.refine import RefineConfig

        return RefineConfig(**self.refine_options)

    def to_dict(self) -> dict:
        return {"track": self.track.to_dict(), "refine_poses": self.refine_poses,
                "refine_options": dict(self.refine_options)}

    @classmethod
    def from_dict(cls, values: dict | None) -> "AnnotateConfig":
        values = dict(values or {})
        keys = {"track", "refine_poses", "refine_options"}
        unknown = sorted(set(values) - keys)
        if unknown:
            raise ValueError(f"annotation config: unknown keys {unknown}; expected {sorted(keys)}")
        return cls(track=TrackConfig.from_dict(values.get("track") or {}),
                   refine_poses=bool(values.get("refine_poses", REFINE_BY_DEFAULT)),
                   refine_options=dict(values.get("refine_options") or {}))

    def fingerprint(self) -> str:
        """sha256 of the canonical JSON of the configuration (not of the code version)."""
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()


@dataclass
class SegmentResult:
    """The outcome of one segment; tables are small pandas frames, files are URLs.

    ``status`` is ``done`` or ``failed``; ``error`` holds the message of a failure and
    ``stage`` the stage it happened in (ingest, refine, plan, depth, tracks, write, or ``worker``
    when its worker process died). ``attempts`` counts the processes the segment ran in and
    ``worker_deaths`` says how each dead one ended; ``source_stats`` holds what the reader
    dropped from the source as data (``Scene.source_stats``).
    """
    split: str
    segment: str
    status: str
    error: str = ""
    stage: str = ""
    objects: pd.DataFrame | None = None
    rejections: pd.DataFrame | None = None
    segment_row: pd.DataFrame | None = None
    files: list[str] = field(default_factory=list)
    source_files: dict[str, str] = field(default_factory=dict)
    source_sha256: dict[str, str] = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    source_stats: dict[str, int] = field(default_factory=dict)
    attempts: int = 1
    worker_deaths: list[str] = field(default_factory=list)
    tracks: list[ObjectTracks] = field(default_factory=list, repr=False)

    @property
    def num_tracks(self) -> int:
        return 0 if self.objects is None or self.objects.empty else int(self.objects["num_tracks"].sum())

    def summary(self) -> dict:
        """JSON-able summary for run.json and status pages (no arrays)."""
        return {"split": self.split, "segment": self.segment, "status": self.status, "error": self.error,
                "stage": self.stage, "num_files": len(self.files), "num_tracks": self.num_tracks,
                "num_objects": 0 if self.objects is None else int(len(self.objects)),
                "source_files": {k: {"url": v, "sha256": self.source_sha256.get(k)}
                                 for k, v in sorted(self.source_files.items())},
                "source_stats": dict(self.source_stats), "attempts": self.attempts,
                "worker_deaths": list(self.worker_deaths),
                "timings_s": {k: round(v, 3) for k, v in self.timings_s.items()}}


def load_scene_for(source: str, split: str, segment: str, config: AnnotateConfig,
                   storage_options: dict | None = None, refine: bool = True) -> Scene:
    """Ingest one segment with what the configuration needs (its cameras, every laser, both returns).

    The lasers and returns loaded are those the object point clouds (``lasers``, ``returns``)
    and the occlusion depth maps (``depth_lasers``, ``depth_returns``) use.
    With ``config.refine_poses`` (and ``refine``) the box labels of the objects that pass the
    planning filters are then refined from the LiDAR (:func:`refine_scene`), so every later stage
    sees the refined boxes.
    """
    from drivetrack.waymo.reader import load_scene

    lasers = sorted(set(config.track.laser_values) | set(config.track.depth_laser_values))
    if len(lasers) == len(LaserName) - 1:   # every lidar (all but UNKNOWN): whatever is calibrated
        lasers = None
    returns = tuple(sorted(set(config.track.returns) | set(config.track.depth_returns)))
    scene = load_scene(source, split, segment, cameras=config.track.camera_values, lasers=lasers,
                       returns=returns, with_images=True, storage_options=storage_options)
    return refine_scene(scene, config) if (refine and config.refine_poses) else scene


def refine_scene(scene: Scene, config: AnnotateConfig) -> Scene:
    """The scene with the boxes of the annotated objects, and of the objects that may hide part of
    them (``RefineConfig.occluders``), refined from their own LiDAR.

    Objects whose registration is not trustworthy keep their labels (the reason is recorded);
    ``scene.box_refinement`` holds one summary per refined-or-kept object for the tables.
    """
    import dataclasses

    from drivetrack.refine import refine_scene_boxes

    # Only objects that pass the planning filters with their labels (type, camera, frames in view,
    # distance) are annotated; label noise of centimetres does not move an object across these
    # coarse filters.
    # (Which clips pass needs no point selection: the costly part of planning a full segment.)
    rough = plan_segment(scene, config.track, select_points=False)
    object_ids = {job.object_id for job in rough.jobs}
    refine_config = config.refine_config()
    if object_ids and refine_config.occluders:
        # and the objects that may hide part of them: the occlusion z-buffer draws those by their
        # boxes, and a noisy box blurs an occluder's surface as it would a tracked object's
        from drivetrack.tracks.core import occluding_objects

        object_ids |= occluding_objects(rough)
    object_ids = sorted(object_ids)
    if not object_ids:
        return scene
    label_offset_s = None
    if config.track.time_model == "trajectory":      # returns are registered at the labels' time
        from drivetrack.tracks.trajectory import carry_label_times, scene_label_times

        label_offset_s = scene_label_times(scene, config.track)[0]
    boxes, results = refine_scene_boxes(scene, refine_config, object_ids,
                                        lasers=config.track.laser_values, returns=config.track.returns,
                                        compensate_sweep_motion=config.track.compensate_sweep_motion,
                                        label_offset_s=label_offset_s)
    refined = dataclasses.replace(scene, boxes=boxes, box_labels=scene.boxes,
                                  box_refinement={oid: r.summary() for oid, r in results.items()})
    if label_offset_s is not None:
        carry_label_times(scene, refined, config.track)
    return refined


def track_segment(scene: Scene, dense_batches: Iterable[DepthBatch], config: AnnotateConfig,
                  plan: SegmentPlan | None = None,
                  map_fn: Callable[[Callable, list], Iterable[ObjectTracks]] | None = None) -> list[ObjectTracks]:
    """Run every object job of a segment against its completed depth maps.

    ``map_fn(function, jobs)`` fans the jobs out (default: the built-in ``map``, in process),
    largest first; the results are in plan order. The segment context (scene, depth maps) is
    shared by reference, never copied per job.
    """
    plan = plan if plan is not None else plan_segment(scene, config.track)
    ctx = prepare_segment(scene, config.track, depth=_depth_by_camera(dense_batches), plan=plan)
    job = _ObjectJobRunner(ctx)
    jobs = list(plan.jobs)
    # largest first (candidate points x frames), so that a pool does not start the largest job
    # last and wait for it alone; the results come back in plan order
    order = sorted(range(len(jobs)), key=lambda i: -jobs[i].num_points * len(jobs[i].frames))
    results: list = [None] * len(jobs)
    for i, tracks in zip(order, (map_fn or map)(job, [jobs[i] for i in order])):
        results[i] = tracks
    return results


class _ObjectJobRunner:
    """Picklable ``job -> run_object_job(ctx, job)`` (a closure would not cross processes)."""

    def __init__(self, ctx):
        self.ctx = ctx

    def __call__(self, job):
        return run_object_job(self.ctx, job)


def write_segment_outputs(out_url: str, split: str, results: list[ObjectTracks]) -> dict[tuple[int, str], list[str]]:
    """Write every accepted clip as release layout v2 tables (:func:`drivetrack.compact.write.write_segment_tables`:
    the segment's clips table and one frames table per camera); (camera, object_id) -> written URLs
    (its clips table first).

    If a write fails, the files already written for this segment are removed before the error
    propagates, so a failed segment leaves no partial output behind.
    """
    from drivetrack.compact.write import write_segment_tables
    from drivetrack.outputs import clips_table_path, frames_table_path
    from drivetrack.tracks.writers import clip_stem

    accepted = []
    for tracks in results:
        if tracks.rejection is None and tracks.num_tracks > 0:
            accepted.append((clip_stem(tracks), tracks))
    try:
        return write_segment_tables(out_url, split, accepted)
    except BaseException:
        if accepted:
            segment = accepted[0][1].segment
            rels = {clips_table_path(split, segment)} | {
                frames_table_path(split, segment, t.camera_name) for _, t in accepted}
            for rel in rels:
                fs, path = fsspec.core.url_to_fs(f"{out_url.rstrip('/')}/{rel}")
                if fs.exists(path):
                    fs.rm(path)
        raise


#: ``on_stage(stage, state, info)`` of :func:`run_segment_stages`: ``stage`` one of :data:`STAGES`,
#: ``state`` ``running``, ``done`` or ``failed``; ``info`` what the stage reports (``count`` and
#: ``unit`` when done, whatever the depth function adds, ``error`` when failed).
StageCallback = Callable[[str, str, dict], None]

#: The stages of one segment, in order (``refine`` runs only with ``config.refine_poses``).
STAGES = (Stage.INGEST, Stage.REFINE, Stage.PLAN, Stage.DEPTH, Stage.TRACKS, Stage.WRITE)


def run_segment_stages(source: str, split: str, segment: str, out_url: str, config: AnnotateConfig, *,
                       storage_options: dict | None = None,
                       map_fn: Callable[[Callable, list], Iterable[ObjectTracks]] | None = None,
                       depth_fn: Callable[[list[DepthBatch]], tuple[list[DepthBatch], dict]] | None = None,
                       on_stage: StageCallback | None = None, hash_sources: bool = True,
                       write_segment_stats: bool = False, raise_errors: bool = False,
                       keep_tracks: bool = False, threads: int = 1) -> SegmentResult:
    """One segment through every stage (:data:`STAGES`): ingest, refine, plan, depth, tracks, write.

    The one staged pipeline of a segment, for the CLI (:func:`annotate_segment`) and the release
    flow's segment task, which injects where the work runs:

    - ``map_fn(function, jobs)`` fans the per-object track jobs out (default: in process);
    - ``depth_fn(sparse_batches) -> (dense_batches, info)`` completes the depth batches, in order
      (default: :func:`complete_depth_batch` in process; the flow's GPU queue), ``info`` is
      reported with the depth stage;
    - ``on_stage(stage, state, info)`` hears every stage start, finish and failure (progress).

    ``threads``: with 2 or more, the depth maps (sparse and completed) of the cameras' batches and,
    unless ``map_fn`` is given, the object jobs run in a pool of that many threads (their kernels
    release the GIL), and so do the core's per-frame and per-clip loops that use
    :func:`drivetrack.parallel.pool_map`; the results are the same and in the same order as with one.

    ``hash_sources``: record the sha256 of each source file (``run.json``). ``write_segment_stats``:
    also write this segment's ``stats/*.parquet`` into ``out_url`` (a per-segment folder).
    A failure comes back as a failed :class:`SegmentResult` naming the stage and the error; with
    ``raise_errors`` the error itself is raised after ``on_stage`` heard it.
    """
    result = SegmentResult(split=split, segment=segment, status=SegmentStatus.RUNNING)
    pool = ThreadPoolExecutor(max_workers=threads) if threads >= 2 else None
    in_threads = pool.map if pool is not None else map
    stack = ExitStack()     # the pool also serves the core's per-frame loops (drivetrack.parallel)
    plan = None
    tracks: list[ObjectTracks] = []
    stage, start = Stage.INGEST, time.perf_counter()

    def begin(name: str) -> None:
        nonlocal stage, start
        stage, start = name, time.perf_counter()
        if on_stage:
            on_stage(name, "running", {})

    def end(info: dict) -> None:
        release_free_heap()     # each stage frees its temporaries; give the pages back before the next
        result.timings_s[stage] = time.perf_counter() - start
        if on_stage:
            on_stage(stage, "done", info)

    try:
        stack.enter_context(parallel.using(in_threads if pool is not None else None))
        begin(Stage.INGEST)
        scene = load_scene_for(source, split, segment, config, storage_options, refine=False)
        result.source_files = dict(scene.source_files)
        result.source_stats = dict(scene.source_stats)
        if hash_sources:
            result.source_sha256 = source_checksums(scene.source_files, storage_options)
        end({"count": int(scene.num_frames), "unit": "frames"})

        if config.refine_poses:
            begin(Stage.REFINE)
            scene = refine_scene(scene, config)
            end({"count": len(scene.box_refinement), "unit": "objects"})

        begin(Stage.PLAN)
        plan = plan_segment(scene, config.track)
        end({"count": len(plan.jobs), "unit": "object jobs"})

        begin(Stage.DEPTH)
        if depth_fn is None:     # each batch completed as soon as it is projected: one sparse batch per thread
            # in process there is no queue to feed: small batches balance the threads and hold
            # fewer full-size maps at once (the maps do not depend on the batching)
            jobs = depth_jobs(scene, config.track, plan, batch=min(config.track.depth_batch, IN_PROCESS_DEPTH_BATCH))
            dense, info = list(in_threads(lambda job: complete_depth_batch(sparse_depth_batch(scene, config, job, plan), config),
                                          jobs)), {}
        else:
            batches = sparse_depth_batches(scene, config, plan, map_fn=in_threads)
            dense, info = depth_fn(batches)
            del batches
        end({"count": len(dense), "unit": "depth batches", **info})

        begin(Stage.TRACKS)
        # handed over as a generator: the batches are let go as each camera's maps are joined
        tracks = track_segment(scene, _handed_over(dense), config, plan, map_fn=map_fn or (in_threads if pool else None))
        end({"count": sum(1 for t in tracks if t.rejection is None and t.num_tracks > 0), "unit": "object clips"})

        begin(Stage.WRITE)
        written = write_segment_outputs(out_url, split, tracks)
        result.files = sorted({u for urls in written.values() for u in urls})
        result.objects, result.rejections, result.segment_row = segment_tables(out_url, scene, plan, tracks, written)
        if write_segment_stats:
            write_tables(out_url, [result])
        result.status, result.stage = SegmentStatus.DONE, ""
        end({"count": len(result.files), "unit": "files"})
    except Exception as error:  # isolate the segment: report (and raise only when asked)
        result.status, result.stage = SegmentStatus.FAILED, stage
        result.error = f"{type(error).__name__}: {error}"
        result.traceback = traceback.format_exc()  # type: ignore[attr-defined]
        planned = stage not in (Stage.INGEST, Stage.REFINE, Stage.PLAN)
        result.segment_row = segment_stats(split, segment, plan if planned else None,
                                           (), status=SegmentStatus.FAILED, error=f"[{stage}] {result.error}")
        if on_stage:
            on_stage(stage, "failed", {"error": result.error})
        if raise_errors:
            raise
    finally:
        stack.close()
        if pool is not None:
            pool.shutdown(wait=True)
    if keep_tracks:
        result.tracks = tracks
    return result


def release_free_heap() -> None:
    """Return the C heap's free pages to the system (glibc ``malloc_trim(0)``; elsewhere a no-op).

    numpy's and pyarrow's temporaries of a stage (range-image batches, [M, 3] point copies, depth
    maps) are freed into glibc's heap, which keeps most of them mapped: after the ingest of a
    full-size segment about 0.35 GiB of the process's RSS is such free memory. Trimming between
    stages keeps the peak to what the next stage really holds (docs/benchmarks.md, issue 18).
    """
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def _malloc_trim():
    global _MALLOC_TRIM
    if _MALLOC_TRIM is None:
        _MALLOC_TRIM = False
        try:
            import ctypes
            import ctypes.util

            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            _MALLOC_TRIM = libc.malloc_trim
            _MALLOC_TRIM.argtypes, _MALLOC_TRIM.restype = [ctypes.c_size_t], ctypes.c_int
        except (OSError, AttributeError):   # not glibc (macOS, musl without it): nothing to trim
            _MALLOC_TRIM = False
    return _MALLOC_TRIM or None


_MALLOC_TRIM = None


def _handed_over(items: list) -> Iterator:
    """Yield and forget the items of ``items`` (the list is emptied), so each can be freed once used."""
    items.reverse()
    while items:
        yield items.pop()


def annotate_segment(source: str, split: str, segment: str, out_url: str, config: AnnotateConfig,
                     storage_options: dict | None = None, keep_tracks: bool = False,
                     threads: int | None = None) -> SegmentResult:
    """Ingest, complete depth, track and write one segment in this process
    (:func:`run_segment_stages`, in ``threads`` threads; default :func:`available_cores`);
    failures come back as a result."""
    return run_segment_stages(source, split, segment, out_url, config, storage_options=storage_options,
                              keep_tracks=keep_tracks, threads=available_cores() if threads is None else threads)


def available_cores() -> int:
    """The CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:      # not on Linux
        return max(1, os.cpu_count() or 1)


def segment_tables(out_url: str, scene: Scene, plan: SegmentPlan, tracks: list[ObjectTracks],
                   written: dict[tuple[int, str], list[str]]) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """``(objects, rejections, segment_row)`` tables of a tracked segment.

    ``written`` is :func:`write_segment_outputs`' result; object rows name their DriveTrack file
    relative to ``out_url``, carry the ``refine_*`` columns of the pose refinement, if any, and the
    ``label_speed_err_p*`` columns: the speed-error percentiles of the same tracks under the
    labelled poses (equal to ``speed_err_p*`` when the labels were used as read).
    """
    files = {key: _relative(out_url, urls[0]) for key, urls in written.items()}
    objects = _with_label_consistency(object_stats(tracks, files), scene, tracks)
    objects = _with_refinement(objects, scene.box_refinement)
    return objects, rejection_stats(plan, tracks), segment_stats(scene.split, scene.segment, plan, tracks)


def _with_label_consistency(objects: pd.DataFrame, scene: Scene, tracks: list[ObjectTracks]) -> pd.DataFrame:
    """Objects table plus ``label_speed_err_p*``: speed-error percentiles under the labelled poses."""
    from drivetrack.tracks.consistency import label_speed_errors, sorted_return_keys

    columns = list(LABEL_SPEED_ERR_COLUMNS)
    if objects.empty:
        return objects.assign(**{c: pd.Series(dtype=float) for c in columns})
    if scene.box_labels is None and all(t.time_model == "velocity" for t in tracks):
        # the tracks were carried with the labels themselves: same figures
        return objects.assign(**{c: objects[s] for c, s in zip(columns, SPEED_ERR_COLUMNS)})
    # refined poses, or the trajectory (which levels yaw-only labels' ego tilt, docs/time.md)
    labels = scene.box_labels if scene.box_labels is not None else scene.boxes
    keys = sorted_return_keys(scene.lidar, f"segment {scene.segment!r}")     # one table for every clip

    def percentiles(t: ObjectTracks) -> np.ndarray:
        errors = label_speed_errors(scene, labels, t, keys)
        errors = errors[np.isfinite(errors)]
        return (np.percentile(errors, SPEED_PERCENTILES) if errors.size
                else np.full(len(SPEED_PERCENTILES), np.nan))

    accepted = [t for t in tracks if t.rejection is None]
    rows = {(t.camera_name, t.object_id): p
            for t, p in zip(accepted, parallel.pool_map(percentiles, accepted))}   # clips on the segment's pool
    values = np.array([rows.get((c, o), np.full(len(SPEED_PERCENTILES), np.nan))
                       for c, o in zip(objects["camera"], objects["object_id"])], dtype=float)
    return objects.assign(**{c: values[:, i] for i, c in enumerate(columns)})


def _with_refinement(objects: pd.DataFrame, refinement: dict[str, dict]) -> pd.DataFrame:
    """Objects table plus the ``refine_*`` columns of each object's pose refinement (if any)."""
    if not refinement or objects.empty:
        return objects
    table = pd.DataFrame.from_dict(refinement, orient="index")
    table.index.name = "object_id"
    return objects.merge(table.reset_index(), on="object_id", how="left")


def _relative(root: str, url: str) -> str:
    root = root.rstrip("/") + "/"
    return url[len(root):] if url.startswith(root) else url


def write_tables(out_url: str, results: list[SegmentResult]) -> dict[str, str]:
    """``stats/objects.parquet``, ``stats/segments.parquet``, ``stats/rejections.parquet``."""
    def concat(frames, columns):
        frames = [f for f in frames if f is not None and not f.empty]
        return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=list(columns))

    base = out_url.rstrip("/")
    frames = {"objects": [r.objects for r in results], "segments": [r.segment_row for r in results],
              "rejections": [r.rejections for r in results]}
    tables = {name: concat(frames[name], columns) for name, columns in TABLES.items()}
    return {name: write_table(f"{base}/stats/{name}.parquet", table) for name, table in tables.items()}


def write_run_json(out_url: str, source: str, config: AnnotateConfig, results: list[SegmentResult],
                   extra: dict | None = None) -> str:
    """``run.json``: configuration, code version, source and every segment with its checksums."""
    run = {"format": "drivetrack-run/1", "code_version": code_version_text(), "source": source,
           "config": config.to_dict(), "config_fingerprint": config.fingerprint(),
           "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
           "segments": [r.summary() for r in results], **(extra or {})}
    return write_json(f"{out_url.rstrip('/')}/run.json", run, indent=2, sort_keys=True)


def _annotate_one(args):
    return annotate_segment(*args)


def _segment_worker(conn, args, tmp_dir: str) -> None:
    """Body of one worker process: annotate one segment, send the result back, exit.

    Temporary files of this process go to ``tmp_dir`` (removed by the parent at the end of the
    run, also when this process is killed).
    """
    os.makedirs(tmp_dir, exist_ok=True)
    os.environ["TMPDIR"] = tmp_dir
    tempfile.tempdir = tmp_dir
    faults.enter_worker()
    result = annotate_segment(*args)
    conn.send(result)
    conn.close()


def _describe_exit(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        try:
            return f"killed by signal {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exited with code {exitcode} before sending its result"


def _worker_failed(split: str, segment: str, deaths: list[str]) -> SegmentResult:
    error = (f"the worker process of segment {segment!r} died in each of {len(deaths)} attempts: "
             + "; ".join(f"attempt {i + 1} {d}" for i, d in enumerate(deaths)))
    r = SegmentResult(split, segment, SegmentStatus.FAILED, error=error, stage=Stage.WORKER, attempts=len(deaths),
                      worker_deaths=list(deaths))
    r.segment_row = segment_stats(split, segment, None, (), status=SegmentStatus.FAILED,
                                  error=f"[{Stage.WORKER}] {error}")
    return r


def _run_in_processes(jobs: list[tuple], workers: int, tmp_root: str,
                      on_result: Callable[[SegmentResult], None] | None) -> dict[str, SegmentResult]:
    """Run each job (``annotate_segment`` arguments) in its own process, ``workers`` at a time.

    A process that ends without sending a result (killed, crashed) is attributed to its own
    segment only; that segment runs again in a fresh process, up to :data:`MAX_ATTEMPTS` in all.
    """
    ctx = multiprocessing.get_context()
    pending = deque(jobs)
    deaths: dict[str, list[str]] = {}
    running: dict = {}            # receiving connection -> (job, process)
    out: dict[str, SegmentResult] = {}
    try:
        while pending or running:
            while pending and len(running) < workers:
                job = pending.popleft()
                segment = job[2]
                attempt = len(deaths.get(segment, ())) + 1
                receive, send = ctx.Pipe(duplex=False)
                process = ctx.Process(target=_segment_worker, name=f"drivetrack-annotate-{segment}",
                                      args=(send, job, os.path.join(tmp_root, f"{segment}.{attempt}")))
                process.start()
                send.close()          # the child holds the only writing end: EOF when it dies
                running[receive] = (job, process)
            for receive in multiprocessing.connection.wait(list(running)):
                job, process = running.pop(receive)
                segment = job[2]
                try:
                    result = receive.recv()
                except (EOFError, OSError):
                    result = None
                finally:
                    receive.close()
                process.join()
                if result is None:
                    deaths.setdefault(segment, []).append(_describe_exit(process.exitcode))
                    if len(deaths[segment]) < MAX_ATTEMPTS:
                        pending.appendleft(job)   # a fresh process; the others keep running
                        continue
                    result = _worker_failed(job[1], segment, deaths[segment])
                else:
                    result.attempts = len(deaths.get(segment, ())) + 1
                    result.worker_deaths = list(deaths.get(segment, ()))
                out[segment] = result
                if on_result:
                    on_result(result)
    finally:
        for job, process in running.values():   # interrupted: stop the workers this run started
            process.terminate()
        for job, process in running.values():
            process.join()
    return out


def annotate(source: str, split: str, segments: list[str], out_url: str, config: AnnotateConfig,
             workers: int = 1, storage_options: dict | None = None,
             on_result: Callable[[SegmentResult], None] | None = None,
             threads: int | None = None) -> list[SegmentResult]:
    """Annotate ``segments`` (in ``workers`` processes), then write the tables and ``run.json``.

    Each segment runs its depth maps, object jobs and per-frame loops in ``threads`` threads (default: the
    available cores divided among the workers, at least 1).

    A failed segment is reported through its result and ``on_result`` and does not stop the
    others. Results come back in the order of ``segments``. With ``workers >= 2`` every segment
    runs in its own process; a segment whose process dies is retried once in a fresh process and
    is then recorded failed (stage ``worker``, the error naming the signal or exit code), the
    other segments' results are kept. At the end (also when interrupted) the ``.partial-*``
    files in ``out_url`` are removed (:func:`remove_partial_files`), and the clip files of the
    failed segments are removed from ``out_url`` before the tables are written
    (:func:`remove_segment_clips`). ``storage_options`` apply to the source; the output folder
    is reached with fsspec's defaults. One run per output folder at a time.

    Raises :class:`drivetrack.names.InvalidNameError` before any work when the split or a
    segment id cannot be part of a path.
    """
    check_name("split", split, "the split to annotate")
    for segment in segments:
        check_name("segment", segment, f"the segments to annotate of split {split!r}")
    if threads is None:
        threads = max(1, available_cores() // max(1, workers))
    if threads < 1:
        raise ValueError(f"threads: expected at least 1, found {threads}")
    jobs = [(source, split, s, out_url, config, storage_options, False, threads) for s in dict.fromkeys(segments)]
    by_segment: dict[str, SegmentResult] = {}
    tmp_root = tempfile.mkdtemp(prefix="drivetrack-annotate-")
    try:
        if workers <= 1:
            for job in jobs:
                by_segment[job[2]] = r = _annotate_one(job)
                if on_result:
                    on_result(r)
        else:
            by_segment = _run_in_processes(jobs, workers, tmp_root, on_result)
        results = [by_segment[s] for s in segments]
        failed = [r.segment for r in results if r.status != SegmentStatus.DONE]
        keep = [_relative(out_url, url) for r in results if r.status == SegmentStatus.DONE for url in r.files]
        remove_segment_clips(out_url, split, failed, keep)
        for r in results:
            if r.status != SegmentStatus.DONE:
                r.files = []
    finally:
        remove_partial_files(out_url)
        shutil.rmtree(tmp_root, ignore_errors=True)
    write_tables(out_url, results)
    write_run_json(out_url, source, config, results)
    return results
