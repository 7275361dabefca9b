"""Release store on local folders: publish, verify (ours and sha256sum -c), cards, Croissant
(validated by mlcroissant), immutability, conflicts, interrupted publishes, gc, diff, CLI."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import threading
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from drivetrack.cli import main as cli
from drivetrack.release import (ConcurrentPublishError, GateBindingError, GatesFailedError, InvalidSourceError,
                                InvalidVersionError, ManifestError, PublishConflictError,
                                PublishInterruptedError, SemVer, StagingCheckError, VersionExistsError,
                                VersionNotFoundError, diff_versions, gc, list_versions, open_store,
                                publish_release, read_manifest, verify_release)
from drivetrack.release.errors import CasConflictError
from drivetrack.release.manifest import manifest_hash

DS = "drivetrack-waymo"


PAPER = np.array([0.0651, 0.1260, 0.2471, 0.5497, 0.8687])  # speed-error percentiles (m/s) at the paper's scale
T_FRAMES = 24  # the gates' minimum clip length


def _clip_arrays(rng, n: int, t: int) -> dict[str, dict[str, np.ndarray]]:
    """Small arrays of one clip in both layouts, as the writers declare them (docs/formats.md)."""
    visibles = rng.random((n, t)) > 0.3
    return {
        "tracks": {"video": rng.integers(0, 255, (t, 6, 8, 3), dtype=np.uint8),
                   "tracks": rng.random((n, t, 2)).astype(np.float32), "visibles": visibles,
                   "timestamps_micros": np.arange(t, dtype=np.int64) * 100_000,
                   "query_frames": np.zeros(n, np.int32), "lidar_sources": np.ones((n, 4), np.int32),
                   "points3d": rng.random((n, t, 3)).astype(np.float32)},
        "tapvid3d": {"images_jpeg_bytes": np.array([b"\xff\xd8jpeg\xff\xd9"] * t),
                     "tracks_XYZ": rng.random((t, n, 3)).astype(np.float32),
                     "visibility": np.ascontiguousarray(visibles.T),
                     "queries_xyt": rng.random((n, 3)).astype(np.float32),
                     "fx_fy_cx_cy": np.array([100.0, 100.0, 4.0, 3.0], np.float32),
                     "extrinsics_w2c": np.tile(np.eye(4, dtype=np.float32), (t, 1, 1)),
                     "distortion_k1_k2_p1_p2_k3": np.zeros(5, np.float32),
                     "timestamps_micros": np.arange(t, dtype=np.int64) * 100_000}}


def _jpeg(rgb: np.ndarray) -> bytes:
    import cv2

    ok, data = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]))
    assert ok
    return data.tobytes()


def write_v2_clip(root: Path, split: str, segment: str, object_id: str, n: int, rng, t: int = T_FRAMES) -> str:
    """One clip as release layout v2 (docs/formats.md): ``clips/{split}/{segment}.parquet`` with its
    row and ``frames/{split}/{segment}_FRONT.parquet`` with its frames. Returns the clips table path."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from drivetrack.compact.layout import CLIPS_SCHEMA, FRAMES_SCHEMA, parquet_options

    arrays = _clip_arrays(rng, n, t)["tracks"]
    stem = f"waymo_{segment}_FRONT_{object_id}"
    row = {"clip": stem, "split": split, "segment": segment, "camera": "FRONT", "object_id": object_id,
           "object_type": "VEHICLE", "num_tracks": n, "num_frames": t, "frames": list(range(t)),
           "timestamps_micros": arrays["timestamps_micros"].tolist(), "tracks": arrays["tracks"].ravel().tolist(),
           "visibles": arrays["visibles"].ravel().tolist(), "query_frames": arrays["query_frames"].tolist(),
           "lidar_sources": arrays["lidar_sources"].ravel().tolist(),
           "points_box": rng.random(3 * n).tolist(), "vehicle_from_box": np.tile(np.eye(4), (t, 1, 1)).ravel().tolist(),
           "query_pixels": [0.5] * (2 * n),
           "width": 8, "height": 6, "intrinsics": [100.0, 100.0, 4.0, 3.0, 0, 0, 0, 0, 0],
           "camera_from_vehicle": np.tile(np.eye(4), (t, 1, 1)).ravel().tolist(),
           "world_from_vehicle": np.tile(np.eye(4), (t, 1, 1)).ravel().tolist()}
    clips = root / "clips" / split / f"{segment}.parquet"
    frames = root / "frames" / split / f"{segment}_FRONT.parquet"
    clips.parent.mkdir(parents=True, exist_ok=True)
    frames.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_pylist([row], schema=CLIPS_SCHEMA), clips, **parquet_options(CLIPS_SCHEMA))
    pq.write_table(pa.Table.from_pydict({
        "segment": [segment] * t, "camera": ["FRONT"] * t, "frame": list(range(t)),
        "timestamp_micros": row["timestamps_micros"],
        "image": [{"bytes": _jpeg(arrays["video"][i]), "path": None} for i in range(t)]},
        schema=FRAMES_SCHEMA), frames, **parquet_options(FRAMES_SCHEMA))
    return f"clips/{split}/{segment}.parquet"


_GATED: dict[tuple, dict[str, bytes]] = {}


def make_output(root: Path, *, seed: int = 0, n_clips: int = 2, splits=("training", "validation")) -> Path:
    """A small annotation output folder in the documented layout (docs/architecture.md) that passes
    the default gates, with its gate report in ``validation/`` (the gates run once per distinct
    content; the clips are written with deterministic bytes, so copies share the report)."""
    rng = np.random.default_rng(seed)
    rows, seg_rows, rej_rows = [], [], []
    for split in splits:
        for i in range(n_clips):
            segment = f"seg{i}" if split == splits[0] else f"{split[0]}seg{i}"  # segment ids are unique
            n = 60 + i
            table = write_v2_clip(root, split, segment, f"{split[:3]}{i}", n, rng)
            err = PAPER * (1 + 0.1 * i + 0.01 * seed)
            rows.append({"split": split, "segment": segment, "camera": "FRONT", "object_id": f"{split[:3]}{i}",
                         "object_type": "VEHICLE", "file": table, "num_tracks": n,
                         "num_frames": T_FRAMES, "visible_fraction": 0.5 + 0.1 * i, "min_camera_distance_m": 10.0,
                         **{f"speed_err_{p}": float(v) for p, v in zip(("p25", "p50", "p75", "p95", "p99"), err)},
                         "num_nonfinite_visible": 0, "num_visible_outside_image": 0})
            too_far = int(i == 0)
            seg_rows.append({"split": split, "segment": segment, "status": "done",
                             "num_object_clips_considered": 1 + too_far, "num_object_clips_annotated": 1,
                             "rejected_too_far": too_far})
            rej_rows += [{"segment": segment, "reason": "too_far"}] * too_far
    (root / "stats").mkdir(exist_ok=True)
    pd.DataFrame(rows).to_parquet(root / "stats" / "objects.parquet")
    pd.DataFrame(seg_rows).to_parquet(root / "stats" / "segments.parquet")
    pd.DataFrame(rej_rows).to_parquet(root / "stats" / "rejections.parquet")
    (root / "run.json").write_text(json.dumps({
        "config": {"depth": {"completer": "nearest"}}, "code_version": {"drivetrack": "0.1.0"}, "seed": seed,
        "segments": [{"segment": "seg0", "split": "training", "sources": {"camera_image": "a" * 64}}]}))
    key = (seed, n_clips, tuple(splits))
    if key not in _GATED:
        from drivetrack.gates import run_gates

        report = run_gates(str(root), data_docs=False)
        assert report.success, [f.gate for f in report.failures]
        _GATED[key] = {p.relative_to(root).as_posix(): p.read_bytes()
                       for p in (root / "validation").rglob("*") if p.is_file()}
    for rel, data in _GATED[key].items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(data)
    return root


def gates_of(root: Path) -> dict:
    """The gate report in ``root/validation/gates.json`` (bound to that folder's content)."""
    return json.loads((root / "validation" / "gates.json").read_text())


def failing_report(root: Path) -> dict:
    """Make one clip of ``root`` have visible points outside the image in its statistics, run the
    gates (they fail) and return their report, bound to the edited folder."""
    from drivetrack.gates import run_gates

    path = root / "stats" / "objects.parquet"
    df = pd.read_parquet(path)
    df.loc[0, "num_visible_outside_image"] = 3
    df.to_parquet(path)
    report = run_gates(str(root), data_docs=False).to_dict()
    assert not report["success"]
    return report


@pytest.fixture
def output(tmp_path) -> Path:
    return make_output(tmp_path / "out")


def sha256sum_check(folder: Path) -> subprocess.CompletedProcess:
    return subprocess.run(["sha256sum", "-c", "--strict", "SHA256SUMS"], cwd=folder, capture_output=True, text=True)


def test_publish_local_verifies_with_drivetrack_and_sha256sum(output, tmp_path):
    store = tmp_path / "store"
    result = publish_release(output, store, "1.0.0", gate_report=gates_of(output))
    vdir = store / DS / "1.0.0"
    assert result.latest == "1.0.0" and result.files == len(list(p for p in vdir.rglob("*") if p.is_file())) - 1
    report = verify_release(store, "1.0.0")
    assert report.ok and report.files_checked == result.files
    done = sha256sum_check(vdir)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.count(": OK") == result.files - 1  # SHA256SUMS does not list itself
    # Nothing left of the transaction; the release files are read-only.
    assert not list((store / DS).glob("_staging/*")) and not list((store / DS).glob("_txn/*"))
    assert not os.access(vdir / "manifest.json", os.W_OK) or os.geteuid() == 0
    assert not (os.stat(vdir / "manifest.json").st_mode & 0o222)


def test_manifest_records_inputs_and_hash(output, tmp_path):
    publish_release(output, tmp_path / "store", "1.0.0", config={"note": "first"}, gate_report=gates_of(output))
    m = read_manifest(tmp_path / "store", "1.0.0")
    assert m["manifest_sha256"] == manifest_hash(m)
    files = {f["path"]: f for f in m["files"]}
    src = output / "clips" / "training" / "seg0.parquet"
    import hashlib
    assert files["clips/training/seg0.parquet"] == {
        "path": "clips/training/seg0.parquet", "size": src.stat().st_size,
        "sha256": hashlib.sha256(src.read_bytes()).hexdigest()}
    assert {"README.md", "croissant.json", "SHA256SUMS", "run.json", "stats/objects.parquet"} <= set(files)
    assert m["segments"][0]["sources"]["camera_image"] == "a" * 64
    assert m["config"] == {"annotation": {"depth": {"completer": "nearest"}}, "publish": {"note": "first"}}
    assert m["run"]["seed"] == 0 and m["code_version"]["drivetrack"]
    assert m["counts"]["splits"]["training"] == {"clips": 2, "npz_clips": 0, "tapvid3d_clips": 0,
                                                 "bytes": m["counts"]["splits"]["training"]["bytes"]}
    assert m["statistics"]["objects"]["num_tracks_total"] == 2 * (60 + 61)
    assert m["statistics"]["segments"]["rejected_too_far_total"] == 2
    # Editing the manifest breaks its top-level hash, and verify refuses it.
    path = tmp_path / "store" / DS / "1.0.0" / "manifest.json"
    os.chmod(path, 0o644)
    path.write_text(path.read_text().replace('"note": "first"', '"note": "edited"'))
    with pytest.raises(ManifestError, match="manifest_sha256"):
        verify_release(tmp_path / "store", "1.0.0")


def test_cards_hf_front_matter_and_croissant_validates(output, tmp_path):
    import mlcroissant as mlc

    publish_release(output, tmp_path / "store", "1.0.0", gate_report=gates_of(output))
    vdir = tmp_path / "store" / DS / "1.0.0"
    text = (vdir / "README.md").read_text()
    front = yaml.safe_load(text.split("---\n")[1])
    assert front["license"] and front["pretty_name"] and front["size_categories"] == ["n<1K"]
    assert front["task_categories"]
    configs = {c["config_name"]: c for c in front["configs"]}
    assert configs["clips"]["data_files"] == [{"split": "training", "path": "clips/training/*.parquet"},
                                              {"split": "validation", "path": "clips/validation/*.parquet"}]
    assert configs["clips"]["default"] is True
    assert configs["frames"]["data_files"][0] == {"split": "training", "path": "frames/training/*.parquet"}
    infos = {i["config_name"]: i["features"] for i in front["dataset_info"]}
    assert {"name": "image", "dtype": "image"} in infos["frames"]
    assert {"name": "tracks", "list": "float32"} in infos["clips"]
    assert "| object.visible_inside_image | pass |" in text and "Citation" in text and "sha256sum -c SHA256SUMS" in text

    doc = json.loads((vdir / "croissant.json").read_text())
    assert doc["conformsTo"] == "http://mlcommons.org/croissant/1.1"
    sums = dict(reversed(line.split("  ", 1)) for line in (vdir / "SHA256SUMS").read_text().splitlines())
    objects = [d for d in doc["distribution"] if d["@type"] == "cr:FileObject"]
    assert objects and all(d["sha256"] == sums[d["contentUrl"]] for d in objects)
    ds = mlc.Dataset(jsonld=str(vdir / "croissant.json"))
    assert not ds.metadata.issues.errors, ds.metadata.issues.report()
    fields = {f.name: f for rs in ds.metadata.record_sets if rs.name == "clips" for f in rs.fields}
    assert fields["tracks"].is_array and fields["num_tracks"].data_types
    clips = sorted((r["clips/clip"].decode(), len(r["clips/tracks"])) for r in ds.records("clips"))
    assert clips[0] == ("waymo_seg0_FRONT_tra0", 60 * 24 * 2)
    frames = list(ds.records("frames"))
    assert len(frames) == 4 * 24
    # The stats record set really loads through mlcroissant from the release folder.
    records = list(ds.records("stats-objects"))
    assert len(records) == 4 and sorted(r["stats-objects/num_tracks"] for r in records) == [60, 60, 61, 61]


def test_second_publish_of_same_version_fails_and_leaves_first_untouched(output, tmp_path):
    store = tmp_path / "store"
    publish_release(output, store, "1.0.0", gate_report=gates_of(output))
    before = {p: p.read_bytes() for p in (store / DS / "1.0.0").rglob("*") if p.is_file()}
    other = make_output(tmp_path / "other", seed=5)
    with pytest.raises(VersionExistsError, match="already published"):
        publish_release(other, store, "1.0.0", gate_report=gates_of(other))
    after = {p: p.read_bytes() for p in (store / DS / "1.0.0").rglob("*") if p.is_file()}
    assert after == before
    assert verify_release(store, "1.0.0").ok


@pytest.mark.parametrize("bad", ["1.0", "v1.0.0", "01.0.0", "1.0.0-", "latest", "1.0.0+build+x", "1.0.0+b5"])
def test_versions_are_checked(output, tmp_path, bad):
    import re

    with pytest.raises(InvalidVersionError, match=re.escape(repr(bad))):
        publish_release(output, tmp_path / "store", bad, gate_report=gates_of(output))
    assert not (tmp_path / "store").exists()


def test_semver_precedence():
    order = ["1.0.0-alpha", "1.0.0-alpha.1", "1.0.0-alpha.beta", "1.0.0-beta", "1.0.0-beta.2",
             "1.0.0-beta.11", "1.0.0-rc.1", "1.0.0", "1.0.1", "1.2.0", "10.0.0"]
    assert sorted(order[::-1], key=SemVer.parse) == order
    assert SemVer.parse("1.0.0+build.5") == SemVer.parse("1.0.0")


def test_failed_gates_write_nothing_unless_accepted(output, tmp_path):
    store = tmp_path / "store"
    failed = failing_report(output)
    with pytest.raises(GatesFailedError, match="object.visible_inside_image"):
        publish_release(output, store, "1.0.0", gate_report=failed)
    assert not store.exists()
    publish_release(output, store, "1.0.0", gate_report=failed, accept_failed_gates="known label noise in seg0")
    m = read_manifest(store, "1.0.0")
    assert m["gates"]["success"] is False and m["gates"]["accepted_failure_reason"] == "known label noise in seg0"
    assert "known label noise in seg0" in (store / DS / "1.0.0" / "README.md").read_text()
    with pytest.raises(GateBindingError, match="'success'"):
        publish_release(output, store, "1.1.0", gate_report={"results": []})


def test_bad_sources_raise_clear_errors(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InvalidSourceError, match="holds no files"):
        publish_release(empty, tmp_path / "store", "1.0.0")
    with pytest.raises(InvalidSourceError, match="does not exist"):
        publish_release(tmp_path / "missing", tmp_path / "store", "1.0.0")
    reserved = tmp_path / "reserved"
    reserved.mkdir()
    (reserved / "README.md").write_text("mine")
    with pytest.raises(InvalidSourceError, match="README.md: not a release member"):
        publish_release(reserved, tmp_path / "store", "1.0.0")
    badrun = tmp_path / "badrun"
    badrun.mkdir()
    (badrun / "run.json").write_text("{not json")
    with pytest.raises(InvalidSourceError, match=r"badrun/run.json: run.json is not valid JSON"):
        publish_release(badrun, tmp_path / "store", "1.0.0")
    badtable = make_output(tmp_path / "badtable")
    (badtable / "clips" / "validation" / "vseg0.parquet").write_bytes(b"not parquet")
    with pytest.raises(InvalidSourceError, match=r"clips/validation/vseg0.parquet: not a readable Parquet table"):
        publish_release(badtable, tmp_path / "store", "1.0.0", gate_report=gates_of(badtable))
    assert not (tmp_path / "store").exists()


def test_arbitrary_folder_is_refused_naming_every_file(tmp_path):
    # publish ships the output contract only (docs/release.md "What publish refuses")
    src = tmp_path / "plain"
    (src / "a").mkdir(parents=True)
    (src / "a" / "x.bin").write_bytes(b"\x00" * 10)
    (src / "top.txt").write_text("hello")
    (src / "empty.dat").write_bytes(b"")
    with pytest.raises(InvalidSourceError) as info:
        publish_release(src, tmp_path / "store", "0.1.0")
    assert all(f"{p}: not a release member" in str(info.value) for p in ("a/x.bin", "top.txt", "empty.dat"))
    assert not (tmp_path / "store").exists()


def test_verify_reports_missing_extra_and_corrupt(output, tmp_path):
    store = tmp_path / "store"
    publish_release(output, store, "1.0.0", gate_report=gates_of(output))
    vdir = store / DS / "1.0.0"
    victim = vdir / "clips" / "training" / "seg0.parquet"
    os.chmod(victim, 0o644)
    data = bytearray(victim.read_bytes())
    data[100] ^= 0xFF  # same size, different content
    victim.write_bytes(bytes(data))
    short = vdir / "frames" / "validation" / "vseg1_FRONT.parquet"
    os.chmod(short, 0o644)
    short.write_bytes(short.read_bytes()[:-1])
    (vdir / "stats" / "segments.parquet").unlink()
    (vdir / "clips" / "training" / "intruder.parquet").write_bytes(b"x")
    report = verify_release(store, "1.0.0")
    assert not report.ok
    assert report.missing == ["stats/segments.parquet"]
    assert report.extra == ["clips/training/intruder.parquet"]
    assert [(c["path"], c["problem"]) for c in report.corrupt] == [
        ("clips/training/seg0.parquet", "sha256"), ("frames/validation/vseg1_FRONT.parquet", "size")]
    assert sha256sum_check(vdir).returncode != 0
    assert cli(["verify", str(store), "--version", "1.0.0"]) == 1


def test_concurrent_publishes_of_one_version_exactly_one_wins(tmp_path):
    store = tmp_path / "store"
    sources = [make_output(tmp_path / f"src{i}") for i in range(4)]
    barrier = threading.Barrier(len(sources))
    outcomes: list = [None] * len(sources)

    def attempt(i):
        barrier.wait()
        try:
            outcomes[i] = publish_release(sources[i], store, "2.0.0", workers=2,
                                          gate_report=gates_of(sources[i]))
        except PublishConflictError as e:
            outcomes[i] = e

    threads = [threading.Thread(target=attempt, args=(i,)) for i in range(len(sources))]
    [t.start() for t in threads]
    [t.join() for t in threads]
    winners = [i for i, o in enumerate(outcomes) if not isinstance(o, Exception)]
    assert len(winners) == 1, outcomes
    losers = [o for o in outcomes if isinstance(o, Exception)]
    assert all(isinstance(e, (ConcurrentPublishError, VersionExistsError)) for e in losers)
    assert all("2.0.0" in str(e) for e in losers)
    assert verify_release(store, "2.0.0").ok
    m = read_manifest(store, "2.0.0")
    assert m["source"] == str(sources[winners[0]])
    assert [v["version"] for v in list_versions(store)] == ["2.0.0"]


def test_concurrent_publishes_of_different_versions_all_indexed(output, tmp_path):
    store = tmp_path / "store"
    versions = ["1.0.0", "1.1.0", "1.2.0-rc.1", "0.9.0", "1.0.1"]
    errors = []

    def attempt(v):
        try:
            publish_release(output, store, v, workers=1, gate_report=gates_of(output))
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)

    threads = [threading.Thread(target=attempt, args=(v,)) for v in versions]
    [t.start() for t in threads]
    [t.join() for t in threads]
    assert not errors
    index = json.loads((store / DS / "versions.json").read_text())
    assert [v["version"] for v in index["versions"]] == ["0.9.0", "1.0.0", "1.0.1", "1.1.0", "1.2.0-rc.1"]
    assert json.loads((store / DS / "latest.json").read_text())["version"] == "1.1.0"  # rc is not latest
    assert all(v["indexed"] for v in list_versions(store))



def test_local_writes_survive_concurrent_pruning_of_shared_folders(tmp_path):
    """The end of one publish removes ``_staging``/``_txn`` when empty while another publish is
    creating its first file below them (CI once lost a publish to this). Writers re-create
    vanished parents; a pruner spinning as fast as it can must not make one of them fail."""
    store = open_store(tmp_path / "s")
    errors, done = [], threading.Event()

    def pruner():
        while not done.is_set():
            store.prune_empty("D/_staging")
            store.prune_empty("D/_txn")

    def writer(k):
        try:
            for i in range(300):
                store.put_if_absent(f"D/_txn/{k}.json", b"claim")
                store.write_bytes(f"D/_staging/v{k}/x/{i}.bin", b"1")
                with store.open_write(f"D/_staging/v{k}/a.bin") as f:
                    f.write(b"2")
                store.move(f"D/_staging/v{k}/a.bin", f"D/v{k}/a.bin")
                assert store.read_bytes(f"D/v{k}/a.bin") == b"2"
                store.compare_and_swap(f"D/_txn/{k}.json", b"next", store.read_with_token(f"D/_txn/{k}.json")[1])
                store.delete_tree(f"D/_staging/v{k}")
                store.delete_tree(f"D/v{k}")
                store.delete(f"D/_txn/{k}.json")
                store.prune_empty("D/_staging")
                store.prune_empty("D/_txn")
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)

    spinner = threading.Thread(target=pruner)
    writers = [threading.Thread(target=writer, args=(k,)) for k in range(3)]
    spinner.start()
    [t.start() for t in writers]
    [t.join() for t in writers]
    done.set()
    spinner.join()
    assert not errors, errors
    # Only empty folders are pruned, and only while empty: the dataset folder stays with its content.
    assert not (tmp_path / "s" / "D" / "_staging").exists() and not (tmp_path / "s" / "D" / "_txn").exists()
    store.write_bytes("D/keep.json", b"{}")
    store.prune_empty("D")
    assert store.read_bytes("D/keep.json") == b"{}"

def test_compare_and_swap_local(tmp_path):
    store = open_store(tmp_path / "s")
    store.put_if_absent("d/x.json", b"1")
    with pytest.raises(FileExistsError):
        store.put_if_absent("d/x.json", b"2")
    data, token = store.read_with_token("d/x.json")
    assert data == b"1"
    store.compare_and_swap("d/x.json", b"3", token)
    with pytest.raises(CasConflictError, match="changed underneath"):
        store.compare_and_swap("d/x.json", b"4", token)  # stale token
    with pytest.raises(CasConflictError):
        store.compare_and_swap("d/x.json", b"5", None)  # expected absent
    assert store.read_bytes("d/x.json") == b"3"


def test_write_error_interrupts_cleanly_then_gc_and_republish(output, tmp_path):
    store = tmp_path / "store"
    # A regular file where the staging folder of one split must go: the OS refuses the write.
    blocker = store / DS / "_staging" / "1.0.0"
    blocker.parent.mkdir(parents=True)

    def block(event, info):
        if event == "uploaded" and not (blocker / "frames").exists():
            (blocker / "frames").write_text("in the way")

    with pytest.raises(PublishInterruptedError) as err:
        publish_release(output, store, "1.0.0", workers=1, progress=block, gate_report=gates_of(output))
    msg = str(err.value)
    assert "uploading" in msg and "frames/" in msg and "No version is visible" in msg
    assert "drivetrack gc" in msg
    assert list_versions(store) == []
    with pytest.raises(VersionNotFoundError, match="interrupted"):
        verify_release(store, "1.0.0")
    with pytest.raises(ConcurrentPublishError, match="resume"):
        publish_release(output, store, "1.0.0")  # the claim is still held
    report = gc(store, DS, older_than_s=0)
    assert any("claim" in a for a in report.actions)
    assert not list((store / DS).glob("_txn/*")) and not list((store / DS).glob("_staging/*"))
    publish_release(output, store, "1.0.0", gate_report=gates_of(output))
    assert verify_release(store, "1.0.0").ok


def test_interrupted_publish_can_be_resumed(output, tmp_path):
    store = tmp_path / "store"

    class Crash(Exception):
        pass

    def crash_after_promotion(event, info):
        if event == "promoted":
            raise Crash("simulated crash before commit")

    with pytest.raises(PublishInterruptedError, match="simulated crash"):
        publish_release(output, store, "1.0.0", progress=crash_after_promotion, gate_report=gates_of(output))
    # The files are in the version folder but without a manifest there is no version.
    assert (store / DS / "1.0.0" / "SHA256SUMS").exists() and list_versions(store) == []
    assert cli(["verify", str(store), "--version", "1.0.0"]) == 2
    result = publish_release(output, store, "1.0.0", resume=True, gate_report=gates_of(output))
    assert result.reused_files == sum(1 for p in output.rglob("*") if p.is_file())
    assert verify_release(store, "1.0.0").ok
    assert [v["version"] for v in list_versions(store)] == ["1.0.0"]


def test_staged_object_corrupted_before_check_is_caught(output, tmp_path):
    store = tmp_path / "store"

    def corrupt(event, info):
        if event == "staged":
            p = store / DS / "_staging" / "1.0.0" / "run.json"
            p.write_bytes(p.read_bytes().replace(b"nearest", b"NEAREST"))

    with pytest.raises(PublishInterruptedError) as err:
        publish_release(output, store, "1.0.0", progress=corrupt, gate_report=gates_of(output))
    assert isinstance(err.value.__cause__, StagingCheckError)
    assert "run.json" in str(err.value) and "sha256" in str(err.value)
    assert list_versions(store) == [] and not (store / DS / "1.0.0" / "manifest.json").exists()


def test_gc_keeps_recent_claims_and_repairs_index(output, tmp_path):
    store = tmp_path / "store"
    publish_release(output, store, "1.0.0", gate_report=gates_of(output))
    (store / DS / "versions.json").unlink()
    (store / DS / "latest.json").unlink()
    (store / DS / "_txn").mkdir(exist_ok=True)
    (store / DS / "_txn" / "1.1.0.json").write_text(json.dumps({"txid": "x", "started_unix": 4e9}))
    report = gc(store, DS)  # default age threshold: the (future-dated) claim is kept
    assert report.skipped_recent and (store / DS / "_txn" / "1.1.0.json").exists()
    assert json.loads((store / DS / "latest.json").read_text())["version"] == "1.0.0"
    assert [v["version"] for v in json.loads((store / DS / "versions.json").read_text())["versions"]] == ["1.0.0"]
    assert verify_release(store, "latest").ok


def test_diff_versions(tmp_path):
    store = tmp_path / "store"
    a = make_output(tmp_path / "a", seed=0, n_clips=2)
    publish_release(a, store, "1.0.0", gate_report=gates_of(a))
    from drivetrack.gates import run_gates
    write_v2_clip(a, "training", "seg0", "tra0", 60, np.random.default_rng(9))
    (a / "clips" / "validation" / "vseg1.parquet").unlink()
    (a / "frames" / "validation" / "vseg1_FRONT.parquet").unlink()
    write_v2_clip(a, "validation", "vseg9", "val9", 20, np.random.default_rng(9))
    segments = pd.read_parquet(a / "stats" / "segments.parquet")
    extra = segments.iloc[[-1]].assign(segment="vseg9")
    pd.concat([segments, extra], ignore_index=True).to_parquet(a / "stats" / "segments.parquet")
    # gates run on a copy (same content, so the report binds to a) to keep a's validation/ as it was
    shutil.copytree(a, tmp_path / "a2")
    report = run_gates(str(tmp_path / "a2"), data_docs=False).to_dict()
    publish_release(a, store, "1.1.0", gate_report=report, accept_failed_gates="test: clips edited by hand")
    d = diff_versions(store, "1.0.0", "1.1.0")
    assert d.added == ["clips/validation/vseg9.parquet", "frames/validation/vseg9_FRONT.parquet"]
    assert d.removed == ["clips/validation/vseg1.parquet", "frames/validation/vseg1_FRONT.parquet"]
    assert d.changed == ["clips/training/seg0.parquet", "frames/training/seg0_FRONT.parquet", "stats/segments.parquet"]
    assert "counts.files" not in d.deltas  # one removed, one added: unchanged values are not listed
    bytes_old = read_manifest(store, "1.0.0")["counts"]["bytes"]
    bytes_new = read_manifest(store, "1.1.0")["counts"]["bytes"]
    assert d.deltas["counts.bytes"] == {"old": bytes_old, "new": bytes_new, "delta": bytes_new - bytes_old}
    with pytest.raises(VersionNotFoundError, match="Published: 1.0.0, 1.1.0"):
        diff_versions(store, "1.0.0", "3.0.0")


def test_cli_publish_versions_diff_verify_gc(output, tmp_path, capsys):
    store = str(tmp_path / "store")
    forged = tmp_path / "forged.json"
    forged.write_text(json.dumps({"success": True, "results": []}))
    assert cli(["publish", str(output), "--store", store, "--version", "1.0.0", "--gate-report", str(forged)]) == 1
    assert "binding" in capsys.readouterr().err
    report = tmp_path / "gates.json"
    report.write_text(json.dumps(failing_report(output)))
    assert cli(["publish", str(output), "--store", store, "--version", "1.0.0", "--gate-report", str(report)]) == 3
    assert "object.visible_inside_image" in capsys.readouterr().err
    assert cli(["publish", str(output), "--store", store, "--version", "1.0.0", "--gate-report", str(report),
                "--accept-failed-gates", "reviewed by hand"]) == 0
    assert cli(["publish", str(output), "--store", store, "--version", "1.0.0", "--gate-report", str(report),
                "--accept-failed-gates", "again"]) == 1
    assert "already published" in capsys.readouterr().err
    assert cli(["publish", str(output), "--store", store, "--version", "1.0", "--gate-report", str(report)]) == 1
    assert cli(["verify", store, "--version", "1.0.0"]) == 0
    assert "OK:" in capsys.readouterr().out
    assert cli(["versions", store, "--json"]) == 0
    assert [v["version"] for v in json.loads(capsys.readouterr().out)] == ["1.0.0"]
    assert cli(["diff", store, "1.0.0", "1.0.0"]) == 0
    assert "0 added, 0 removed, 0 changed" in capsys.readouterr().out
    assert cli(["gc", store, "--older-than", "0"]) == 0


def test_local_cas_lock_is_stale_by_its_age_not_by_the_wait(tmp_path):
    """A lock left by a killed writer (old mtime) is named; a live one delays the writer only."""
    import os
    import threading
    import time as _time

    from drivetrack.release import LockTimeoutError
    from drivetrack.release.store import open_store

    store = open_store(str(tmp_path / "store"))
    store.compare_and_swap("d/versions.json", b"1", None)
    _, token = store.read_with_token("d/versions.json")
    lock = store.path("d/versions.json") + ".lock"
    # a live holder for 0.3 s: the writer waits, then succeeds
    open(lock, "w").close()
    threading.Timer(0.3, os.unlink, args=(lock,)).start()
    start = _time.monotonic()
    store.compare_and_swap("d/versions.json", b"2", token)
    assert _time.monotonic() - start >= 0.25
    assert store.read_with_token("d/versions.json")[0] == b"2"
    # a stale lock (an hour old): a clear error naming it and the way out
    open(lock, "w").close()
    old = _time.time() - 3600
    os.utime(lock, (old, old))
    with pytest.raises(LockTimeoutError, match=r"versions\.json\.lock.*held for 3600 s.*drivetrack gc"):
        store.compare_and_swap("d/versions.json", b"3", store.read_with_token("d/versions.json")[1])
