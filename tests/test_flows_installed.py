"""The flows from an installed wheel on a real Dask cluster: ``dask scheduler`` and two ``dask
worker`` processes (loopback, free ports), the release flow run from another working directory
against them, with a fresh work folder, publishing.

"Installed": the project is built into a wheel (from a copy of the sources, so the checkout is
not written), installed with ``pip install --no-deps --target SITE``, and every process runs the
shared interpreter with ``PYTHONPATH=SITE`` only: the checkout is not on the path and not the
working directory, and each process proves that ``drivetrack`` and ``flows`` (and the default
gates) come from SITE. The dependencies are the shared environment's.
"""
from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """SITE: the wheel's contents, nothing else."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in ("drivetrack", "flows"):
        shutil.copytree(REPO / name, src / name, ignore=ignore)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                    "-w", str(tmp / "dist"), str(src)], check=True, env=env, cwd=tmp, timeout=120)
    (wheel,) = (tmp / "dist").glob("drivetrack-*.whl")
    site = tmp / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-compile", "--target",
                    str(site), str(wheel)], check=True, env=env, cwd=tmp, timeout=120)
    return site


def _env(site: Path, prefect_home: Path) -> dict:
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PREFECT_API_URL", "DRIVETRACK_DASK_ADDRESS", "DASK_TEMPORARY_DIRECTORY")}
    env.update(PYTHONPATH=str(site), PREFECT_HOME=str(prefect_home), DO_NOT_TRACK="1",
               PREFECT_SERVER_ANALYTICS_ENABLED="false", DASK_LOGGING__DISTRIBUTED="warning")
    return env


WHERE = ("import json, drivetrack, flows, drivetrack.gates.config as g; "
         "print(json.dumps([drivetrack.__file__, flows.__file__, str(g.DEFAULT_CONFIG_PATH), str(flows.REPO)]))")


def test_wheel_install_runs_the_release_on_dask_scheduler_and_workers(installed, synth_source, synth_segments,
                                                                      tmp_path):
    site = installed
    run_dir = tmp_path / "elsewhere"
    run_dir.mkdir()
    env = _env(site, tmp_path / "prefect")
    out = subprocess.run([sys.executable, "-c", WHERE], env=env, cwd=run_dir, capture_output=True, text=True,
                         timeout=120, check=True)
    files = json.loads(out.stdout.strip().splitlines()[-1])
    for f in files[:3]:
        assert Path(f).resolve().is_relative_to(site.resolve()), f"{f} is not from the installed wheel {site}"
    assert Path(files[2]).is_file() and Path(files[3]).resolve() == run_dir.resolve()

    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    dask = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    procs = []
    logs = tmp_path / "logs"
    logs.mkdir()
    try:
        procs.append(subprocess.Popen(
            [*dask, "--host", "127.0.0.1", "--port", str(port), "--dashboard-address", "127.0.0.1:0"],
            env=env, cwd=run_dir, stdout=open(logs / "scheduler.log", "wb"), stderr=subprocess.STDOUT))
        for i in range(2):
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "distributed.cli.dask_worker", address, "--host", "127.0.0.1",
                 "--nthreads", "1", "--name", f"w{i}", "--resources", "GPU=1", "--dashboard-address",
                 "127.0.0.1:0", "--local-directory", str(tmp_path / "dask"), "--memory-limit", "0"],
                env=env, cwd=run_dir, stdout=open(logs / f"worker-{i}.log", "wb"), stderr=subprocess.STDOUT))
        from distributed import Client

        deadline = time.monotonic() + 60
        while True:
            try:
                client = Client(address, timeout="5s")
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        with client:
            client.wait_for_workers(2, timeout=60)
            workers = set(client.scheduler_info()["workers"])
            seen = client.run(eval, "(__import__('drivetrack').__file__, __import__('flows').__file__)")
            assert set(seen) == workers
            for addr, (dt, fl) in seen.items():
                assert Path(dt).resolve().is_relative_to(site.resolve()), (addr, dt)
                assert Path(fl).resolve().is_relative_to(site.resolve()), (addr, fl)

            (run_dir / "config.yaml").write_text('track: {cameras: ["FRONT"]}\n')
            store, work = tmp_path / "store", tmp_path / "work"
            res = subprocess.run(
                [sys.executable, "-m", "flows.release", "--version", "0.1.0", "--source", synth_source,
                 "--store", str(store), "--work", str(work), "--dask-address", address, "--config", "config.yaml",
                 "--segments", synth_segments[0]],   # one segment: its depth batches still spread over both workers
                env=env, cwd=run_dir, capture_output=True, text=True, timeout=300)
            assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
            assert "released drivetrack-waymo 0.1.0" in res.stdout
            status = json.loads((store / "drivetrack-waymo" / "0.1.0" / "status.json").read_text())
            depth_workers = {w for s in status["segments"] for w in (s["stages"]["depth"]["worker"] or "").split(",")
                             if w}
            assert depth_workers and depth_workers <= workers, (depth_workers, workers)
    finally:
        for p in reversed(procs):       # the workers first: with their scheduler gone they wait to close
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    from drivetrack.release import verify_release

    assert verify_release(str(store), "0.1.0").ok
    assert not list(site.rglob(".prefect")), "run-time state was written inside the installed package"
