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

from drivetrack.status import (SEGMENT_STAGES, ReleaseStatus, StatusError, read_status, render_status_html,
                               write_status)

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

    src = tmp_path / "release-src"
    write_status(str(src), st)
    (src / "run.json").write_text(json.dumps({"config": {}, "segments": []}))
    publish_release(str(src), str(store), st.version)


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
        assert served == (tmp_path / "store" / "drivetrack-waymo" / "1.2.3" / "status.html").read_text()
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
    assert pixels(DONE_BG) > 5 * pixels(FAILED_BG) > 0
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
