"""Release store against a real S3-compatible HTTP server on loopback (moto server mode):
publish + verify + sha256sum -c on a download, conditional writes, concurrent publishes,
the server stopped mid-publish, an object corrupted after publish."""
from __future__ import annotations

import json
import subprocess
import threading

import pytest
from s3server import S3Server, s3_server, s3_store  # noqa: F401 - fixtures
from test_release import gates_of, make_output

from drivetrack.cli import main as cli
from drivetrack.release import (ConcurrentPublishError, PublishConflictError, PublishInterruptedError,
                                VersionExistsError, VersionNotFoundError, gc, list_versions, open_store,
                                publish_release, read_manifest, verify_release)
from drivetrack.release.errors import CasConflictError

DS = "drivetrack-waymo"


def test_publish_to_s3_verifies_with_drivetrack_and_sha256sum(tmp_path, s3_server, s3_store):
    url, opts = s3_store
    src = make_output(tmp_path / "out", n_clips=1)
    result = publish_release(src, url, "1.0.0", storage_options=opts, gate_report=gates_of(src))
    assert verify_release(url, "1.0.0", storage_options=opts).ok
    # Download the release folder and check it with the standard tool.
    store = open_store(url, opts)
    local = tmp_path / "download"
    store.fs.get(store.path(f"{DS}/1.0.0") + "/", str(local), recursive=True)
    done = subprocess.run(["sha256sum", "-c", "--strict", "SHA256SUMS"], cwd=local, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.count(": OK") == result.files - 1
    # The CLI with --endpoint-url.
    assert cli(["verify", url, "--version", "latest", "--endpoint-url", s3_server.endpoint_url]) == 0
    assert not store.find(f"{DS}/_staging") and not store.find(f"{DS}/_txn")


def test_s3_second_publish_fails_without_touching_first(tmp_path, s3_store):
    url, opts = s3_store
    a = make_output(tmp_path / "a", n_clips=1)
    publish_release(a, url, "1.0.0", storage_options=opts, gate_report=gates_of(a))
    store = open_store(url, opts)
    before = {p: store.read_bytes(f"{DS}/1.0.0/{p}") for p in store.find(f"{DS}/1.0.0")}
    with pytest.raises(VersionExistsError, match="already published"):
        b = make_output(tmp_path / "b", seed=9, n_clips=1)
        publish_release(b, url, "1.0.0", storage_options=opts, gate_report=gates_of(b))
    after = {p: store.read_bytes(f"{DS}/1.0.0/{p}") for p in store.find(f"{DS}/1.0.0")}
    assert after == before


def test_s3_conditional_writes(s3_store):
    url, opts = s3_store
    store = open_store(url, opts)
    store.put_if_absent("x/claim.json", b"1")
    with pytest.raises(FileExistsError):
        store.put_if_absent("x/claim.json", b"2")
    data, etag = store.read_with_token("x/claim.json")
    assert data == b"1" and etag
    store.compare_and_swap("x/claim.json", b"3", etag)
    with pytest.raises(CasConflictError, match="changed underneath"):
        store.compare_and_swap("x/claim.json", b"4", etag)
    with pytest.raises(CasConflictError):
        store.compare_and_swap("x/claim.json", b"5", None)
    assert store.read_bytes("x/claim.json") == b"3"
    assert store.read_with_token("x/absent.json") == (None, None)


def test_s3_concurrent_publishes_exactly_one_wins(tmp_path, s3_store):
    url, opts = s3_store
    sources = [make_output(tmp_path / f"src{i}", n_clips=1) for i in range(3)]
    barrier = threading.Barrier(len(sources))
    outcomes: list = [None] * len(sources)

    def attempt(i):
        barrier.wait()
        try:
            outcomes[i] = publish_release(sources[i], url, "3.0.0", storage_options=opts, workers=4,
                                          gate_report=gates_of(sources[i]))
        except PublishConflictError as e:
            outcomes[i] = e

    threads = [threading.Thread(target=attempt, args=(i,)) for i in range(len(sources))]
    [t.start() for t in threads]
    [t.join() for t in threads]
    winners = [i for i, o in enumerate(outcomes) if not isinstance(o, Exception)]
    assert len(winners) == 1, outcomes
    assert all(isinstance(o, (ConcurrentPublishError, VersionExistsError))
               for o in outcomes if isinstance(o, Exception))
    assert verify_release(url, "3.0.0", storage_options=opts).ok
    assert read_manifest(url, "3.0.0", storage_options=opts)["source"] == str(sources[winners[0]])


def test_s3_object_corrupted_after_publish_is_reported(tmp_path, s3_server, s3_store, capsys):
    url, opts = s3_store
    src = make_output(tmp_path / "out", n_clips=1)
    publish_release(src, url, "1.0.0", storage_options=opts, gate_report=gates_of(src))
    bucket = url.removeprefix("s3://").split("/")[0]
    key = f"releases/{DS}/1.0.0/clips/training/seg0.parquet"
    client = s3_server.client()
    body = bytearray(client.get_object(Bucket=bucket, Key=key)["Body"].read())
    body[-10] ^= 0x01
    client.put_object(Bucket=bucket, Key=key, Body=bytes(body))
    client.delete_object(Bucket=bucket, Key=f"releases/{DS}/1.0.0/stats/segments.parquet")
    report = verify_release(url, "1.0.0", storage_options=opts)
    assert [(c["path"], c["problem"]) for c in report.corrupt] == [("clips/training/seg0.parquet", "sha256")]
    assert report.missing == ["stats/segments.parquet"] and not report.ok
    assert cli(["verify", url, "--version", "1.0.0", "--endpoint-url", s3_server.endpoint_url]) == 1
    out = capsys.readouterr().out
    assert "CORRUPT  clips/training/seg0.parquet: sha256" in out and "MISSING  stats/segments.parquet" in out


def test_server_stopped_mid_publish_leaves_nothing_visible_then_resume(tmp_path):
    """Its own server: stopped after a few uploads, restarted (moto keeps state in memory)."""
    server = S3Server().start()
    try:
        bucket = server.new_bucket()
        url = f"s3://{bucket}/releases"
        src = make_output(tmp_path / "out", n_clips=3)
        uploaded = []

        def stop_after_three(event, info):
            if event == "uploaded":
                uploaded.append(info["path"])
                if len(uploaded) == 3:
                    server.stop()

        with pytest.raises(PublishInterruptedError) as err:
            publish_release(src, url, "1.0.0", storage_options=server.storage_options(fail_fast=True),
                            workers=1, progress=stop_after_three, gate_report=gates_of(src))
        msg = str(err.value)
        assert "interrupted" in msg and "No version is visible" in msg and "--resume" in msg
        server.start()  # a new port, same in-memory buckets
        opts = server.storage_options()
        assert list_versions(url, storage_options=opts) == []
        with pytest.raises(VersionNotFoundError, match="interrupted"):
            verify_release(url, "1.0.0", storage_options=opts)
        store = open_store(url, opts)
        assert store.find(f"{DS}/_staging/1.0.0")  # staged files left for the resume
        with pytest.raises(ConcurrentPublishError, match="being published"):
            publish_release(src, url, "1.0.0", storage_options=opts, gate_report=gates_of(src))
        result = publish_release(src, url, "1.0.0", storage_options=opts, resume=True, gate_report=gates_of(src))
        assert result.reused_files >= 3
        assert verify_release(url, "1.0.0", storage_options=opts).ok
        latest = json.loads(store.read_bytes(f"{DS}/latest.json"))
        assert latest["version"] == "1.0.0"
    finally:
        server.stop()


def test_s3_gc_cleans_an_interrupted_publish(tmp_path, s3_store):
    url, opts = s3_store
    src = make_output(tmp_path / "out", n_clips=1)

    def crash(event, info):
        if event == "checked":
            raise RuntimeError("simulated crash after staging")

    with pytest.raises(PublishInterruptedError, match="simulated crash"):
        publish_release(src, url, "1.0.0", storage_options=opts, progress=crash, gate_report=gates_of(src))
    store = open_store(url, opts)
    assert store.find(f"{DS}/_staging/1.0.0") and store.exists(f"{DS}/_txn/1.0.0.json")
    report = gc(url, DS, older_than_s=0, storage_options=opts)
    assert report.removed_objects > 0
    assert not store.find(f"{DS}/_staging") and not store.find(f"{DS}/_txn") and not store.find(f"{DS}/1.0.0")
    publish_release(src, url, "1.0.0", storage_options=opts, gate_report=gates_of(src))
    assert verify_release(url, "1.0.0", storage_options=opts).ok
