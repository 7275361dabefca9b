"""Hostile inputs to publish (issue 13, items 3, 4 and 6): publish ships only regular files of the
output contract whose clips match the declared formats, with a gate report bound to exactly that
content, and never clips of segments that did not finish.

One real annotation (the session fixture ``annotated_output``) is copied once and gated once;
every test tampers with its own copy and checks that nothing became visible in the store.
"""
from __future__ import annotations

import io
import json
import os
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from drivetrack.release import (GateBindingError, GatesFailedError, InvalidSourceError, publish_release,
                                read_manifest, verify_release)

DS = "drivetrack-waymo"


@pytest.fixture(scope="module")
def gated(annotated_output, tmp_path_factory):
    """(a copy of the annotation output, the report of the gates run on it)."""
    from drivetrack.gates import run_gates

    base = tmp_path_factory.mktemp("hostile_publish") / "out"
    shutil.copytree(annotated_output, base, symlinks=True)
    report = run_gates(str(base), data_docs=False).to_dict()
    assert report["success"], [r["gate"] for r in report["failures"]]
    return base, report


@pytest.fixture
def out(gated, tmp_path) -> Path:
    dst = tmp_path / "out"
    shutil.copytree(gated[0], dst, symlinks=True)
    return dst


@pytest.fixture
def report(gated) -> dict:
    return json.loads(json.dumps(gated[1]))


def _nothing_published(store: Path) -> None:
    left = sorted(str(p.relative_to(store)) for p in store.rglob("*") if p.is_file()) if store.exists() else []
    assert not [p for p in left if not p.endswith((".lock",))], left


def _refused(out: Path, store: Path, report: dict, error=InvalidSourceError, **kw) -> str:
    with pytest.raises(error) as info:
        publish_release(out, store, "1.0.0", gate_report=report, workers=2, **kw)
    _nothing_published(store)
    return str(info.value)


def _clips(out: Path, folder: str = "clips") -> list[Path]:
    """The clips tables of ``out`` (``folder="frames"``: its frames tables)."""
    return sorted((out / folder).glob("*/*.parquet"))


@pytest.fixture(scope="module")
def exported(gated, tmp_path_factory) -> Path:
    """The gated output's clips exported as npz (what ``publish_npz`` publishes)."""
    from drivetrack.compact.export import FORMATS, export_clips

    dst = tmp_path_factory.mktemp("hostile_publish_npz")
    export_clips(str(gated[0]), list(FORMATS), str(dst))
    return dst


def _npz_clips(root: Path, folder: str = "tracks") -> list[Path]:
    return sorted((root / folder).glob("*/waymo_*.npz"))


def _npz_copy(exported: Path, tmp_path: Path, folder: str = "tracks", index: int = 0) -> Path:
    src = _npz_clips(exported, folder)[index]
    dst = tmp_path / folder / src.parent.name / src.name
    dst.parent.mkdir(parents=True)
    shutil.copy(src, dst)
    return dst


def _npz_refused(path: Path, layout: str = "drivetrack") -> str:
    """The refusal publish (with ``publish_npz``) makes of an npz clip: its header check."""
    from drivetrack.release.contents import check_clip_npz

    with pytest.raises(InvalidSourceError) as info, open(path, "rb") as f:
        check_clip_npz(f, str(path), layout)
    return str(info.value)


def _rewrite_npz(path: Path, change) -> None:
    """Re-save ``path`` with its arrays passed through ``change(dict) -> dict`` (pickles allowed)."""
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    np.savez(path, **change(arrays))


# ---- item 3: publish takes only regular files of the output contract --------------------------

def test_symlink_to_a_file_outside_is_refused(out, report, tmp_path):
    secret = tmp_path / "secret.json"
    secret.write_text(json.dumps({"aws_secret_access_key": "leaked"}))
    (out / "run.json").unlink()
    (out / "run.json").symlink_to(secret)
    msg = _refused(out, tmp_path / "store", report)
    assert "run.json" in msg and "symbolic link" in msg


def test_symlinked_folder_is_refused(out, report, tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "waymo_x_FRONT_1.png").write_bytes(b"\x89PNG not really")
    (out / "previews").mkdir()
    (out / "previews" / "training").symlink_to(elsewhere, target_is_directory=True)
    msg = _refused(out, tmp_path / "store", report)
    assert "previews/training" in msg and "symbolic link" in msg


def test_dotfile_is_refused(out, report, tmp_path):
    (out / ".env").write_text("AWS_SECRET_ACCESS_KEY=leaked\n")
    msg = _refused(out, tmp_path / "store", report)
    assert ".env" in msg and "hidden" in msg


def test_unknown_file_and_fifo_are_refused(out, report, tmp_path):
    (out / "stats" / "notes.txt").write_text("scratch")
    os.mkfifo(out / "run.fifo")
    msg = _refused(out, tmp_path / "store", report)
    assert "stats/notes.txt: not a release member" in msg
    assert "run.fifo: a fifo" in msg


def test_npz_with_an_object_member_is_refused(exported, tmp_path):
    clip = _npz_copy(exported, tmp_path)
    payload = np.empty(1, dtype=object)
    payload[0] = {"pickled": "payload"}
    _rewrite_npz(clip, lambda a: {**a, "lidar_sources": payload})
    msg = _npz_refused(clip)
    assert clip.name in msg and "'lidar_sources'" in msg and "|O" in msg


@pytest.mark.parametrize("change, words", [
    (lambda a: {**a, "tracks": a["tracks"].astype(np.float64)}, ["'tracks'", "<f8", "float32"]),
    (lambda a: {**a, "visibles": a["visibles"][:, :-1]}, ["'visibles'", "T="]),
    (lambda a: {**a, "extra": np.zeros(3)}, ["['extra']", "not part of"]),
    (lambda a: {k: v for k, v in a.items() if k != "points3d"}, ["missing", "points3d"]),
], ids=["wrong-dtype", "wrong-shape", "extra-member", "missing-member"])
def test_npz_member_not_as_declared_is_refused(exported, tmp_path, change, words):
    clip = _npz_copy(exported, tmp_path, index=-1)
    _rewrite_npz(clip, change)
    msg = _npz_refused(clip)
    assert clip.name in msg
    for w in words:
        assert w in msg, msg


def test_tapvid3d_member_not_as_declared_is_refused(exported, tmp_path):
    clip = _npz_copy(exported, tmp_path, "tapvid3d")
    _rewrite_npz(clip, lambda a: {**a, "tracks_XYZ": np.swapaxes(a["tracks_XYZ"], 0, 1)})
    msg = _npz_refused(clip, "tapvid3d")
    assert clip.name in msg and "'tracks_XYZ'" in msg


def test_truncated_npz_is_refused(exported, tmp_path):
    # a member whose stored data is shorter than its header declares (the zip itself is intact)
    clip = _npz_copy(exported, tmp_path)
    with np.load(clip) as z:
        arrays = {k: z[k] for k in z.files}
    buf = io.BytesIO()
    np.lib.format.write_array(buf, arrays["tracks"])
    with zipfile.ZipFile(clip, "w") as zf:
        for k, v in arrays.items():
            if k == "tracks":
                zf.writestr("tracks.npy", buf.getvalue()[:-100])
            else:
                b = io.BytesIO()
                np.lib.format.write_array(b, v)
                zf.writestr(f"{k}.npy", b.getvalue())
    msg = _npz_refused(clip)
    assert clip.name in msg and "'tracks'" in msg and "bytes" in msg
    # and a file cut short (no central directory)
    whole = _npz_clips(exported)[1].read_bytes()
    clip.write_bytes(whole[: len(whole) // 2])
    msg = _npz_refused(clip)
    assert clip.name in msg and "not a readable .npz" in msg


def test_truncated_clips_table_is_refused(out, report, tmp_path):
    table = _clips(out)[0]
    table.write_bytes(table.read_bytes()[: table.stat().st_size // 2])
    msg = _refused(out, tmp_path / "store", report)
    assert f"clips/{table.parent.name}/{table.name}: not a readable Parquet table" in msg


def test_npz_in_the_source_are_left_out_unless_publish_npz(out, report, exported, tmp_path):
    """Without ``publish_npz`` stray npz files of the source are not published; with it, npz are
    exported from the tables (stale or tampered ones replaced) and published."""
    stale = out / "tracks" / "training" / _npz_clips(exported)[0].name
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"not what the tables hold")
    store = tmp_path / "store"
    publish_release(out, store, "1.0.0", gate_report=report, workers=2)
    files = {f["path"] for f in read_manifest(store, "1.0.0")["files"]}
    assert not [f for f in files if f.endswith(".npz")]
    publish_release(out, store, "1.0.1", gate_report=report, workers=2, publish_npz=True)
    manifest = read_manifest(store, "1.0.1")
    npz = sorted(f["path"] for f in manifest["files"] if f["path"].endswith(".npz"))
    assert npz == sorted(p.relative_to(exported).as_posix() for p in exported.rglob("*.npz"))
    assert (store / DS / "1.0.1" / stale.relative_to(out)).read_bytes() == (exported / stale.relative_to(out)).read_bytes()
    split = manifest["counts"]["splits"]["training"]
    assert split["clips"] == split["npz_clips"] == split["tapvid3d_clips"] == len(npz) // 2
    assert verify_release(store, "1.0.1").ok


def test_statistics_table_without_its_schema_is_refused(out, report, tmp_path):
    path = out / "stats" / "rejections.parquet"
    pd.read_parquet(path).drop(columns=["reason"]).to_parquet(path)
    msg = _refused(out, tmp_path / "store", report)
    assert "stats/rejections.parquet" in msg and "lacks column(s) ['reason']" in msg
    path.write_bytes(b"PAR1 not parquet PAR1")
    msg = _refused(out, tmp_path / "store2", report)
    assert "stats/rejections.parquet: cannot be read as parquet" in msg


# ---- item 4: a gate report is bound to the content it validated ---------------------------------

def test_forged_report_is_refused(out, tmp_path):
    msg = _refused(out, tmp_path / "store", {"success": True, "results": []}, GateBindingError)
    assert "binding" in msg


def test_report_with_a_contradicting_verdict_is_refused(out, report, tmp_path):
    report["results"][0]["success"] = False  # success stays True
    msg = _refused(out, tmp_path / "store", report, GateBindingError)
    assert "results failed" in msg


def test_report_of_a_different_folder_is_refused(out, report, tmp_path):
    # other content: one segment's tables fewer (a path difference, caught before anything is written)
    gone = _clips(out)[0]
    frames = [p for p in _clips(out, "frames") if p.name.startswith(gone.stem)]
    for p in [gone, *frames]:
        p.unlink()
    msg = _refused(out, tmp_path / "store", report, GateBindingError)
    assert f"clips/{gone.parent.name}/{gone.name}" in msg and f"frames/{frames[0].parent.name}/{frames[0].name}" in msg


def test_clip_changed_after_the_gates_same_size_is_refused(out, report, tmp_path):
    # same size, other bytes: caught on the staged bytes, and the staging is cleaned up
    # (a byte of a JPEG in a frames table: the table still reads, only its sha256 tells)
    clip = _clips(out, "frames")[0]
    data = bytearray(clip.read_bytes())
    data[len(data) // 2] ^= 0xFF
    clip.write_bytes(bytes(data))
    msg = _refused(out, tmp_path / "store", report, GateBindingError)
    assert f"frames/{clip.parent.name}/{clip.name}: sha256" in msg


def test_edited_statistics_table_is_refused(out, report, tmp_path):
    path = out / "stats" / "objects.parquet"
    df = pd.read_parquet(path)
    df.loc[0, "visible_fraction"] = 0.99
    df.to_parquet(path)
    msg = _refused(out, tmp_path / "store", report, GateBindingError)
    assert "stats/objects.parquet: sha256" in msg


def test_no_report_runs_the_gates_and_failed_gates_are_recorded(out, tmp_path):
    # no report: the gates run now; here they fail (a clip with visible points outside the image)
    path = out / "stats" / "objects.parquet"
    df = pd.read_parquet(path)
    df.loc[0, "num_visible_outside_image"] = 7
    df.to_parquet(path)
    store = tmp_path / "store"
    with pytest.raises(GatesFailedError):
        publish_release(out, store, "1.0.0", workers=2)
    _nothing_published(store)
    assert (out / "validation" / "gates.json").exists()
    publish_release(out, store, "1.0.0", workers=2, accept_failed_gates="test: known bad clip")
    manifest = read_manifest(store, "1.0.0")
    gates = manifest["gates"]
    assert gates["success"] is False and gates["ran_by"] == "publish"
    assert gates["accepted_failure_reason"] == "test: known bad clip"
    card = (store / DS / "1.0.0" / "README.md").read_text()
    assert "Gates FAILED" in card and "Published despite failed gates" in card
    assert verify_release(store, "1.0.0").ok


def test_bound_report_publishes_and_is_recorded(out, report, tmp_path):
    store = tmp_path / "store"
    publish_release(out, store, "1.0.0", gate_report=report, workers=2)
    gates = read_manifest(store, "1.0.0")["gates"]
    assert gates["success"] is True and gates["binding_sha256"] == report["binding"]["sha256"]
    croissant = (store / DS / "1.0.0" / "croissant.json").read_text()
    assert "|O" not in croissant


# ---- item 6: no partial files, no clips of failed segments -------------------------------------

def test_partial_files_are_refused(out, report, tmp_path):
    clip = _clips(out)[0]
    shutil.copy(clip, clip.parent / ".partial-k3j2h1.parquet")
    msg = _refused(out, tmp_path / "store", report)
    assert ".partial-k3j2h1.parquet" in msg


def test_clips_of_a_failed_segment_are_refused(out, report, tmp_path):
    path = out / "stats" / "segments.parquet"
    df = pd.read_parquet(path)
    failed = str(df.loc[0, "segment"])
    df.loc[0, "status"] = "failed"
    df.to_parquet(path)
    msg = _refused(out, tmp_path / "store", report)
    theirs = [p for p in _clips(out) + _clips(out, "frames") if p.name.startswith(failed)]
    assert theirs
    for p in theirs[:5]:
        assert p.name in msg
    assert "recorded as 'failed'" in msg
