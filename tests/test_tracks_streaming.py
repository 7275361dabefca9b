"""The writers stream tracks, points3d, video and TAPVid-3D arrays: files equal the whole arrays."""
from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from test_tracks import DT, FRONT, H, SceneBuilder, W, camera_model, world_center

from drivetrack.tracks import (
    TrackConfig,
    core,
    kernel,
    object_jobs,
    prepare_segment,
    run_object_job,
    write_object_outputs,
)
from drivetrack.tracks.writers import OPENCV_FROM_WAYMO_CAMERA, decode_video

ROLLING = TrackConfig(rolling_shutter=True, chunk_points=97, depth_completer_options={"max_reach_px": 3.0})
GLOBAL = TrackConfig(rolling_shutter=False, depth_completer_options={"max_reach_px": 3.0})


def _scene(rolling=False):
    b = SceneBuilder(ego_speed=3.0, k1=-0.05)
    b.add_object("car", world_center(b, 9.0), spacing=0.12)
    start = world_center(b, 6.0, y=-3.0)
    b.add_object("crossing", start[None] + np.outer(2.0 * np.arange(b.t) * DT, [0, 1, 0]), size=(1.0, 0.8, 0.8),
                 spacing=0.08)
    scene = b.build()
    if rolling:   # a rolling-shutter camera (readout of 30 ms, left to right)
        frames = scene.cameras[FRONT]
        frames = replace(frames, model=camera_model(k1=-0.05, direction=1),
                         readout_done_time=frames.trigger_time + 0.03)
        scene = replace(scene, cameras={FRONT: frames})
    return scene


def _run(scene, config):
    ctx = prepare_segment(scene, config)
    return {job.object_id: run_object_job(ctx, job) for job in object_jobs(ctx)}


def _rerun(result):
    """The tracks recomputed in one chunk of all points (numpy path: its own candidate chunks)."""
    n = result.num_tracks
    return np.concatenate([c[0] for c in result.source.point_chunks(points=n or 1)]) if n else None


@pytest.mark.parametrize("rolling", [False, True])
def test_streamed_files_equal_the_materialised_arrays(tmp_path, monkeypatch, rolling):
    # chunks of k points (global) / 97 candidates (rolling) and of 3 frames: N is not a multiple
    t = SceneBuilder().t
    monkeypatch.setattr(core, "CHUNK_POINT_FRAMES", 7 * t)                       # the job's scratch chunks
    results = _run(_scene(rolling), ROLLING if rolling else GLOBAL)
    for r in results.values():
        assert r.projection == ("rolling_shutter" if rolling else "global_shutter")
        assert (r.source.numpy_path is not None) == rolling
        assert r.num_tracks > 100 and (r.num_candidates % 97 if rolling else True)
        k = next(k for k in (7, 8, 9, 11) if r.num_tracks % k)
        monkeypatch.setattr(core, "CHUNK_POINT_FRAMES", k * t)                   # k points per chunk
        assert len(list(r.source.point_chunks())) == (r.num_candidates // 97 + 1 if rolling else r.num_tracks // k + 1)
        urls = write_object_outputs(str(tmp_path), "validation", r, writers=("drivetrack",))
        monkeypatch.setattr(core, "CHUNK_POINT_FRAMES", 3 * r.num_tracks)       # 3 frames per time chunk
        assert len(list(r.source.frame_chunks())) == (t + 2) // 3
        urls += write_object_outputs(str(tmp_path), "validation", r, writers=("tapvid3d",))
        tracks, points3d, visibles = r.tracks, r.points3d, r.visibles                # materialised
        assert tracks.dtype == points3d.dtype == np.float32
        with np.load(urls[0], allow_pickle=False) as d:
            assert d["tracks"].tobytes() == tracks.tobytes()
            assert d["points3d"].tobytes() == points3d.tobytes()
            np.testing.assert_array_equal(d["visibles"], visibles)
            np.testing.assert_array_equal(d["video"], decode_video(r))
            assert d["video"].shape == (t, H, W, 3)
        with np.load(urls[1], allow_pickle=False) as d:
            opencv = OPENCV_FROM_WAYMO_CAMERA @ r.camera_from_vehicle
            points = np.swapaxes(points3d.astype(np.float64), 0, 1)
            xyz = np.einsum("tij,tnj->tni", opencv[:, :3, :3], points) + opencv[:, None, :3, 3]
            assert d["tracks_XYZ"].tobytes() == xyz.astype(np.float32).tobytes()
            np.testing.assert_array_equal(d["visibility"], visibles.T)
            q = d["queries_xyt"]
            frame = q[:, 2].astype(int)
            assert np.all(visibles[np.arange(r.num_tracks), frame])
            assert q[:, :2].tobytes() == tracks[np.arange(r.num_tracks), frame].tobytes()
            assert d["images_jpeg_bytes"].shape == (t,)
        # whole-array and chunked recomputation agree, and the job's sanity counts are those of the tracks
        assert _rerun(r).tobytes() == tracks.tobytes()
        assert r.num_nonfinite_visible == int((visibles & ~np.isfinite(tracks).all(-1)).sum()) == 0


def test_job_keeps_no_tracks_until_asked():
    r = _run(_scene(), GLOBAL)["car"]
    assert r._materialised == {}
    assert r.num_tracks == r.visibles.shape[0] == r.points_box.shape[0] and r.points_box.dtype == np.float64
    a = r.tracks
    assert r.tracks is a and set(r._materialised) == {"tracks"}


def test_numpy_and_kernel_jobs_stream_the_same_files(tmp_path):
    scene = _scene()
    fused = _run(scene, GLOBAL)["car"]
    reference = _run(scene, replace(GLOBAL, kernel="numpy"))["car"]
    assert reference.source.numpy_path is not None and fused.source.numpy_path is None
    a = write_object_outputs(str(tmp_path / "a"), "validation", fused)
    b = write_object_outputs(str(tmp_path / "b"), "validation", reference)
    for x, y in zip(a, b):
        with np.load(x, allow_pickle=False) as dx, np.load(y, allow_pickle=False) as dy:
            assert dx.files == dy.files
            for key in dx.files:
                if dx[key].dtype.kind == "f":
                    np.testing.assert_allclose(dx[key], dy[key], rtol=1e-6, atol=1e-4, err_msg=key)
                else:
                    np.testing.assert_array_equal(dx[key], dy[key], err_msg=key)


@pytest.mark.parametrize("bad, message", [(None, "no camera image"), (b"\xff\xd8junk\xff\xd9", "camera image is not a decodable JPEG"),
                                          ("small", "image is 80x60, calibration says 160x120")])
def test_bad_image_midway_names_segment_camera_frame_and_leaves_no_file(tmp_path, bad, message):
    r = _run(_scene(), GLOBAL)["car"]
    jpeg = list(r.jpeg)
    jpeg[5] = cv2.imencode(".jpg", np.zeros((60, 80, 3), np.uint8))[1].tobytes() if bad == "small" else bad
    r = replace(r, jpeg=jpeg)
    with pytest.raises(ValueError, match=rf"segment 'seg_test-1' camera FRONT frame 5: {message}"):
        write_object_outputs(str(tmp_path), "validation", r, writers=("drivetrack",))
    assert not any(p.is_file() for p in tmp_path.rglob("*"))


def test_kernel_points3d_frames_match_point_chunks():
    r = _run(_scene(), GLOBAL)["car"]
    time_major = np.concatenate(list(r.source.frame_chunks(frames=4)))
    assert time_major.tobytes() == np.ascontiguousarray(r.points3d.swapaxes(0, 1)).tobytes()
    assert kernel.NUMBA_AVAILABLE
