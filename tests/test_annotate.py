"""The annotation pipeline end to end on a small synthetic source (drivetrack.annotate + CLI)."""
from __future__ import annotations

import glob
import json
import os
import shutil

import numpy as np
import pandas as pd
import pytest

from drivetrack.annotate import (AnnotateConfig, annotate, complete_depth_batch, load_scene_for,
                                 sparse_depth_batches, track_segment)
from drivetrack.cli import main
from drivetrack.tracks import plan_segment

DRIVETRACK_KEYS = {"video": np.uint8, "tracks": np.float32, "visibles": np.bool_, "timestamps_micros": np.int64,
                   "query_frames": np.int32, "lidar_sources": np.int32, "points3d": np.float32}


def _drivetrack_files(out: str) -> list[str]:
    return sorted(f for f in glob.glob(f"{out}/**/waymo_*.npz", recursive=True) if "tapvid3d" not in f)


def _clip_ids(out: str) -> list[str]:
    """Clip ids of every row of the output's clips tables (release layout v2)."""
    import pyarrow.parquet as pq

    return sorted(c for path in glob.glob(f"{out}/clips/*/*.parquet")
                  for c in pq.read_table(path, columns=["clip"]).column("clip").to_pylist())


def test_output_is_the_v2_layout(annotated_output):
    """annotate writes clips and frames tables, no npz."""
    assert _clip_ids(annotated_output)
    assert glob.glob(f"{annotated_output}/frames/training/*_FRONT.parquet")
    assert not _drivetrack_files(annotated_output)


def test_exported_outputs_load_with_plain_numpy(exported_output):
    files = _drivetrack_files(exported_output)
    assert files, "the synthetic source must yield at least one annotated clip"
    for path in files:
        with np.load(path, allow_pickle=False) as z:
            assert set(DRIVETRACK_KEYS) <= set(z.files), path
            for key, dtype in DRIVETRACK_KEYS.items():
                assert z[key].dtype == dtype, (path, key, z[key].dtype)
            n, t = z["visibles"].shape
            assert z["video"].shape[0] == t and z["video"].shape[-1] == 3
            assert z["tracks"].shape == (n, t, 2) and z["points3d"].shape == (n, t, 3)
            assert z["lidar_sources"].shape == (n, 4) and z["query_frames"].shape == (n,)
            assert np.all(z["visibles"].any(axis=1)), "every track is visible in at least one frame"
            assert np.all(np.diff(z["timestamps_micros"]) > 0)
            vis = z["visibles"]
            xy = z["tracks"][vis]
            h, w = z["video"].shape[1:3]
            assert np.all(np.isfinite(xy))
            assert np.all((xy[:, 0] >= 0) & (xy[:, 0] < w) & (xy[:, 1] >= 0) & (xy[:, 1] < h))


def test_tables_and_run_json(annotated_output, synth_segments):
    objects = pd.read_parquet(f"{annotated_output}/stats/objects.parquet")
    segments = pd.read_parquet(f"{annotated_output}/stats/segments.parquet")
    assert sorted(segments["segment"]) == sorted(synth_segments)
    assert set(segments["status"]) == {"done"}
    assert len(objects) == len(_clip_ids(annotated_output))
    for column in ("speed_err_p25", "speed_err_p50", "speed_err_p95", "num_tracks", "visible_fraction"):
        assert column in objects.columns
    # every file named in the table exists, relative to the output folder
    for rel in objects["file"]:
        assert os.path.exists(os.path.join(annotated_output, rel)), rel
    run = json.load(open(f"{annotated_output}/run.json"))
    assert run["config"] == AnnotateConfig().to_dict()
    assert run["config_fingerprint"] == AnnotateConfig().fingerprint()
    assert [s["segment"] for s in run["segments"]] == synth_segments
    for s in run["segments"]:
        assert s["status"] == "done"
        checks = s["source_files"]
        assert {"lidar", "lidar_box", "vehicle_pose", "camera_image"} <= set(checks)
        assert all(len(c["sha256"]) == 64 for c in checks.values())


def test_staged_api_matches_one_call(synth_source, synth_segments, annotated_output, exported_output):
    """Stages run one by one (as the flow does), in this thread, give the same tracks as annotate()
    with its depth batches and object jobs in two threads (conftest)."""
    config = AnnotateConfig()
    segment = synth_segments[0]
    scene = load_scene_for(synth_source, "training", segment, config)
    plan = plan_segment(scene, config.track)
    batches = sparse_depth_batches(scene, config, plan)
    assert all(not b.dense and b.maps.dtype == np.float32 for b in batches)
    dense = [complete_depth_batch(b, config) for b in batches]
    assert all(d.dense and d.method == "nearest" for d in dense)
    with pytest.raises(ValueError, match="already completed"):
        complete_depth_batch(dense[0], config)
    with pytest.raises(ValueError, match="not completed"):
        track_segment(scene, batches, config, plan)
    results = [t for t in track_segment(scene, dense, config, plan) if t.rejection is None]
    files = [f for f in _drivetrack_files(exported_output) if segment in os.path.basename(f)]
    assert len(results) == len(files)
    for t in results:
        match = [f for f in files if f.endswith(f"_{t.camera_name}_{t.object_id}.npz")]
        assert len(match) == 1
        with np.load(match[0], allow_pickle=False) as z:
            np.testing.assert_array_equal(z["tracks"], t.tracks)
            np.testing.assert_array_equal(z["visibles"], t.visibles)


def test_failing_segment_is_isolated_and_named(synth_source, synth_segments, tmp_path):
    """A truncated component file fails its segment with the file named; the other is done."""
    source = tmp_path / "src"
    shutil.copytree(synth_source, source)
    bad = source / "training" / "lidar_box" / f"{synth_segments[1]}.parquet"
    data = bad.read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    out = tmp_path / "out"
    results = annotate(str(source), "training", synth_segments, str(out), AnnotateConfig())
    assert [r.status for r in results] == ["done", "failed"]
    assert results[1].stage == "ingest"
    assert "lidar_box" in results[1].error and synth_segments[1] in results[1].error
    segments = pd.read_parquet(out / "stats" / "segments.parquet").set_index("segment")
    assert segments.loc[synth_segments[1], "status"] == "failed"
    assert "lidar_box" in segments.loc[synth_segments[1], "error"]
    assert not [f for f in _clip_ids(str(out)) if synth_segments[1] in f]
    assert not glob.glob(f"{out}/*/training/{synth_segments[1]}*.parquet")
    assert [f for f in _clip_ids(str(out)) if synth_segments[0] in f]


def test_cli_exit_codes(synth_source, synth_segments, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["annotate", synth_source, "--out", str(out), "--segment", synth_segments[0],
                 "--depth", "ipbasic"]) == 0
    run = json.load(open(out / "run.json"))
    assert run["config"]["track"]["depth_completer"] == "ipbasic"
    assert main(["annotate", synth_source, "--out", str(out), "--segment", "no_such_segment"]) == 1
    assert main(["annotate", synth_source, "--out", str(out), "--depth", "no-such-method"]) == 2
    err = capsys.readouterr().err
    assert "no-such-method" in err and "nearest" in err


def test_config_file_unknown_key_is_named(tmp_path):
    from drivetrack.commands.annotate import load_config

    path = tmp_path / "c.yaml"
    path.write_text("track:\n  min_frames: 10\nrefine_poses: false\n")
    assert load_config(str(path)).track.min_frames == 10
    path.write_text("track:\n  min_frame: 10\n")
    with pytest.raises(ValueError, match="min_frame"):
        load_config(str(path))


def test_the_staged_core_with_injected_depth_map_and_progress_gives_the_cli_files(
        synth_source, synth_segments, annotated_output, tmp_path):
    """The flow's segment task and `drivetrack annotate` run one function: with the flow's kind of
    depth_fn / map_fn / on_stage injected, the clip files are the CLI's byte for byte."""
    import hashlib
    from pathlib import Path

    from drivetrack.annotate import STAGES, AnnotateConfig, complete_depth_batch, run_segment_stages

    config, segment = AnnotateConfig(), synth_segments[0]
    events, mapped, depth_calls = [], [], []

    def depth_fn(batches):
        depth_calls.append(len(batches))
        return [complete_depth_batch(b, config) for b in batches], {"worker": "here"}

    def map_fn(fn, jobs):
        mapped.append(len(jobs))
        return [fn(j) for j in jobs]

    out = tmp_path / "seg"
    result = run_segment_stages(synth_source, "training", segment, str(out), config, map_fn=map_fn,
                                depth_fn=depth_fn, on_stage=lambda s, st, info: events.append((s, st, info)),
                                write_segment_stats=True)
    assert result.status == "done", result.error
    assert [(s, st) for s, st, _ in events] == [(s, st) for s in STAGES for st in ("running", "done")]
    done = {s: info for s, st, info in events if st == "done"}
    assert done["depth"]["worker"] == "here" and done["depth"]["count"] == depth_calls[0] > 0
    assert mapped and done["write"]["count"] == len(result.files) > 0
    assert {p.name for p in (out / "stats").iterdir()} == {"objects.parquet", "segments.parquet",
                                                            "rejections.parquet"}
    for url in result.files:
        rel = Path(url).relative_to(out)
        assert hashlib.sha256((out / rel).read_bytes()).digest() == \
            hashlib.sha256((Path(annotated_output) / rel).read_bytes()).digest(), rel

    events.clear()
    with pytest.raises(Exception, match="no_such_segment"):
        run_segment_stages(synth_source, "training", "no_such_segment", str(tmp_path / "bad"), config,
                           on_stage=lambda s, st, info: events.append((s, st, info)), raise_errors=True)
    assert [(s, st) for s, st, _ in events] == [("ingest", "running"), ("ingest", "failed")]
    failed = run_segment_stages(synth_source, "training", "no_such_segment", str(tmp_path / "bad"), config)
    assert failed.status == "failed" and failed.stage == "ingest" and "no_such_segment" in failed.error
