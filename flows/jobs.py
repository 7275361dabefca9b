"""The per-segment job, run inside one coarse Prefect task on a Dask worker: ingestion, depth
jobs fanned out on the GPU queue, per-object track jobs, writing. Each step is one call of the
pipeline API (``drivetrack.annotate``); this module only routes work and records progress.

Work folder layout (any fsspec URL; shared storage when the cluster is remote)::

    WORK/segments/{split}/{segment}/{key16}/      one segment's outputs for one content key
        {split}/...npz, stats/*.parquet             (written by the pipeline API)
        _done.json                                  completion record, written last
    WORK/progress/{split}/{segment}.json          live stage states of the running job
"""
from __future__ import annotations

import contextlib
import errno
import functools
import inspect
import json
import time
import traceback

import fsspec

DONE = "_done.json"
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


def _fs(url: str, storage_options: dict | None):
    fs, path = fsspec.core.url_to_fs(str(url), **(storage_options or {}))
    return fs, path.rstrip("/")


def segment_dir(work: str, split: str, segment: str, key: str) -> str:
    return f"{str(work).rstrip('/')}/segments/{split}/{segment}/{key[:16]}"


def progress_path(work: str, split: str, segment: str) -> str:
    return f"{str(work).rstrip('/')}/progress/{split}/{segment}.json"


def write_json(url: str, doc: dict, storage_options: dict | None = None) -> None:
    """Write through a temporary name and a move (a reader never sees half a record)."""
    fs, path = _fs(url, storage_options)
    fs.makedirs(path.rsplit("/", 1)[0], exist_ok=True)
    tmp = f"{path}.{time.time_ns()}.tmp"
    with fs.open(tmp, "w") as f:
        json.dump(doc, f, indent=1, default=str)
    fs.mv(tmp, path)


def read_json(url: str, storage_options: dict | None = None) -> dict | None:
    fs, path = _fs(url, storage_options)
    try:
        with fs.open(path, "r") as f:
            return json.load(f)
    except FileNotFoundError:
        return None
    except json.JSONDecodeError:
        return None


def completion_record(work: str, split: str, segment: str, key: str,
                      storage_options: dict | None = None) -> dict | None:
    """The record of a finished job with this key, if it exists, matches the key and every file
    it lists is present with its size; else None (the segment must be computed)."""
    seg_dir = segment_dir(work, split, segment, key)
    rec = read_json(f"{seg_dir}/{DONE}", storage_options)
    if not rec or rec.get("key") != key or rec.get("status") != "done":
        return None
    fs, root = _fs(seg_dir, storage_options)
    try:
        sizes = {p[len(root) + 1:]: int(i.get("size") or 0) for p, i in fs.find(root, detail=True).items()}
    except FileNotFoundError:
        return None
    for rel, size in (rec.get("files") or {}).items():
        if sizes.get(rel) != size:
            return None
    return rec


class _Recorder:
    """Stage states of one segment job, mirrored to ``WORK/progress/...json`` as they change."""

    def __init__(self, work, split, segment, key, storage_options):
        self.url = progress_path(work, split, segment)
        self.so = storage_options
        self.doc = {"split": split, "segment": segment, "key": key, "stages": {}, "updated": time.time()}

    def _flush(self):
        self.doc["updated"] = time.time()
        try:
            write_json(self.url, self.doc, self.so)
        except OSError:  # progress is advisory; the job's result is what counts
            pass

    @contextlib.contextmanager
    def stage(self, name: str):
        info = {"state": "running", "started": time.time()}
        self.doc["stages"][name] = info
        self._flush()
        try:
            yield info
        except BaseException as e:
            info.update(state="failed", finished=time.time(), error=f"{type(e).__name__}: {e}")
            info["seconds"] = info["finished"] - info["started"]
            self._flush()
            raise
        info.update(state="done", finished=time.time())
        info["seconds"] = info["finished"] - info["started"]
        self._flush()


def _len(x) -> int | None:
    try:
        return len(x)
    except TypeError:
        return None


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


def run_segment(source: str, split: str, segment: str, key: str, work: str, config: dict,
                storage_options: dict | None = None, gpu_wait_s: float = 0.0) -> dict:
    """Compute one segment into ``segment_dir(work, split, segment, key)`` and write its
    completion record last. Returns the record (small, JSON-safe). Raises on failure after
    recording the failed stage and its error in the progress file."""
    from drivetrack import annotate as core
    from drivetrack.depth.stage import sparse_depth_batches
    from drivetrack.tracks import plan_segment
    from flows.runtime import GPU, submit_resource_jobs

    from flows.credentials import resolve_options

    storage_options = resolve_options(storage_options)  # references resolved here, on the worker
    cfg = core.AnnotateConfig.from_dict(config)
    out = segment_dir(work, split, segment, key)
    fs, root = _fs(out, storage_options=None)
    if fs.exists(root):
        fs.rm(root, recursive=True)  # leftovers of an interrupted attempt with this key
    rec = _Recorder(work, split, segment, key, None)
    with rec.stage("ingest") as st:
        scene = core.load_scene_for(source, split, segment, cfg, storage_options=storage_options)
        plan = plan_segment(scene, cfg.track)
        st.update(count=int(scene.num_frames), unit="frames")
    with rec.stage("depth") as st:
        batches = sparse_depth_batches(scene, cfg, plan)
        if batches:
            with _dask_client() as client:
                futures = submit_resource_jobs(client, depth_job, batches, cfg, resource=GPU,
                                               key_prefix=f"depth-{segment[:24]}", wait_s=gpu_wait_s)
                done = client.gather(futures)
        else:
            done = []
        dense = [d[0][0] for d in done]
        # per batch: which completer on which device of which worker (docs/orchestration.md, Status)
        per_batch = [{"camera": int(b.camera), "frames": int(len(b.frames)), "completer": info["completer"],
                      "device": info["device"], "worker": addr, "seconds": round(secs, 3)}
                     for b, ((_, info), addr, secs) in zip(batches, done)]
        st.update(count=len(batches), unit="depth batches", worker=",".join(sorted({d[1] for d in done})) or None,
                  completer=",".join(sorted({b["completer"] for b in per_batch})) or None,
                  device=",".join(sorted({b["device"] for b in per_batch})) or None, batches=per_batch)
        del batches
    with rec.stage("tracks") as st:
        with _dask_client() as client:
            tracks = core.track_segment(scene, dense, cfg, plan, map_fn=dask_map_fn(client))
        del dense
        st.update(count=sum(1 for t in tracks if t.rejection is None and t.num_tracks > 0), unit="object clips")
    with rec.stage("write") as st:
        written = core.write_segment_outputs(out, split, tracks, cfg.track.writers)
        objects, rejections, segment_row = core.segment_tables(out, scene, plan, tracks, written)
        result = core.SegmentResult(split=split, segment=segment, status="done", objects=objects,
                                    rejections=rejections, segment_row=segment_row)
        core.write_tables(out, [result])
        st.update(count=sum(len(v) for v in written.values()), unit="files")
    sizes = {p[len(root) + 1:]: int(i.get("size") or 0) for p, i in fs.find(root, detail=True).items()}
    record = {"status": "done", "key": key, "split": split, "segment": segment, "files": sizes,
              "stages": rec.doc["stages"], "finished": time.time()}
    write_json(f"{out}/{DONE}", record)
    return record


def _count_objects(result) -> int | None:
    for name in ("num_object_clips_annotated", "objects", "clips"):
        v = getattr(result, name, None)
        if isinstance(v, int):
            return v
        if v is not None and _len(v) is not None:
            return _len(v)
    return None


def failure_summary(exc: BaseException) -> str:
    """One line (type: message) plus the innermost frame, for the status page."""
    tb = traceback.extract_tb(exc.__traceback__) if exc.__traceback__ else []
    where = f" (at {tb[-1].filename.rsplit('/', 1)[-1]}:{tb[-1].lineno})" if tb else ""
    return f"{type(exc).__name__}: {exc}{where}"
