"""Status model, status.json / status.html, and `drivetrack status` serving a published release's
page, rendered in headless Chromium."""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from drivetrack.release.status import SEGMENT_STAGES, ReleaseStatus, StatusError, read_status, write_status
from drivetrack.release.status_pages import render_status_html

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]
FAILED_BG = (0xF8, 0xD7, 0xDA)
DONE_BG = (0xD1, 0xE7, 0xDD)


def sample_status(n_done: int = 3) -> ReleaseStatus:
    st = ReleaseStatus(dataset="drivetrack-waymo", version="1.2.3", source="data/synthetic", store="store")
    st.update_release("list", "done", count=n_done + 2, unit="segments")
    st.update_release("segments", "running")
    for i in range(n_done):
        st.add_segment("training", f"seg-done-{i}", key=f"k{i}")
        for s in SEGMENT_STAGES:
            st.update("training", f"seg-done-{i}", s, "running")
            st.update("training", f"seg-done-{i}", s, "done", count=10 + i, unit="items", cached=(i == 0))
    st.add_segment("training", "seg-broken", key="kb")
    st.update("training", "seg-broken", "ingest", "done", count=30, unit="frames", seconds=0.5)
    st.update("training", "seg-broken", "depth", "failed",
              error="ValueError: camera_image/seg-broken.parquet: column '[CameraImageComponent].image' <bad> & co")
    st.update("training", "seg-broken", "tracks", "skipped")
    st.update("training", "seg-broken", "write", "skipped")
    st.add_segment("training", "seg-running", key="kr")
    st.update("training", "seg-running", "ingest", "running")
    return st


def test_states_counts_and_round_trip(tmp_path):
    st = sample_status()
    c = st.counts()
    assert c == {"pending": 0, "running": 1, "done": 3, "failed": 1, "skipped": 0}
    assert st.find("training", "seg-broken").state == "failed"
    assert st.find("training", "seg-broken").error.startswith("depth: ValueError: camera_image/seg-broken")
    assert st.find("training", "seg-done-0").cached and not st.find("training", "seg-done-1").cached
    assert st.stage_counts()["depth"]["failed"] == 1 and st.stage_counts()["tracks"]["skipped"] == 1
    done = st.find("training", "seg-done-1").stages["ingest"]
    assert done.seconds is not None and done.seconds >= 0 and done.finished >= done.started
    json_url, html_url = write_status(str(tmp_path / "out"), st)
    doc = json.loads(Path(json_url).read_text())
    assert doc["counts"]["failed"] == 1 and doc["state"] == "running"
    again = read_status(str(tmp_path / "out"))
    assert again.to_dict() == st.to_dict()
    assert not list((tmp_path / "out").glob(".*.tmp"))


def test_bad_updates_name_what_is_wrong():
    st = sample_status()
    with pytest.raises(StatusError, match=r"seg-broken stage depth: unknown state 'exploded'"):
        st.update("training", "seg-broken", "depth", "exploded")
    with pytest.raises(StatusError, match=r"no segment training/nope"):
        st.update("training", "nope", "depth", "done")
    with pytest.raises(StatusError, match=r"unknown stage 'paint'"):
        st.update("training", "seg-broken", "paint", "done")
    with pytest.raises(StatusError, match=r"already in the status"):
        st.add_segment("training", "seg-broken")
    with pytest.raises(StatusError, match=r"format"):
        ReleaseStatus.from_dict({"format": "other", "dataset": "d", "version": "1.0.0"})


def test_html_is_self_contained_and_lists_every_segment():
    st = sample_status()
    page = render_status_html(st)
    for seg in st.segments:
        assert f'data-segment="{seg.segment}" data-state="{seg.state}"' in page
    assert "&lt;bad&gt; &amp; co" in page and "<bad>" not in page   # errors are escaped
    assert "<script" not in page.lower()
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", page), "no external resources"
    assert "@import" not in page and "url(" not in page
    assert re.search(r'data-count="failed"[^>]*>failed: 1<', page)
    assert 'http-equiv="refresh"' not in page and 'http-equiv="refresh"' in render_status_html(st, refresh_s=5)


def _publish_status_release(store: Path, tmp_path: Path, st: ReleaseStatus) -> None:
    from drivetrack.release import publish_release

    from test_release import gates_of, make_output

    # a small output folder that publish accepts (its own bound gate report), with the status
    src = make_output(tmp_path / "release-src", n_clips=1)
    write_status(str(src), st)
    publish_release(str(src), str(store), st.version, gate_report=gates_of(src))


def _serve(args: list[str]):
    proc = subprocess.Popen([sys.executable, "-m", "drivetrack.cli", "status", *args, "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    m = re.search(r"(http://127\.0\.0\.1:\d+/)", line)
    if not m:
        proc.kill()
        raise AssertionError(f"drivetrack status did not start: {line!r} {proc.stderr.read()}")
    return proc, m.group(1)


def test_cli_prints_and_refuses_unknown_versions(tmp_path):
    st = sample_status()
    _publish_status_release(tmp_path / "store", tmp_path, st)
    out = subprocess.run([sys.executable, "-m", "drivetrack.cli", "status", str(tmp_path / "store"), "--print"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "drivetrack-waymo 1.2.3" in out.stdout and "failed" in out.stdout and "seg-broken" in out.stdout
    bad = subprocess.run([sys.executable, "-m", "drivetrack.cli", "status", str(tmp_path / "store"),
                          "--version", "9.9.9", "--print"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "9.9.9" in bad.stderr


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed "
                                              "(apt-get install -y chromium): no headless browser test")
def test_status_page_served_and_rendered_in_chromium(tmp_path):
    st = sample_status(n_done=6)
    st.update_release("segments", "failed", error="1 of 8 segments failed")
    _publish_status_release(tmp_path / "store", tmp_path, st)
    proc, url = _serve([str(tmp_path / "store"), "--version", "1.2.3"])
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            served = r.read().decode()
        # rendered from the published status.json and the release's own tables (quality beside state)
        from drivetrack.release.status_pages import read_quality

        quality = read_quality(str(tmp_path / "store" / "drivetrack-waymo" / "1.2.3"))
        assert served == render_status_html(st, quality=quality)
        assert 'data-segment="seg-broken" data-state="failed"' in served
        with urllib.request.urlopen(url + "status.json", timeout=10) as r:
            assert json.loads(r.read())["counts"]["failed"] == 1
        shot = tmp_path / "status.png"
        common = [CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'chromium-profile'}"]
        dom = subprocess.run([*common, "--dump-dom", url], capture_output=True, text=True, timeout=90)
        assert dom.returncode == 0, dom.stderr[-2000:]
        for seg in st.segments:
            assert f'data-segment="{seg.segment}"' in dom.stdout
        r = subprocess.run([*common, f"--screenshot={shot}", "--window-size=1280,900", url],
                           capture_output=True, text=True, timeout=90)
        assert r.returncode == 0 and shot.exists(), r.stderr[-2000:]
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    import imageio.v3 as iio

    img = np.asarray(iio.imread(shot))[..., :3].astype(int)
    assert img.shape[:2] == (900, 1280)

    def pixels(rgb):
        return int((np.abs(img - np.array(rgb)).sum(axis=-1) <= 6).sum())
    # the failed segment's and the done segments' cells are drawn in their state colours
    assert pixels(FAILED_BG) > 500, "no failed-state cell visible"
    assert pixels(DONE_BG) > 2 * pixels(FAILED_BG) > 0   # 6 done segments, 1 failed (and its quality cells)
    keep = os.environ.get("DRIVETRACK_KEEP_SCREENSHOT")
    if keep:
        shutil.copy(shot, keep)


def test_serving_a_build_folder_rerenders_live(tmp_path):
    st = sample_status()
    write_status(str(tmp_path / "build"), st)
    proc, url = _serve([str(tmp_path / "build")])
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            first = r.read().decode()
        assert 'data-segment="seg-running" data-state="running"' in first
        for s in SEGMENT_STAGES:
            st.update("training", "seg-running", s, "done")
        write_status(str(tmp_path / "build"), st)
        with urllib.request.urlopen(url, timeout=10) as r:
            second = r.read().decode()
        assert 'data-segment="seg-running" data-state="done"' in second
        assert 'http-equiv="refresh"' in second
    finally:
        proc.terminate()
        proc.wait(timeout=10)


# ---- quality beside state, previews and the version index, on a published annotation -------------

#: A bound some clips miss: track speeds agree with the labelled box speeds to 1e-7..1e-4 m/s on the
#: synthetic segments since the labels' tilt is one per object (label_tilt: constant; some were above 1e-3 before).
STRICT_BOUND_MPS = 1e-6
STRICT_GATES = {"object": {"speed_err_p50_max_mps": {"value": STRICT_BOUND_MPS, "reason": "demo: a bound some clips miss"}}}


def _status_of_folder(src: Path, version: str, previews: list[str]) -> ReleaseStatus:
    """A finished build's status for an annotation folder: one done segment per stats row."""
    import pandas as pd

    st = ReleaseStatus(dataset="drivetrack-waymo", version=version, source="synthetic", store="store")
    segs = pd.read_parquet(src / "stats" / "segments.parquet")
    for row in segs.itertuples():
        st.add_segment(row.split, row.segment, key=f"k-{row.segment}")
        for stage, count, unit in (("ingest", row.num_frames, "frames"), ("depth", 4, "depth batches"),
                                   ("tracks", row.num_object_clips_annotated, "object clips"),
                                   ("write", 2 * row.num_object_clips_annotated, "files")):
            st.update(row.split, row.segment, stage, "running")
            st.update(row.split, row.segment, stage, "done", count=int(count), unit=unit)
    for name in st.stages:
        st.update_release(name, "done")
    st.previews, st.published = previews, True
    return st


@pytest.fixture(scope="module")
def two_version_store(annotated_output, tmp_path_factory) -> Path:
    """0.1.0: the annotation without previews or gates; 0.2.0: with previews and a gate report
    that fails one bound (accepted), so the pages show failing gates with their values."""
    from drivetrack.gates import run_gates
    from drivetrack.release import publish_release
    from drivetrack.show import write_previews
    from drivetrack.release.status_pages import read_quality

    base = tmp_path_factory.mktemp("status_store")
    store = base / "store"
    src = base / "src"
    shutil.copytree(annotated_output, src)
    write_status(str(src), _status_of_folder(src, "0.1.0", []))
    publish_release(str(src), str(store), "0.1.0")
    root = str(src).rstrip("/") + "/"
    previews = [u[len(root):] for u in write_previews(str(src), per_split=2)]
    report = run_gates(str(src), STRICT_GATES).to_dict()
    assert not report["success"]
    write_status(str(src), _status_of_folder(src, "0.2.0", previews), quality=read_quality(str(src)))
    publish_release(str(src), str(store), "0.2.0", gate_report=report,
                    accept_failed_gates=f"demo: speed_err_p50 bound of {STRICT_BOUND_MPS} m/s is deliberately strict")
    return store


def test_quality_beside_state_from_the_release_tables(two_version_store):
    import pandas as pd

    from drivetrack.release.status_pages import read_quality

    rel = two_version_store / "drivetrack-waymo" / "0.2.0"
    q = read_quality(str(rel))
    objs = pd.read_parquet(rel / "stats" / "objects.parquet")
    segs = pd.read_parquet(rel / "stats" / "segments.parquet")
    assert q.gates_success is False and q.gates_failed >= 1
    for row in segs.itertuples():
        mine = objs[objs.segment == row.segment]
        got = q.of(row.split, row.segment)
        assert got["clips"] == row.num_object_clips_annotated and got["tracks"] == row.num_tracks
        assert got["speed_err_p50"] == pytest.approx(float(mine.speed_err_p50.median()))
        assert got["refined_share"] == pytest.approx(float(mine.refine_applied.eq(True).mean()))
        assert got["rejected"] == {c[len("rejected_"):]: int(getattr(row, c)) for c in segs.columns
                                   if c.startswith("rejected_") and getattr(row, c)}
        too_slow = mine[mine.speed_err_p50 > STRICT_BOUND_MPS]
        gate = [g for g in got["gates"] if g["gate"] == "object.speed_err_p50_max"]
        assert (len(gate) == 1 and gate[0]["num_failing"] == len(too_slow)) if len(too_slow) else not gate
    page = (rel / "status.html").read_text()    # the page published inside the release
    assert page.count('data-q="speed_err_p50"') == len(segs) and "object.speed_err_p50_max" in page
    from drivetrack.gates.report import _fmt

    assert "speed_err_p50=" in page and f"expected in [0, {_fmt(STRICT_BOUND_MPS)}]" in page


def _get(url: str) -> tuple[int, str, bytes]:
    import urllib.error

    try:
        with urllib.request.urlopen(url, timeout=20) as r:
            return r.status, r.headers.get("Content-Type", ""), r.read()
    except urllib.error.HTTPError as e:
        return e.code, "", b""


def _screenshot(url: str, shot: Path, tmp_path: Path, height: int) -> np.ndarray:
    import imageio.v3 as iio

    common = [CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'chromium-profile'}"]
    r = subprocess.run([*common, f"--screenshot={shot}", f"--window-size=1500,{height}",
                        "--virtual-time-budget=3000", url], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and shot.exists(), r.stderr[-2000:]
    return np.asarray(iio.imread(shot))[..., :3].astype(int)


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed "
                                              "(apt-get install -y chromium): no headless browser test")
def test_version_index_page_and_previews_served_and_rendered_in_chromium(two_version_store, tmp_path):
    proc, url = _serve([str(two_version_store)])
    try:
        code, ctype, body = _get(url)
        index = body.decode()
        assert code == 200 and ctype.startswith("text/html")
        assert index.index('data-version="0.2.0"') < index.index('data-version="0.1.0"'), "newest first"
        assert 'href="0.2.0/"' in index and "first version" in index and "from 0.1.0: +" in index
        assert ">accepted<" in index and "2 done, 0 failed" in index
        code, _, body = _get(url + "0.2.0/")
        page = body.decode()
        assert code == 200 and 'data-q="gates"' in page and "object.speed_err_p50_max" in page
        st = json.loads(_get(url + "0.2.0/status.json")[2])
        assert st["previews"]
        for rel in st["previews"]:
            code, ctype, data = _get(url + "0.2.0/" + rel)
            expect = (two_version_store / "drivetrack-waymo" / "0.2.0" / rel).read_bytes()
            assert code == 200 and data == expect and ctype == ("image/png" if rel.endswith(".png") else "video/mp4")
        assert _get(url + "0.2.0/manifest.json")[0] == 404 and _get(url + "9.9.9/")[0] == 404
        assert _get(url + "0.2.0")[0] == 200  # redirected to 0.2.0/

        img = _screenshot(url + "0.2.0/", tmp_path / "status-page.png", tmp_path, 1300)
        common = [CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'chromium-profile'}"]
        dom = subprocess.run([*common, "--dump-dom", url + "0.2.0/"], capture_output=True, text=True, timeout=120)
        assert dom.stdout.count("<img") == sum(1 for p in st["previews"] if p.endswith(".png"))
        assert int((np.abs(img - np.array(DONE_BG)).sum(axis=-1) <= 6).sum()) > 500, "no done-state cells"
        assert int((np.abs(img - np.array(FAILED_BG)).sum(axis=-1) <= 6).sum()) > 200, "no failing-gate cell"
        index_img = _screenshot(url, tmp_path / "version-index.png", tmp_path, 420)
        assert int((np.abs(index_img - np.array(FAILED_BG)).sum(axis=-1) <= 6).sum()) > 100, "gate outcome cell"
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    keep = os.environ.get("DRIVETRACK_KEEP_SCREENSHOTS")
    if keep:
        shutil.copy(tmp_path / "status-page.png", Path(keep) / "status-page.png")
        shutil.copy(tmp_path / "version-index.png", Path(keep) / "version-index.png")


def test_depth_stage_records_the_gpu_queue_choice_per_batch():
    """The flow's depth stage carries completer, device and per-batch records (issue 17.2); they
    survive status.json and show on the page."""
    from drivetrack.release.status import ReleaseStatus
    from drivetrack.release.status_pages import render_status_html

    status = ReleaseStatus(dataset="d", version="0.1.0")
    status.add_segment("training", "seg")
    batches = [{"camera": 1, "frames": 8, "completer": "nearest-torch", "device": "cuda:0",
                "worker": "tcp://127.0.0.1:1", "seconds": 0.5}]
    status.update("training", "seg", "depth", "done", count=1, unit="depth batches", worker="tcp://127.0.0.1:1",
                  completer="nearest-torch", device="cuda:0", batches=batches)
    again = ReleaseStatus.from_dict(status.to_dict())
    depth = again.segments[0].stages["depth"]
    assert (depth.completer, depth.device, depth.batches) == ("nearest-torch", "cuda:0", batches)
    assert "nearest-torch on cuda:0" in render_status_html(again)
