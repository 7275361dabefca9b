"""Hostile run-time: what the flows expose on the network and in Prefect's records, and whether
the tests stand alone next to a `make release` of the same checkout.

- the local Dask cluster's dashboards (scheduler and workers) listen on loopback only;
- a secret in ``storage_options`` / ``store_options`` / a URL is refused before Prefect stores
  the flow run; references (``{"env": NAME}``) are stored instead and resolved in the task;
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

SECRET = "wJalrXUtnFEMI-K7MDENG-bPxRfiCYEXAMPLEKEY-7f3a"   # a made-up value that must never be stored


# ---- listening sockets ------------------------------------------------------------------------

def _listening(ports: set[int]) -> dict[int, set[str]]:
    import psutil

    out: dict[int, set[str]] = {}
    for c in psutil.net_connections(kind="tcp"):
        if c.status == psutil.CONN_LISTEN and c.laddr and c.laddr.port in ports:
            out.setdefault(c.laddr.port, set()).add(c.laddr.ip)
    return out


def test_local_cluster_dashboards_listen_on_loopback_only():
    from flows.runtime import ClusterConfig, dask_cluster

    cfg = ClusterConfig(n_workers=1, threads_per_worker=1, processes=True, gpus=0)
    with dask_cluster(cfg) as (client, address):
        info = client.scheduler_info()
        ports = {("scheduler", info["services"]["dashboard"])}
        ports |= {(addr, w["services"]["dashboard"]) for addr, w in info["workers"].items()}
        assert len(ports) == 2, ports
        found = _listening({p for _, p in ports})
        for who, port in ports:
            assert found.get(port), f"{who}: nothing listens on dashboard port {port}"
            assert found[port] == {"127.0.0.1"}, f"{who}'s dashboard on port {port} listens on {found[port]}"
        assert "127.0.0.1" in client.dashboard_link and address.startswith("tcp://127.0.0.1:")


def test_dashboard_host_is_an_explicit_choice(monkeypatch):
    from flows.runtime import ClusterConfig, worker_specs

    assert ClusterConfig().dashboard_host == "127.0.0.1"
    monkeypatch.setenv("DRIVETRACK_DASK_DASHBOARD_HOST", "0.0.0.0")
    cfg = ClusterConfig.from_env(n_workers=1, gpus=0, processes=False)
    assert cfg.dashboard_host == "0.0.0.0"
    assert worker_specs(cfg)["cpu-0"]["options"]["dashboard_address"] == "0.0.0.0:0"


# ---- secrets in parameters --------------------------------------------------------------------

@pytest.fixture(scope="module")
def prefect_server():
    from flows.runtime import prefect_api

    with prefect_api() as url:
        yield url


def _everything_prefect_stored() -> str:
    """Every flow run's parameters, every task run, every log line the server holds, as text."""
    from prefect.client.orchestration import get_client

    with get_client(sync_client=True) as client:
        runs = client.read_flow_runs(limit=200)
        tasks = client.read_task_runs(limit=200)
        logs = client.read_logs(limit=200)
    return json.dumps([r.model_dump(mode="json") for r in runs] + [t.model_dump(mode="json") for t in tasks]
                      + [lg.model_dump(mode="json") for lg in logs])


@pytest.mark.parametrize("where, options", [
    ("storage_options", {"key": "AKIAEXAMPLE", "secret": SECRET}),
    ("store_options", {"client_kwargs": {"aws_secret_access_key": SECRET}}),
    ("storage_options", {"token": {"type": "service_account", "private_key": SECRET}}),
    ("store_options", {"account_name": "acct", "sas_token": SECRET}),
    ("storage_options", {"headers": {"Authorization": f"Bearer {SECRET}"}}),
    ("store", f"s3://AKIAEXAMPLE:{SECRET}@bucket/releases"),
])
def test_secret_parameters_are_refused_before_prefect_stores_them(prefect_server, synth_source, tmp_path,
                                                                   where, options):
    from flows.credentials import SecretParameterError
    from flows.release import release

    kwargs = dict(version="0.1.0", source=synth_source, store=str(tmp_path / "store"), work=str(tmp_path / "work"),
                  segments=["no_such_segment"], n_workers=1, dask_processes=False)
    kwargs[where] = options
    with pytest.raises(SecretParameterError, match=r"secret|password") as err:
        release(**kwargs)
    assert SECRET not in str(err.value)                       # the error names the option, not the value
    assert SECRET not in _everything_prefect_stored()


def test_references_are_stored_and_resolved_in_the_task(prefect_server, synth_source, tmp_path, monkeypatch):
    from flows.credentials import resolve_options
    from flows.release import release

    ref = {"key": {"env": "DT_HOSTILE_KEY"}, "secret": {"env": "DT_HOSTILE_SECRET"}}
    monkeypatch.setenv("DT_HOSTILE_KEY", "AKIAEXAMPLE")
    monkeypatch.setenv("DT_HOSTILE_SECRET", SECRET)
    assert resolve_options(ref) == {"key": "AKIAEXAMPLE", "secret": SECRET}
    kwargs = dict(version="0.1.0", source=synth_source, store=str(tmp_path / "store"), work=str(tmp_path / "work"),
                  segments=["no_such_segment"], n_workers=1, dask_processes=False, storage_options=ref)
    # resolved where the source is opened (the list task), with the variable set: it lists the source
    with pytest.raises(ValueError, match="segment 'no_such_segment' is not in"):
        release(**kwargs)
    # unset on the worker: the task names the variable and the option, never a value
    monkeypatch.delenv("DT_HOSTILE_SECRET")
    with pytest.raises(KeyError, match=r"secret refers to the environment variable DT_HOSTILE_SECRET"):
        release(**kwargs)
    stored = _everything_prefect_stored()
    assert SECRET not in stored and '"DT_HOSTILE_SECRET"' in stored


# ---- tests that stand alone -------------------------------------------------------------------

def test_tests_have_their_own_prefect_home_not_the_checkouts():
    """A `make release` in this checkout uses REPO/.prefect (its database, caches, artifacts);
    the tests must not share it (conftest sets a fresh PREFECT_HOME before prefect is imported)."""
    import os

    from prefect.settings import get_current_settings

    home = Path(get_current_settings().home).resolve()
    assert home == Path(os.environ["PREFECT_HOME"]).resolve()
    assert not home.is_relative_to(REPO), f"the tests' PREFECT_HOME {home} is inside the checkout {REPO}"
    # An API URL inherited from the shell (a `make serve` of this checkout) is dropped when the
    # suite starts; checked in a fresh interpreter, since servers the tests start set their own.
    import subprocess
    import sys

    probe = subprocess.run(
        [sys.executable, "-c", "import os, runpy; runpy.run_path('conftest.py'); "
                               "print(os.environ.get('PREFECT_API_URL', ''))"],
        cwd=Path(__file__).parent, capture_output=True, text=True, timeout=120,
        env={**os.environ, "PREFECT_API_URL": "http://127.0.0.1:4200/api"})
    assert probe.returncode == 0, probe.stderr[-2000:]
    assert probe.stdout.strip() == "", f"the tests would use an inherited server: {probe.stdout!r}"


def test_make_system_deps_survives_an_offline_apt_get(tmp_path):
    """`make test` on a machine whose network hangs: apt-get is bounded and its failure does not
    fail make; the browser test is then skipped with its reason."""
    import os
    import subprocess
    import time

    if os.getuid() != 0:
        pytest.skip("system-deps installs with apt-get only as root")
    fake = tmp_path / "bin"
    fake.mkdir()
    (fake / "apt-get").write_text("#!/bin/sh\nexec sleep 600\n")   # a hung network
    (fake / "apt-get").chmod(0o755)
    env = {**os.environ, "PATH": f"{fake}:/usr/bin:/bin"}
    t0 = time.monotonic()
    res = subprocess.run(["make", "--no-print-directory", "-C", str(REPO), "system-deps", "APT_TIMEOUT=2",
                          "CHROMIUM=drivetrack-test-no-such-browser"],
                         env=env, capture_output=True, text=True, timeout=60)
    took = time.monotonic() - t0
    assert res.returncode == 0, res.stdout + res.stderr
    assert took < 30, f"make system-deps waited {took:.0f} s for a hung apt-get"
    assert "browser test will be skipped" in res.stdout
    makefile = (REPO / "Makefile").read_text()
    assert "-m pytest -q -rs" in makefile, "make test must print skip reasons"
