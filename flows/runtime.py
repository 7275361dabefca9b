"""Run-time plumbing for the flows: one Prefect API server per run, the Dask cluster, and the
GPU queue (the Dask resource ``GPU``).

- :func:`prefect_api` starts ONE Prefect server in this (the parent) process when
  ``PREFECT_API_URL`` is unset and exports the URL, so that Dask worker processes started later
  talk to it instead of each starting their own (STACK.md: per-worker servers collide).
- :func:`dask_cluster` starts a local cluster, or connects to an existing scheduler address
  (dask-jobqueue, dask-kubernetes, a cloud provider, ``dask scheduler`` by hand).
- Depth jobs carry ``resources={"GPU": 1}``: only workers started with that resource take them,
  one at a time each. A local cluster on a machine without GPUs gives its workers the resource,
  so that they drain the GPU queue on the CPU; with GPUs, it adds one worker per GPU beside the
  CPU workers. :func:`require_resource` refuses to submit to a cluster where no worker has it
  (Dask would wait forever).
"""
from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

from flows import REPO

GPU = "GPU"
"""The Dask resource name of the depth-completion queue."""


class NoWorkerForResourceError(RuntimeError):
    """No worker of the cluster offers the resource a job needs."""


# ---- Prefect -----------------------------------------------------------------------------------

class _FullServer:
    """``prefect server start`` in a subprocess: API, UI and the background services (the
    scheduler that turns cron schedules into runs does not run in the embedded server)."""

    def __init__(self, port: int | None = None):
        import socket

        if port is None:
            with socket.socket() as sock:
                sock.bind(("127.0.0.1", 0))
                port = sock.getsockname()[1]
        self.port = port
        self.address = f"http://127.0.0.1:{port}"
        self.api_url = f"{self.address}/api"
        self.proc = None

    def start(self, timeout: float) -> None:
        import sys
        import urllib.request

        log = open(os.path.join(os.environ.get("PREFECT_HOME", "."), f"server-{self.port}.log"), "ab")
        self.proc = subprocess.Popen([sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1",
                                      "--port", str(self.port)], stdout=log, stderr=subprocess.STDOUT,
                                     env={**os.environ, "PREFECT_API_URL": ""})
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"prefect server start exited with {self.proc.returncode}; see {log.name}")
            try:
                with urllib.request.urlopen(f"{self.api_url}/health", timeout=2) as r:
                    if r.status == 200:
                        return
            except OSError:
                time.sleep(0.5)
        self.stop()
        raise RuntimeError(f"the Prefect server at {self.address} did not answer within {timeout:.0f} s; "
                           f"see {log.name}")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.proc = None


def _drain_api_logs(timeout_s: float = 10.0) -> None:
    """Send the flow/task logs still queued for the API and stop the log worker, before the server
    it talks to stops (otherwise the worker's late batch prints "Error logging to API ... All
    connection attempts failed" after a successful run). Best effort: a failure here must not
    hide the run's own result."""
    try:
        from prefect.logging.handlers import APILogWorker

        result = APILogWorker.drain_all(timeout=timeout_s)
        if hasattr(result, "close"):        # inside an event loop: the drains have started, don't await
            result.close()
    except Exception as error:  # noqa: BLE001 - shutdown path
        print(f"prefect: could not flush logs to the API before stopping the server: {error}", flush=True)


@contextlib.contextmanager
def prefect_api(timeout_s: float = 120.0, *, full: bool = False) -> Iterator[str]:
    """Yield the Prefect API URL to use: ``PREFECT_API_URL`` if set (a server or Prefect Cloud),
    else a server started here once (SQLite under ``PREFECT_HOME``, kept between runs so that task
    caches and run history survive), stopped on exit; ``full=True`` starts ``prefect server
    start`` instead (UI and scheduler, needed to serve cron schedules). The URL is exported in ``os.environ``
    before any Dask worker starts and set in this process's Prefect settings."""
    from prefect.settings import PREFECT_API_URL, temporary_settings

    url = os.environ.get("PREFECT_API_URL")
    server = None
    if not url:
        from prefect.server.api.server import SubprocessASGIServer

        server = _FullServer() if full else SubprocessASGIServer()
        t0 = time.perf_counter()
        server.start(timeout=int(timeout_s))
        url = server.api_url
        print(f"prefect: started a server at {server.address} in {time.perf_counter() - t0:.1f} s "
              f"(PREFECT_HOME={os.environ.get('PREFECT_HOME')})", flush=True)
    old = os.environ.get("PREFECT_API_URL")
    os.environ["PREFECT_API_URL"] = url
    try:
        with temporary_settings({PREFECT_API_URL: url}):
            yield url
    finally:
        if server is not None:
            from prefect.settings import PREFECT_LOGGING_TO_API_ENABLED

            with temporary_settings({PREFECT_LOGGING_TO_API_ENABLED: False}):
                _drain_api_logs()       # send buffered flow/task logs while the server still listens
                server.stop()
            if old is None:
                os.environ.pop("PREFECT_API_URL", None)
            else:
                os.environ["PREFECT_API_URL"] = old


# ---- Dask --------------------------------------------------------------------------------------

def gpu_count() -> int:
    """Visible NVIDIA GPUs (``CUDA_VISIBLE_DEVICES`` if set, else ``nvidia-smi -L``); 0 without."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        return len([d for d in visible.split(",") if d.strip() and d.strip() != "-1"])
    exe = shutil.which("nvidia-smi")
    if not exe:
        return 0
    try:
        out = subprocess.run([exe, "-L"], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return 0
    return sum(1 for line in out.stdout.splitlines() if line.startswith("GPU ")) if out.returncode == 0 else 0


@dataclass(frozen=True)
class ClusterConfig:
    """``address``: an existing scheduler (``tcp://host:8786``) - used as is, its workers'
    resources decide where depth jobs go. Otherwise a local cluster of ``n_workers`` CPU workers
    with ``threads_per_worker`` threads (``processes=False`` keeps them in this process), plus
    ``gpus`` GPU workers (None: one per visible GPU). ``cpu_drains_gpu`` (default: when there is
    no GPU) gives every CPU worker one ``GPU`` slot so they run depth jobs on the CPU."""
    address: str | None = None
    n_workers: int = 2
    threads_per_worker: int = 1
    processes: bool = True
    gpus: int | None = None
    cpu_drains_gpu: bool | None = None
    memory_limit: str = "auto"
    dashboard_host: str = "127.0.0.1"
    """Interface of the local cluster's dashboards (scheduler and workers, free ports): loopback
    unless asked (``DRIVETRACK_DASK_DASHBOARD_HOST=0.0.0.0`` listens on every interface, and
    shows the cluster to the network)."""

    @classmethod
    def from_env(cls, **overrides) -> "ClusterConfig":
        """``DRIVETRACK_DASK_ADDRESS``, ``DRIVETRACK_DASK_WORKERS``, ``DRIVETRACK_DASK_THREADS``,
        ``DRIVETRACK_GPUS``, ``DRIVETRACK_DASK_DASHBOARD_HOST``; explicit non-None overrides win."""
        env = {}
        if os.environ.get("DRIVETRACK_DASK_ADDRESS"):
            env["address"] = os.environ["DRIVETRACK_DASK_ADDRESS"]
        if os.environ.get("DRIVETRACK_DASK_DASHBOARD_HOST"):
            env["dashboard_host"] = os.environ["DRIVETRACK_DASK_DASHBOARD_HOST"].strip()
        for var, key in (("DRIVETRACK_DASK_WORKERS", "n_workers"), ("DRIVETRACK_DASK_THREADS", "threads_per_worker"),
                         ("DRIVETRACK_GPUS", "gpus")):
            if os.environ.get(var):
                try:
                    env[key] = int(os.environ[var])
                except ValueError:
                    raise ValueError(f"{var}={os.environ[var]!r} is not an integer") from None
        env.update({k: v for k, v in overrides.items() if v is not None})
        cfg = cls(**env)
        if cfg.address is None and (cfg.n_workers < 1 or cfg.threads_per_worker < 1):
            raise ValueError(f"a local cluster needs n_workers >= 1 and threads_per_worker >= 1, "
                             f"found {cfg.n_workers} and {cfg.threads_per_worker}")
        return cfg


def worker_specs(cfg: ClusterConfig) -> dict[str, dict]:
    """The local cluster's workers as ``distributed.SpecCluster`` specs: ``cpu-i`` workers and one
    ``gpu-i`` worker per GPU pinned with ``CUDA_VISIBLE_DEVICES`` (what dask-cuda does)."""
    from distributed import Nanny, Worker

    cls = Nanny if cfg.processes else Worker
    gpus = gpu_count() if cfg.gpus is None else cfg.gpus
    drain = (gpus == 0) if cfg.cpu_drains_gpu is None else cfg.cpu_drains_gpu
    tmp = os.environ.get("DASK_TEMPORARY_DIRECTORY") or str(REPO / "build" / "dask-scratch")
    base = {"nthreads": cfg.threads_per_worker, "dashboard_address": _dashboard(cfg), "local_directory": tmp}
    if cfg.processes:
        base["memory_limit"] = cfg.memory_limit
    specs = {}
    for i in range(cfg.n_workers):
        opts = dict(base, name=f"cpu-{i}")
        if drain:
            opts["resources"] = {GPU: 1}
        specs[f"cpu-{i}"] = {"cls": cls, "options": opts}
    for i in range(gpus):
        opts = dict(base, name=f"gpu-{i}", nthreads=1, resources={GPU: 1})
        if cfg.processes:
            opts["env"] = {"CUDA_VISIBLE_DEVICES": str(i)}
        specs[f"gpu-{i}"] = {"cls": cls, "options": opts}
    return specs


def _dashboard(cfg: ClusterConfig) -> str:
    """``host:0`` (a free port on ``cfg.dashboard_host``); IPv6 hosts in brackets."""
    host = cfg.dashboard_host
    if ":" in host and not host.startswith("["):
        host = f"[{host}]"
    return f"{host}:0"


@contextlib.contextmanager
def dask_cluster(cfg: ClusterConfig | None = None, *, specs: dict[str, dict] | None = None):
    """Yield ``(client, address)``: connected to ``cfg.address``, or to a local cluster built
    from :func:`worker_specs` (or the given ``specs``), closed on exit."""
    from distributed import Client, Scheduler, SpecCluster

    cfg = cfg or ClusterConfig.from_env()
    if cfg.address:
        client = Client(cfg.address, timeout="30s")
        try:
            yield client, cfg.address
        finally:
            client.close()
        return
    tmp = os.environ.get("DASK_TEMPORARY_DIRECTORY") or str(REPO / "build" / "dask-scratch")
    os.makedirs(tmp, exist_ok=True)
    os.environ.setdefault("DASK_TEMPORARY_DIRECTORY", tmp)
    specs = specs if specs is not None else worker_specs(cfg)
    scheduler = {"cls": Scheduler, "options": {"dashboard_address": _dashboard(cfg), "host": "127.0.0.1"}}
    for spec in specs.values():
        spec.setdefault("options", {}).setdefault("host", "127.0.0.1")
    cluster = SpecCluster(workers=specs, scheduler=scheduler, asynchronous=False, silence_logs=40)
    client = Client(cluster)
    try:
        client.wait_for_workers(len(specs), timeout=120)
        yield client, cluster.scheduler_address
    finally:
        client.close()
        cluster.close()


def workers_with(client, resource: str = GPU) -> dict[str, float]:
    """Worker address -> amount of ``resource`` it offers (workers without it left out)."""
    info = client.scheduler_info(n_workers=-1) if _takes_n_workers(client) else client.scheduler_info()
    out = {}
    for addr, w in info.get("workers", {}).items():
        amount = (w.get("resources") or {}).get(resource)
        if amount:
            out[addr] = float(amount)
    return out


def _takes_n_workers(client) -> bool:
    import inspect

    return "n_workers" in inspect.signature(client.scheduler_info).parameters


def require_resource(client, resource: str = GPU, *, wait_s: float = 0.0, what: str = "depth jobs") -> dict[str, float]:
    """Raise :class:`NoWorkerForResourceError` unless some worker offers ``resource`` (waiting up
    to ``wait_s`` seconds for one to join). Returns :func:`workers_with`."""
    deadline = time.monotonic() + wait_s
    while True:
        found = workers_with(client, resource)
        if found or time.monotonic() >= deadline:
            break
        time.sleep(0.5)
    if not found:
        info = client.scheduler_info()
        described = ", ".join(f"{a} resources={w.get('resources') or {}}" for a, w in info.get("workers", {}).items())
        raise NoWorkerForResourceError(
            f"{what} need the Dask resource {resource!r} but no worker of the cluster at "
            f"{info.get('address')} offers it (workers: {described or 'none'}). Start GPU workers with "
            f"`--resources {resource}=1` (see infra/gpu-workers.md, e.g. `dask cuda worker ... --resources "
            f"{resource}=1`), or on a machine without GPUs give CPU workers the resource "
            f"(`dask worker ... --resources {resource}=1`) so they drain the queue on the CPU.")
    return found


def _run_recording_worker(fn: Callable, *args):
    """Run ``fn(*args)`` on a Dask worker; return ``(result, worker address, seconds)``."""
    from distributed import get_worker

    t0 = time.perf_counter()
    result = fn(*args)
    return result, get_worker().address, time.perf_counter() - t0


def submit_resource_jobs(client, fn: Callable, items: Iterable, *args, resource: str = GPU,
                         key_prefix: str = "depth", wait_s: float = 0.0) -> list:
    """Submit ``fn(item, *args)`` for each item as Dask jobs that need one unit of ``resource``
    (guarded by :func:`require_resource`). Each future gives ``(result, worker address, seconds)``."""
    import uuid

    require_resource(client, resource, wait_s=wait_s)
    token = uuid.uuid4().hex[:8]
    return [client.submit(_run_recording_worker, fn, item, *args, resources={resource: 1}, pure=False,
                          key=f"{key_prefix}-{token}-{i}") for i, item in enumerate(items)]
