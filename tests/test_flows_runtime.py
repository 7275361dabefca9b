"""Orchestration plumbing without a full release: the GPU queue on Dask, its guard, content
keys, transient-error classification, and the scheduled deployment's definition."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from drivetrack.release import keys, work as workdir  # noqa: E402
from flows import jobs  # noqa: E402
from flows.runtime import (GPU, ClusterConfig, NoWorkerForResourceError, dask_cluster,  # noqa: E402
                           require_resource, submit_resource_jobs, worker_specs, workers_with)


def complete_nearest(sparse):
    """A real depth job: the registry's nearest completer on one sparse map."""
    from drivetrack.depth import get_completer

    return get_completer("nearest")(sparse)


def test_depth_jobs_land_only_on_the_gpu_worker():
    cfg = ClusterConfig(n_workers=1, threads_per_worker=2, processes=False, gpus=1, cpu_drains_gpu=False)
    specs = worker_specs(cfg)
    assert GPU not in specs["cpu-0"]["options"].get("resources", {})
    assert specs["gpu-0"]["options"]["resources"] == {GPU: 1}
    rng = np.random.default_rng(0)
    sparse = np.zeros((12, 48, 480), np.float32)  # reach of the nearest completer: width / 96 px
    sparse[:, ::3, ::3] = rng.uniform(2, 50, size=(12, 16, 160))  # a lidar-like lattice
    with dask_cluster(cfg, specs=specs) as (client, _):
        gpu_workers = workers_with(client, GPU)
        assert len(gpu_workers) == 1
        (gpu_addr,) = gpu_workers
        all_workers = set(client.scheduler_info()["workers"])
        assert len(all_workers) == 2
        # plain jobs may go anywhere; depth jobs only where the resource is
        futures = submit_resource_jobs(client, complete_nearest, list(sparse))
        results = client.gather(futures)
        assert {addr for _, addr, _ in results} == {gpu_addr}
        for s, (dense, _, secs) in zip(sparse, results):
            assert dense.shape == s.shape and dense.dtype == np.float32 and secs >= 0
            known = s > 0
            np.testing.assert_array_equal(dense[known], s[known])
            assert (dense > 0).sum() > known.sum()  # it did complete something


def test_no_gpu_worker_fails_clearly_and_cpu_workers_can_drain_the_queue():
    cfg = ClusterConfig(n_workers=2, processes=False, gpus=0, cpu_drains_gpu=False)
    with dask_cluster(cfg) as (client, _):
        with pytest.raises(NoWorkerForResourceError, match=r"no worker of the cluster .* offers it"):
            submit_resource_jobs(client, complete_nearest, [np.zeros((4, 4), np.float32)])
        with pytest.raises(NoWorkerForResourceError, match=r"resources=\{\}"):
            require_resource(client, wait_s=0.6)
    # the default local cluster on a machine without GPUs: every worker takes one depth job at a time
    drain = ClusterConfig(n_workers=2, processes=False, gpus=0)
    specs = worker_specs(drain)
    assert [s["options"]["resources"] for s in specs.values()] == [{GPU: 1}, {GPU: 1}]


def test_cluster_config_from_env(monkeypatch):
    monkeypatch.setenv("DRIVETRACK_DASK_WORKERS", "3")
    monkeypatch.setenv("DRIVETRACK_DASK_THREADS", "2")
    cfg = ClusterConfig.from_env(threads_per_worker=4)
    assert (cfg.n_workers, cfg.threads_per_worker, cfg.address) == (3, 4, None)
    monkeypatch.setenv("DRIVETRACK_DASK_WORKERS", "three")
    with pytest.raises(ValueError, match="DRIVETRACK_DASK_WORKERS='three'"):
        ClusterConfig.from_env()
    monkeypatch.delenv("DRIVETRACK_DASK_WORKERS")
    with pytest.raises(ValueError, match="n_workers >= 1"):
        ClusterConfig.from_env(n_workers=0)
    monkeypatch.setenv("DRIVETRACK_DASK_ADDRESS", "tcp://10.0.0.1:8786")
    assert ClusterConfig.from_env().address == "tcp://10.0.0.1:8786"


def test_segment_keys_follow_content_config_and_code(tmp_path):
    root = tmp_path / "src"
    for comp in ("camera_image", "lidar"):
        (root / "training" / comp).mkdir(parents=True)
        for seg in ("a", "b"):
            (root / "training" / comp / f"{seg}.parquet").write_bytes(f"{comp}-{seg}".encode())
    memo = {}
    sums = keys.segment_checksums(str(root), "training", "a", memo=memo)
    assert set(sums) == {"camera_image", "lidar"} and all(v.startswith("sha256:") for v in sums.values())
    k = keys.segment_key("training", "a", sums, "cfg1", "code1")
    assert k == keys.segment_key("training", "a", dict(sums), "cfg1", "code1")
    assert k != keys.segment_key("training", "a", sums, "cfg2", "code1")
    assert k != keys.segment_key("training", "a", sums, "cfg1", "code2")
    (root / "training" / "lidar" / "a.parquet").write_bytes(b"changed bytes")
    changed = keys.segment_checksums(str(root), "training", "a", memo=memo)
    assert changed["lidar"] != sums["lidar"] and changed["camera_image"] == sums["camera_image"]
    with pytest.raises(FileNotFoundError, match="segment 'zzz'"):
        keys.segment_checksums(str(root), "training", "zzz")
    assert len(keys.code_fingerprint()) == 64
    assert keys.code_fingerprint(outputs_only=True) != keys.code_fingerprint()


def test_completion_records_detect_missing_or_changed_files(tmp_path):
    work = str(tmp_path / "work")
    d = Path(workdir.segment_dir(work, "training", "s1", "k" * 64))
    (d / "training").mkdir(parents=True)
    (d / "training" / "clip.npz").write_bytes(b"12345")
    workdir.write_record(str(d / workdir.DONE), {"status": "done", "key": "k" * 64,
                                         "files": {"training/clip.npz": 5}})
    assert workdir.completion_record(work, "training", "s1", "k" * 64)["status"] == "done"
    assert workdir.completion_record(work, "training", "s1", "j" * 64) is None
    (d / "training" / "clip.npz").write_bytes(b"123")
    assert workdir.completion_record(work, "training", "s1", "k" * 64) is None


def test_a_damaged_completion_record_is_an_error_naming_it_not_a_recompute(tmp_path):
    work = str(tmp_path / "work")
    d = Path(workdir.segment_dir(work, "training", "s1", "k" * 64))
    d.mkdir(parents=True)
    (d / workdir.DONE).write_text('{"status": "done", "key": "kk')
    with pytest.raises(ValueError, match=r"s1/kkkk.*_done\.json: not a valid JSON"):
        workdir.completion_record(work, "training", "s1", "k" * 64)
    assert workdir.completion_record(work, "training", "s2", "k" * 64) is None   # absent: compute it


def test_transient_errors_are_retried_and_data_errors_are_not():
    import errno

    assert jobs.is_transient(TimeoutError("read timed out"))
    assert jobs.is_transient(ConnectionResetError(errno.ECONNRESET, "reset"))
    wrapped = RuntimeError("publish interrupted")
    wrapped.__cause__ = OSError(errno.ETIMEDOUT, "timed out")
    assert jobs.is_transient(wrapped)
    assert not jobs.is_transient(FileNotFoundError(2, "missing", "x.parquet"))
    assert not jobs.is_transient(ValueError("column '[CameraImageComponent].image' is null"))
    assert not jobs.is_transient(None)


def test_next_version():
    from drivetrack.release.catalog import next_version

    assert next_version(None) == "0.1.0"
    assert next_version("1.2.3") == "1.2.4"
    assert next_version("1.2.3-rc.1") == "1.2.4"


def test_deployment_definition_loads_with_its_schedule():
    from prefect.flows import load_flow_from_entrypoint

    from flows.serve import DEFAULT_CRON, DEPLOYMENT_NAME, build_deployment

    d = build_deployment(cron="15 4 * * 1", source="s3://bucket/waymo", store="s3://bucket/releases")
    assert d.name == DEPLOYMENT_NAME and d.entrypoint == "flows.release.release"
    (sched,) = d.schedules
    assert sched.schedule.cron == "15 4 * * 1" and sched.active
    assert d.parameters["version"] == "auto" and d.parameters["skip_unchanged"] is True
    assert d.parameters["source"] == "s3://bucket/waymo"
    assert build_deployment().schedules[0].schedule.cron == DEFAULT_CRON

    doc = yaml.safe_load((REPO / "infra" / "prefect.yaml").read_text())
    (dep,) = doc["deployments"]
    assert dep["name"] == DEPLOYMENT_NAME
    assert dep["schedules"][0]["cron"] == DEFAULT_CRON and dep["schedules"][0]["active"] is True
    path, _, name = dep["entrypoint"].partition(":")
    assert (REPO / path).is_file()
    loaded = load_flow_from_entrypoint(str(REPO / dep["entrypoint"]))
    assert loaded.name == "release"
    params = set(loaded.parameters.properties)
    assert set(dep["parameters"]) <= params and {"version", "source", "store", "dask_address"} <= params


def _lidar_batch(seed: int, frames: int = 3):
    from drivetrack.depth.stage import DepthBatch

    rng = np.random.default_rng(seed)
    sparse = np.zeros((frames, 40, 192), np.float32)
    sparse[:, 1::4, ::5] = rng.uniform(2, 60, size=(frames, 10, 39)).astype(np.float32)
    sparse[:, 30:, 100:140] = 0.0                                   # a hole wider than the reach
    return DepthBatch("seg-torch", 1, np.arange(frames, dtype=np.int64), sparse, dense=False, method="")


def test_nearest_torch_runs_through_the_gpu_queue_and_matches_nearest():
    """The GPU queue's torch completer (CPU torch here), submitted as Dask jobs with the GPU
    resource, gives the maps of the CPU `nearest` completer: the same filled pixels, each a
    nearest return (ties aside); every batch records completer, device and worker."""
    pytest.importorskip("torch")
    from drivetrack.annotate import AnnotateConfig

    from flows.jobs import depth_job

    batches = [_lidar_batch(1), _lidar_batch(2)]
    torch_cfg = AnnotateConfig.from_dict({"track": {"depth_completer": "nearest-torch"}})
    cpu_cfg = AnnotateConfig()
    cfg = ClusterConfig(n_workers=2, processes=False, gpus=0)           # CPU workers drain the GPU queue
    with dask_cluster(cfg) as (client, _):
        gpu_workers = set(workers_with(client, GPU))
        torch_done = client.gather(submit_resource_jobs(client, depth_job, batches, torch_cfg))
        cpu_done = client.gather(submit_resource_jobs(client, depth_job, batches, cpu_cfg))
    for b, ((t, t_info), t_addr, _), ((c, c_info), c_addr, _) in zip(batches, torch_done, cpu_done):
        assert t_info == {"completer": "nearest-torch", "device": "cpu"} and t.method == "nearest-torch"
        assert c_info == {"completer": "nearest", "device": "cpu"} and c.method == "nearest"
        assert {t_addr, c_addr} <= gpu_workers
        assert t.maps.shape == c.maps.shape == b.maps.shape and t.maps.dtype == np.float32
        np.testing.assert_array_equal(t.maps > 0, c.maps > 0)              # the same pixels filled
        assert (t.maps > 0).sum() > (b.maps > 0).sum()
        assert np.mean(t.maps == c.maps) > 0.95                          # equidistant ties may differ
        assert np.isin(t.maps[t.maps > 0], b.maps[b.maps > 0]).all()     # every value a lidar return


def test_depth_choice_gpu_worker_uses_torch_on_its_device_cpu_workers_nearest():
    from flows.jobs import depth_choice, worker_cuda

    assert depth_choice("nearest", cuda=True) == ("nearest-torch", "cuda:0")
    assert depth_choice("nearest-torch", cuda=True) == ("nearest-torch", "cuda:0")
    assert depth_choice("nearest", cuda=False) == ("nearest", "cpu")
    assert depth_choice("nearest-torch", cuda=False) == ("nearest-torch", "cpu")
    assert depth_choice("ipbasic", cuda=True) == ("ipbasic", "cpu")
    import os
    if os.environ.get("CUDA_VISIBLE_DEVICES", None) == "" or not __import__("shutil").which("nvidia-smi"):
        assert worker_cuda() is False          # no GPU lent to this machine: torch is not even imported


def _cuda() -> bool:
    try:
        import torch
    except ImportError:
        return False
    return torch.cuda.is_available()


@pytest.mark.skipif(not _cuda(), reason="no CUDA device visible to torch (run this on a GPU node: "
                                        "infra/gpu-workers.md)")
def test_on_a_gpu_node_the_default_depth_runs_as_torch_on_cuda():
    """On a GPU node: the local cluster's GPU worker (a process pinned to GPU 0) completes the
    default configuration's depth batches with nearest-torch on cuda:0, matching `nearest`."""
    from drivetrack.annotate import AnnotateConfig
    from drivetrack.depth import get_completer

    from flows.jobs import depth_job

    batches = [_lidar_batch(3)]
    cfg = ClusterConfig(n_workers=1, processes=True, gpus=1, cpu_drains_gpu=False)
    with dask_cluster(cfg) as (client, _):
        (gpu_addr,) = workers_with(client, GPU)
        [((dense, info), addr, _)] = client.gather(submit_resource_jobs(client, depth_job, batches, AnnotateConfig()))
    assert addr == gpu_addr and info == {"completer": "nearest-torch", "device": "cuda:0"}
    cpu = np.stack([get_completer("nearest")(m) for m in batches[0].maps])
    np.testing.assert_array_equal(dense.maps > 0, cpu > 0)
    assert np.mean(dense.maps == cpu) > 0.95


def test_content_keys_and_run_json_hash_sources_and_name_the_code_one_way(tmp_path):
    from drivetrack.provenance import code_version, code_version_text, source_checksums

    root = tmp_path / "src"
    (root / "training" / "camera_image").mkdir(parents=True)
    (root / "training" / "camera_image" / "a.parquet").write_bytes(b"abc")
    url = str(root / "training" / "camera_image" / "a.parquet")
    plain = source_checksums({"camera_image": url})
    assert keys.segment_checksums(str(root), "training", "a") == {"camera_image": "sha256:" + plain["camera_image"]}
    version = code_version()
    assert set(version) == {"drivetrack", "git_commit", "git_dirty"}
    assert code_version_text(version).startswith(version["drivetrack"])
    assert code_version_text({"drivetrack": "1.0", "git_commit": "ab" * 20, "git_dirty": True}) == \
        "1.0+gabababababab.dirty"
