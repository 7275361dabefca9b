"""The per-segment job, run inside one coarse Prefect task on a Dask worker: ingestion, depth
jobs fanned out on the GPU queue, per-object track jobs, writing. Each step is one call of the
pipeline API (``drivetrack.annotate``); this module only routes work and records progress.

The work folder's layout and records are :mod:`drivetrack.release.work`.
"""
from __future__ import annotations

import contextlib
import errno
import functools
import time
import traceback

import fsspec

from drivetrack.release.work import DONE, progress_path, segment_dir, write_record

TRANSIENT_ERRNOS = {errno.ECONNRESET, errno.ECONNREFUSED, errno.ETIMEDOUT, errno.EAGAIN, errno.EPIPE,
                    errno.EHOSTUNREACH, errno.ENETUNREACH, errno.EIO}


def is_transient(exc: BaseException | None) -> bool:
    """Storage or network errors worth retrying: timeouts, dropped connections, throttling.
    Missing files, bad data and code errors are not."""
    seen = 0
    while exc is not None and seen < 5:
        if isinstance(exc, (TimeoutError, ConnectionError)):
            return True
        if isinstance(exc, OSError) and not isinstance(exc, (FileNotFoundError, PermissionError,
                                                              IsADirectoryError, NotADirectoryError)):
            if exc.errno in TRANSIENT_ERRNOS:
                return True
        name = type(exc).__name__
        if name in ("ClientConnectionError", "ServerDisconnectedError", "EndpointConnectionError",
                    "ReadTimeoutError", "ConnectTimeoutError", "SlowDown", "ServiceUnavailable"):
            return True
        text = str(exc)
        if any(code in text for code in ("SlowDown", "RequestTimeout", "InternalError", "503 Service Unavailable")):
            return True
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return False


#: The release status's stage of each core stage (drivetrack.annotate.STAGES): refinement and
#: planning are part of ingestion on the status board.
BOARD_STAGE = {"ingest": "ingest", "refine": "ingest", "plan": "ingest", "depth": "depth", "tracks": "tracks",
               "write": "write"}


class _Recorder:
    """``on_stage`` of the segment job: stage states mirrored to ``WORK/progress/...json`` as
    they change, under the status board's stage names (:data:`BOARD_STAGE`)."""

    def __init__(self, work, split, segment, key, storage_options):
        self.url = progress_path(work, split, segment)
        self.so = storage_options
        self.doc = {"split": split, "segment": segment, "key": key, "stages": {}, "updated": time.time()}
        self.frames = None

    def _flush(self):
        self.doc["updated"] = time.time()
        try:
            write_record(self.url, self.doc, self.so)
        except OSError:  # progress is advisory; the job's result is what counts
            pass

    def __call__(self, stage: str, state: str, info: dict) -> None:
        name = BOARD_STAGE[stage]
        now = time.time()
        entry = self.doc["stages"].get(name)
        if state == "running":
            if entry is None:
                self.doc["stages"][name] = {"state": "running", "started": now}
                self._flush()
            return
        if stage == "ingest" and state == "done":
            self.frames = info.get("count")   # the board's ingest count: frames, once planning is done
            return
        if state == "done" and stage in ("refine",):
            return
        entry.update(state=state, finished=now, seconds=now - entry["started"])
        if state == "failed":
            entry["error"] = info.get("error")
        elif stage == "plan":
            entry.update(count=self.frames, unit="frames")
        else:
            entry.update(info)
        self._flush()


def _dask_client():
    """A client for fanning out from inside a Dask worker task (secedes from the worker's
    thread pool while waiting), or the default client outside one."""
    from distributed import get_client, worker_client
    from distributed.worker import get_worker

    try:
        get_worker()
    except ValueError:
        return contextlib.nullcontext(get_client())
    return worker_client()


def _apply(fn, item):
    return fn(item)


# ---- the depth (GPU) queue: which completer, on which device --------------------------------------

GPU_COMPLETER = "nearest-torch"
"""What the default ``nearest`` completion runs as on a worker that sees CUDA: the same
nearest-neighbour fill (docs/depth.md: equal fill mask, equidistant ties may pick another
return), batched on the GPU."""


@functools.lru_cache(maxsize=1)
def worker_cuda() -> bool:
    """Whether this process sees a CUDA device torch can use (cached per process). No visible GPU
    (``CUDA_VISIBLE_DEVICES``/``nvidia-smi``) or no torch: False, without importing torch."""
    from flows.runtime import gpu_count

    if gpu_count() == 0:
        return False
    try:
        import torch
    except ImportError:
        return False
    return bool(torch.cuda.is_available())


def depth_choice(configured: str, *, cuda: bool) -> tuple[str, str]:
    """``(completer, device)`` for one depth job: on a worker that sees CUDA the default
    ``nearest`` runs as :data:`GPU_COMPLETER` on ``cuda:0`` (the worker's GPU: GPU workers are
    pinned with ``CUDA_VISIBLE_DEVICES``) and ``nearest-torch`` on ``cuda:0``; elsewhere
    ``nearest-torch`` runs on the CPU. Other completers run as configured, on the CPU."""
    if configured in ("nearest", GPU_COMPLETER) and cuda:
        return GPU_COMPLETER, "cuda:0"
    return configured, "cpu"


def depth_job(batch, config):
    """The unit of the GPU queue: complete one depth batch with :func:`depth_choice`'s completer
    on this worker. Returns ``(dense batch, {"completer", "device"})``."""
    import dataclasses

    from drivetrack.depth.stage import complete_depth_batch

    track = config.track
    completer, device = depth_choice(track.depth_completer, cuda=worker_cuda())
    if completer != track.depth_completer:
        options = {k: v for k, v in track.depth_completer_options.items() if k == "max_reach_px"}
        track = type(track).from_dict({**track.to_dict(), "depth_completer": completer,
                                       "depth_completer_options": options})
        config = dataclasses.replace(config, track=track)
    dense = complete_depth_batch(batch, config, device=device if completer == GPU_COMPLETER else None)
    return dense, {"completer": completer, "device": device}


def dask_map_fn(client, min_jobs: int = 2):
    """``map_fn(function, jobs)`` for :func:`drivetrack.annotate.track_segment` that fans object
    jobs out on the cluster: the function (it holds the segment context: scene and depth maps)
    is scattered once, each job ships only its small description."""
    def map_fn(fn, items):
        items = list(items)
        if len(items) < min_jobs:
            return [fn(i) for i in items]
        [fn_future] = client.scatter([fn], hash=False)
        futures = client.map(_apply, [fn_future] * len(items), items, pure=False)
        return client.gather(futures)
    return map_fn


def gpu_depth_fn(cfg, segment: str, gpu_wait_s: float = 0.0):
    """``depth_fn`` for :func:`drivetrack.annotate.run_segment_stages`: every batch is one job of
    the GPU queue (:func:`depth_job`); the info names per batch which completer ran on which
    device of which worker (docs/orchestration.md, Status)."""
    from flows.runtime import GPU, submit_resource_jobs

    def depth_fn(batches):
        done = []
        if batches:
            with _dask_client() as client:
                futures = submit_resource_jobs(client, depth_job, batches, cfg, resource=GPU,
                                               key_prefix=f"depth-{segment[:24]}", wait_s=gpu_wait_s)
                done = client.gather(futures)
        per_batch = [{"camera": int(b.camera), "frames": int(len(b.frames)), "completer": info["completer"],
                      "device": info["device"], "worker": addr, "seconds": round(secs, 3)}
                     for b, ((_, info), addr, secs) in zip(batches, done)]
        return [d[0][0] for d in done], {
            "worker": ",".join(sorted({d[1] for d in done})) or None,
            "completer": ",".join(sorted({b["completer"] for b in per_batch})) or None,
            "device": ",".join(sorted({b["device"] for b in per_batch})) or None, "batches": per_batch}
    return depth_fn


def cluster_map_fn(fn, items):
    """``map_fn`` for :func:`drivetrack.annotate.run_segment_stages`: the object jobs fanned out
    on the Dask cluster (:func:`dask_map_fn`) from inside the segment task."""
    with _dask_client() as client:
        return dask_map_fn(client)(fn, items)


def run_segment(source: str, split: str, segment: str, key: str, work: str, config: dict,
                storage_options: dict | None = None, gpu_wait_s: float = 0.0) -> dict:
    """Compute one segment into ``segment_dir(work, split, segment, key)`` with the core's
    staged pipeline (:func:`drivetrack.annotate.run_segment_stages`: depth on the GPU queue,
    object jobs on the cluster, progress in ``WORK/progress``) and write its completion record
    last. Returns the record (small, JSON-safe). Raises on failure after recording the failed
    stage and its error in the progress file."""
    from drivetrack.annotate import AnnotateConfig, run_segment_stages
    from flows.credentials import resolve_options

    storage_options = resolve_options(storage_options)  # references resolved here, on the worker
    cfg = AnnotateConfig.from_dict(config)
    out = segment_dir(work, split, segment, key)
    fs, root = fsspec.core.url_to_fs(out)
    root = root.rstrip("/")
    if fs.exists(root):
        fs.rm(root, recursive=True)  # leftovers of an interrupted attempt with this key
    recorder = _Recorder(work, split, segment, key, None)
    run_segment_stages(source, split, segment, out, cfg, storage_options=storage_options, map_fn=cluster_map_fn,
                       depth_fn=gpu_depth_fn(cfg, segment, gpu_wait_s), on_stage=recorder, hash_sources=False,
                       write_segment_stats=True, raise_errors=True)
    sizes = {p[len(root) + 1:]: int(i.get("size") or 0) for p, i in fs.find(root, detail=True).items()}
    record = {"status": "done", "key": key, "split": split, "segment": segment, "files": sizes,
              "stages": recorder.doc["stages"], "finished": time.time()}
    write_record(f"{out}/{DONE}", record)
    return record


def failure_summary(exc: BaseException) -> str:
    """One line (type: message) plus the innermost frame, for the status page."""
    tb = traceback.extract_tb(exc.__traceback__) if exc.__traceback__ else []
    where = f" (at {tb[-1].filename.rsplit('/', 1)[-1]}:{tb[-1].lineno})" if tb else ""
    return f"{type(exc).__name__}: {exc}{where}"
