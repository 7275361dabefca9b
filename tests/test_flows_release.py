"""The release flow end to end on a small synthetic source, on one Prefect server and a local
Dask cluster: an induced failure in one segment leaves the other done and blocks publishing
(gates); the re-run after the fix recomputes only that segment and publishes; a scheduled run
of unchanged inputs publishes nothing; the release verifies and its status page lists every
segment."""
from __future__ import annotations

import json
import re
import shutil
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

pytestmark = pytest.mark.slow

SEGMENTS = 2
FRAMES = 26          # >= the 24-frame field-of-view filter
GATES = None        # the default gates of infra/gates.yaml
CONFIG = {"track": {"cameras": ["FRONT"]}}


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    from drivetrack.synth import SynthConfig, generate_segment

    root = tmp_path_factory.mktemp("source")
    cfg = SynthConfig(seed=7, frames=FRAMES, preset="small", cameras=("FRONT",))
    for i in range(SEGMENTS):
        generate_segment(str(root), cfg, i)
    return root


@pytest.fixture(scope="module")
def prefect_server():
    from flows.runtime import prefect_api

    with prefect_api() as url:
        yield url


def _status(out: str) -> dict:
    return json.loads((Path(out) / "status.json").read_text())


def test_release_flow_isolates_failures_resumes_and_skips_unchanged(source, prefect_server, tmp_path):
    from drivetrack.release import list_versions, verify_release
    from drivetrack.waymo.reader import list_segments
    from flows.release import release

    store, work = tmp_path / "store", tmp_path / "work"
    segs = list_segments(str(source), "training")
    assert len(segs) == SEGMENTS
    bad, good = segs[0], segs[1]
    bad_file = source / "training" / "camera_image" / f"{bad}.parquet"
    original = bad_file.read_bytes()
    bad_file.write_bytes(original[: len(original) // 3])  # a truncated upload
    common = dict(source=str(source), store=str(store), work=str(work), gates_config=GATES, config=CONFIG, n_workers=2,
                  threads_per_worker=1, dask_processes=False)

    # 1. one segment fails: the other is done, the failure is reported, the gates block publishing
    r1 = release(version="0.1.0", **common)
    assert r1["published"] is False and "quality gates failed" in r1["error"]
    st1 = _status(r1["out"])
    by_seg = {s["segment"]: s for s in st1["segments"]}
    assert by_seg[good]["state"] == "done" and not by_seg[good]["cached"]
    assert by_seg[bad]["state"] == "failed"
    assert by_seg[bad]["stages"]["ingest"]["state"] == "failed"
    assert bad in by_seg[bad]["error"] or "camera_image" in by_seg[bad]["error"], by_seg[bad]["error"]
    assert by_seg[bad]["stages"]["write"]["state"] == "skipped"
    assert st1["stages"]["gates"]["state"] == "failed" and st1["stages"]["publish"]["state"] == "failed"
    assert list_versions(str(store)) == []
    # the good segment's depth jobs ran on a worker holding the GPU resource (CPU drain here)
    assert by_seg[good]["stages"]["depth"]["count"] > 0 and by_seg[good]["stages"]["depth"]["worker"]
    arts1 = _run_markdown(r1["flow_run_id"])
    seg_md = {seg: next(a for k, a in arts1.items() if k.startswith("release-0-1-0-segment-") and seg in a)
              for seg in segs}
    assert "| ingest | failed |" in seg_md[bad] and "segment.status" in seg_md[bad], seg_md[bad]
    assert "Gates: release FAILED" in seg_md[good] and "- clips: " in seg_md[good]
    assert "0 of 2 segments reused" in arts1["release-0-1-0-reused"]
    good_record = next((work / "segments" / "training" / good).glob("*/_done.json"))
    stamp = good_record.stat().st_mtime_ns

    # 2. fix the file and re-run: only the failed segment is computed, the release publishes
    bad_file.write_bytes(original)
    r2 = release(version="0.1.0", **common)
    assert r2["published"] is True, r2
    st2 = _status(r2["out"])
    by_seg = {s["segment"]: s for s in st2["segments"]}
    assert by_seg[good]["state"] == "done" and by_seg[good]["cached"] is True
    assert by_seg[bad]["state"] == "done" and by_seg[bad]["cached"] is False
    assert good_record.stat().st_mtime_ns == stamp, "the unchanged segment was recomputed"
    report = verify_release(str(store), "0.1.0")
    assert report.ok and report.files_checked > 5
    published = store / "drivetrack-waymo" / "0.1.0"
    page = (published / "status.html").read_text()
    for s in segs:
        assert f'data-segment="{s}" data-state="done"' in page
    pub_status = json.loads((published / "status.json").read_text())
    assert pub_status["published"] is True and pub_status["counts"]["done"] == SEGMENTS
    assert pub_status["state"] == "done" and pub_status["stages"]["publish"]["state"] == "done"
    # previews are in the release, listed on its status page and linked from its card
    assert pub_status["stages"]["previews"]["state"] == "done" and pub_status["previews"]
    for rel in pub_status["previews"]:
        assert (published / rel).exists(), rel
        assert f'href="{rel}"' in page
    card = (published / "README.md").read_text()
    assert "## Previews" in card and any(p in card for p in pub_status["previews"])
    run = json.loads((published / "run.json").read_text())
    assert run["release_fingerprint"] == r2["fingerprint"]
    assert {s["segment"] for s in run["segments"]} == set(segs)
    assert all(s["source_checksums"]["camera_image"].startswith("sha256:") for s in run["segments"])

    # the Prefect UI's view: the segment table and the progress artifacts of this test's runs
    # (filtered by flow run: artifact keys are global, another release may have made the same)
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import (ArtifactFilter, ArtifactFilterFlowRunId, ArtifactFilterKey,
                                                FlowFilter, FlowFilterName)

    with get_client(sync_client=True) as client:
        runs = [r.id for r in client.read_flow_runs(flow_filter=FlowFilter(name=FlowFilterName(any_=["release-build"])))
                if (r.parameters or {}).get("work") == str(work) and (r.parameters or {}).get("version") == "0.1.0"]
        assert len(runs) == 2, runs
        arts = client.read_artifacts(artifact_filter=ArtifactFilter(
            key=ArtifactFilterKey(any_=["release-0-1-0-segments", "release-0-1-0-progress"]),
            flow_run_id=ArtifactFilterFlowRunId(any_=runs)))
    kinds = {a.key: a for a in arts}
    assert set(kinds) == {"release-0-1-0-segments", "release-0-1-0-progress"}
    latest_table = max((a for a in arts if a.key.endswith("segments")), key=lambda a: a.created)
    rows = json.loads(latest_table.data) if isinstance(latest_table.data, str) else latest_table.data
    assert {r["segment"] for r in rows} == set(segs) and {r["state"] for r in rows} == {"done"}
    assert max(float(a.data) for a in arts if a.key.endswith("progress")) == 100.0

    # Prefect shows the reuse: the reused segment is named in this run's artifact (it has no task
    # run), and every segment has its summary with quality and gate results
    arts2 = _run_markdown(r2["flow_run_id"])
    reused = arts2["release-0-1-0-reused"]
    assert "1 of 2 segments reused" in reused and good in reused and bad not in reused
    for seg in segs:
        md = next(a for k, a in arts2.items() if k.startswith("release-0-1-0-segment-") and f"/{seg}:" in a)
        assert f"training/{seg}: done" in md and "Gates: release passed" in md
        assert re.search(r"- clips: [1-9]", md) and re.search(r"- tracks: [1-9]", md), md
        assert re.search(r"- speed error p50 \(median over clips\): [0-9.e+-]+ m/s", md), md
        assert ("reused" in md.splitlines()[0]) == (seg == good)
    # the page shows quality beside state
    assert 'data-q="speed_err_p50"' in page and 'data-q="gates"' in page

    # an explicit version that exists is refused before any work
    from drivetrack.release import VersionExistsError

    with pytest.raises(VersionExistsError, match="0.1.0 is already published"):
        release(version="0.1.0", **common)

    # 3. a scheduled run (version auto) of unchanged inputs, config and code publishes nothing
    from drivetrack.release.keys import code_fingerprint

    code_before = code_fingerprint()
    r3 = release(version="auto", skip_unchanged=True, **common)
    if code_fingerprint() != code_before or code_before != json.loads(
            (published / "run.json").read_text())["code_fingerprint"]:
        # The package was edited while this test ran (a shared working tree, never CI's clean
        # clone): the code fingerprint moved mid-run, so "unchanged" cannot be asserted.
        pytest.skip("drivetrack/ changed during the test run; the unchanged-inputs check needs a stable tree")
    assert r3["published"] is False and r3["unchanged_since"] == "0.1.0"
    assert [v["version"] for v in list_versions(str(store))] == ["0.1.0"]
    assert _status(r3["out"])["counts"]["done"] == SEGMENTS
    assert all(s["cached"] for s in _status(r3["out"])["segments"])


def _run_markdown(flow_run_id: str) -> dict[str, str]:
    """The markdown artifacts of one flow run, by key (looked up by the run, not by a global key)."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterFlowRunId, ArtifactFilterType

    with get_client(sync_client=True) as client:
        arts = client.read_artifacts(artifact_filter=ArtifactFilter(
            flow_run_id=ArtifactFilterFlowRunId(any_=[flow_run_id]), type=ArtifactFilterType(any_=["markdown"])))
    return {a.key: a.data for a in arts}


def test_unknown_segment_fails_before_any_work(source, prefect_server, tmp_path):
    from flows.release import release

    with pytest.raises(ValueError, match="segment 'no_such_segment' is not in"):
        release(version="0.2.0", source=str(source), store=str(tmp_path / "store"), work=str(tmp_path / "work"),
                segments=["no_such_segment"], n_workers=1, dask_processes=False)
    st = _status(str(tmp_path / "work" / "releases" / "0.2.0"))
    assert st["stages"]["list"]["state"] == "failed" and "no_such_segment" in st["stages"]["list"]["error"]
    shutil.rmtree(tmp_path / "work")


def test_flow_logs_reach_the_api_before_the_server_stops(prefect_server):
    """Logs queued for the API are sent when drained (what prefect_api does before stopping its
    server), not left to a late batch that finds the server gone."""
    import asyncio
    import uuid

    from prefect import flow, get_run_logger
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import LogFilter, LogFilterFlowRunId

    from flows.runtime import _drain_api_logs

    marker = f"drain-check-{uuid.uuid4().hex}"

    @flow(name="log-drain-check")
    def noisy():
        get_run_logger().info(marker)
        from prefect.runtime import flow_run
        return flow_run.id

    run_id = noisy()
    _drain_api_logs()

    async def messages():
        async with get_client() as client:
            logs = await client.read_logs(log_filter=LogFilter(flow_run_id=LogFilterFlowRunId(any_=[run_id])))
            return [log.message for log in logs]

    assert marker in asyncio.run(messages())
