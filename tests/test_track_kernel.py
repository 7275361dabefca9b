"""The fused numba kernel of the track stage equals the numpy reference path."""
from __future__ import annotations

from dataclasses import fields, replace

import numpy as np
import pytest

from drivetrack.depth import lookup_max4
from drivetrack.geometry import box_from_center_heading, rotation_z
from drivetrack.tracks import TrackConfig, object_jobs, prepare_segment, run_object_job
from drivetrack.tracks import kernel
from drivetrack.tracks.context import SegmentContext
from drivetrack.tracks.core import _any_rolling_frame, fill_invalid_positions, track_speeds
from test_tracks import (DT, FRONT, H, W, SceneBuilder, camera_model, world_center)

pytestmark = pytest.mark.skipif(not kernel.NUMBA_AVAILABLE, reason="numba is not importable")

#: The track kernel's own-box and other-box arguments turned off (TrackConfig.own_surface_margin_m=None).
OFF = (np.zeros((0, 6)), np.zeros(0, dtype=bool), np.zeros((0, 0, 21)))


def _hand_built_clip(seed=3, n=3000, t_count=7):
    """Box-frame points, per-frame transforms and depth maps covering every visibility case."""
    rng = np.random.default_rng(seed)
    model = camera_model(k1=-0.1)                       # d < 0.8 (untrusted) beyond r2 = 2
    # points spread widely around a box 6 m ahead: some behind the camera at some frames
    points_box = rng.uniform([-8.0, -6.0, -3.0], [8.0, 6.0, 3.0], size=(n, 3))
    # the box drives towards and past the camera, turning back and forth: validity flickers
    # along tracks (held positions, including ties between equally near valid frames)
    centres = np.stack([np.linspace(9.0, -1.0, t_count), np.linspace(-1.0, 1.0, t_count),
                        np.full(t_count, 0.2)], -1)
    camera_from_box = box_from_center_heading(centres, np.where(np.arange(t_count) % 2 == 1, 0.9, 0.0))
    camera_from_box[:, :3, :3] = camera_from_box[:, :3, :3] @ rotation_z(0.1)[None]
    shift_camera = rng.normal(0.0, 0.05, size=(t_count, 3))
    vehicle_from_box = box_from_center_heading(centres + [1.5, 0.0, 1.0], np.linspace(0.2, -0.3, t_count))
    world_from_box = box_from_center_heading(centres * 2.0 + [100.0, -50.0, 0.0], np.linspace(0, 1, t_count))
    # depth: unknown (0) in the left third, elsewhere surfaces spread over the points' depths so
    # that both sides of the occlusion test are dense
    maps = rng.uniform(0.3, 12.0, size=(t_count, H, W)).astype(np.float32)
    maps[:, :, : W // 3] = 0.0
    return model, points_box, camera_from_box, shift_camera, vehicle_from_box, world_from_box, maps


def _reference(model, points_box, camera_from_box, shift_camera, vehicle_from_box, world_from_box,
               maps, ratio, duration_s):
    """Tracks, visibles, points3d [n, T, ...], speeds [n] with the documented numpy functions."""
    points_camera = (np.einsum("tij,nj->tni", camera_from_box[:, :3, :3], points_box)
                     + camera_from_box[:, None, :3, 3] + shift_camera[:, None])
    pixels, valid = model.pixels_from_camera(points_camera)
    ok = valid & model.inside_image(pixels)
    surface = lookup_max4(maps, pixels)
    visible = ok & ~((surface > 0) & (surface < ratio * points_camera[..., 0]))
    points3d = np.einsum("tij,nj->tni", vehicle_from_box[:, :3, :3], points_box) + vehicle_from_box[:, None, :3, 3]
    world = np.einsum("tij,nj->tni", world_from_box[:, :3, :3], points_box) + world_from_box[:, None, :3, 3]
    speeds = track_speeds(world, np.round(np.linspace(0, duration_s, len(maps)) * 1e6).astype(np.int64))
    tracks = fill_invalid_positions(np.swapaxes(pixels, 0, 1).astype(np.float32))
    return tracks, visible.T, np.swapaxes(points3d, 0, 1).astype(np.float32), speeds, valid, ok, surface


def test_kernel_equals_numpy_reference_in_every_visibility_case():
    model, p, cam, shift, veh, world, maps = _hand_built_clip()
    ratio, duration = 0.95, 0.6
    tracks_ref, vis_ref, p3_ref, speeds_ref, valid, ok, surface = _reference(
        model, p, cam, shift, veh, world, maps, ratio, duration)
    points_camera_x = np.einsum("tj,nj->tn", cam[:, 0, :3], p) + cam[:, None, 0, 3] + shift[:, None, 0]
    # every case is present in this clip
    assert (points_camera_x <= 0).any()                                        # behind the camera
    assert ((points_camera_x > 0) & ~valid).any()                              # untrusted distortion
    assert (valid & ~ok).any()                                                 # outside the image
    assert (ok & (surface > 0) & (surface < ratio * points_camera_x)).any()    # occluded
    assert (ok & (surface == 0)).any()                                         # unknown depth: visible
    assert vis_ref.any(axis=1).sum() not in (0, len(p))                        # some kept, some dropped
    assert (~valid.all(axis=0) & valid.any(axis=0)).any()                      # held positions used
    v = valid.T
    assert (~v[:, 1:-1] & v[:, :-2] & v[:, 2:]).any()                          # ... with a tie
    near = ok & (np.abs(surface - ratio * points_camera_x) < 0.01 * points_camera_x)
    assert near.sum() > 10                                                     # occlusion near the limit

    status = np.empty(len(p), np.int8)
    speeds = np.empty(len(p))
    world_step = np.ascontiguousarray(world[1:] - world[:-1])
    kept = kernel.screen_points(p, cam, shift, world_step, kernel.camera_parameters(model), maps, ratio, *OFF,
                                duration, np.nan, np.nan, status, speeds)
    keep = vis_ref.any(axis=1)
    np.testing.assert_array_equal(status == kernel.KEPT, keep)
    np.testing.assert_array_equal(status[~keep], kernel.DROPPED_INVISIBLE)
    assert kept == keep.sum()
    np.testing.assert_allclose(speeds, speeds_ref, rtol=1e-9)

    # fill_tracks on every point (kept or not) equals the reference row by row
    tracks = np.empty((len(p), len(maps), 2), np.float32)
    visibles = np.empty((len(p), len(maps)), bool)
    points3d = np.empty((len(p), len(maps), 3), np.float32)
    kernel.fill_tracks(p, np.arange(len(p))[::-1].copy(), cam, shift, veh, kernel.camera_parameters(model), maps, ratio, *OFF, tracks, visibles,
                       points3d)
    np.testing.assert_array_equal(visibles, vis_ref)
    np.testing.assert_array_equal(np.isnan(tracks), np.isnan(tracks_ref))     # never-valid tracks stay NaN
    np.testing.assert_allclose(tracks, tracks_ref, rtol=1e-6, atol=1e-3, equal_nan=True)
    np.testing.assert_allclose(points3d, p3_ref, rtol=1e-6, atol=1e-5)


def test_speed_filter_status():
    model, p, cam, shift, veh, world, maps = _hand_built_clip(seed=5, n=500)
    world_step = np.ascontiguousarray(world[1:] - world[:-1])
    args = (p, cam, shift, world_step, kernel.camera_parameters(model), maps, 0.95, *OFF, 0.6)
    status0, speeds = np.empty(len(p), np.int8), np.empty(len(p))
    kernel.screen_points(*args, np.nan, np.nan, status0, speeds)
    box_speed = float(np.median(speeds))
    status = np.empty(len(p), np.int8)
    kept = kernel.screen_points(*args, box_speed, 2.0, status, np.empty(len(p)))
    fast = (status0 == kernel.KEPT) & ~(np.abs(speeds - box_speed) <= 2.0)
    assert fast.any() and (status0 == kernel.KEPT).sum() > fast.sum()
    np.testing.assert_array_equal(status == kernel.DROPPED_SPEED, fast)
    np.testing.assert_array_equal(status == kernel.DROPPED_INVISIBLE, status0 == kernel.DROPPED_INVISIBLE)
    assert kept == (status == kernel.KEPT).sum()


def test_empty_and_single_frame_inputs():
    model, p, cam, shift, veh, world, maps = _hand_built_clip(n=10)
    params = kernel.camera_parameters(model)
    empty = np.zeros((0, 3))
    status, speeds = np.empty(0, np.int8), np.empty(0)
    assert kernel.screen_points(empty, cam, shift, np.ascontiguousarray(world[1:] - world[:-1]), params, maps,
                                0.95, *OFF, 0.6, np.nan, np.nan, status, speeds) == 0
    kernel.fill_tracks(empty, np.zeros(0, np.int64), cam, shift, veh, params, maps, 0.95, *OFF, np.empty((0, 7, 2), np.float32),
                       np.empty((0, 7), bool), np.empty((0, 7, 3), np.float32))
    # one frame: speed NaN, so the speed filter drops every visible point (as the numpy path does)
    status, speeds = np.empty(10, np.int8), np.empty(10)
    kernel.screen_points(p, cam[:1], shift[:1], np.zeros((0, 4, 4)), params, maps[:1], 0.95, *OFF, 0.0,
                         np.nan, np.nan, status, speeds)
    assert np.isnan(speeds).all()
    status2 = np.empty(10, np.int8)
    kernel.screen_points(p, cam[:1], shift[:1], np.zeros((0, 4, 4)), params, maps[:1], 0.95, *OFF, 0.0,
                         1.0, 5.0, status2, speeds)
    np.testing.assert_array_equal(status2 == kernel.DROPPED_SPEED, status == kernel.KEPT)


def _assert_same_tracks(a, b):
    assert a.rejection == b.rejection and a.projection == b.projection
    for name in ("num_candidates", "num_dropped_invisible", "num_dropped_speed", "num_ambiguous_occlusion"):
        assert getattr(a, name) == getattr(b, name), name
    if a.occlusion_margin is not None or b.occlusion_margin is not None:
        # the kernel path folds each image's surface tests and depth-map margin into bits and
        # float16 at once; the numpy path computes them per chunk: the same values
        np.testing.assert_array_equal(a.occlusion_margin, b.occlusion_margin, err_msg="occlusion_margin")
    for name in ("visibles", "query_frames", "lidar_sources", "frames"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for name in ("tracks", "points3d"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype == np.float32 and x.shape == y.shape, name
        np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-4, err_msg=name)
    np.testing.assert_allclose(a.track_speed_mps, b.track_speed_mps, rtol=1e-9, equal_nan=True)
    np.testing.assert_allclose(a.speed_error_mps, b.speed_error_mps, rtol=1e-9, atol=1e-12, equal_nan=True)


def _both(scene, config):
    ctx = prepare_segment(scene, replace(config, kernel="numpy"))
    numpy_results = {job.object_id: run_object_job(ctx, job) for job in object_jobs(ctx)}
    ctx = SegmentContext(replace(ctx.plan, config=replace(config, kernel="numba")), ctx.depth)
    numba_results = {job.object_id: run_object_job(ctx, job) for job in object_jobs(ctx)}
    assert numpy_results.keys() == numba_results.keys()
    return numpy_results, numba_results


@pytest.mark.parametrize("rolling_shutter,grown", [(False, False), (True, False), (False, True)])
def test_run_object_job_same_with_either_kernel(rolling_shutter, grown):
    # distortion, a moving ego, an occluder crossing in front, a partly hidden car, a speed filter
    b = SceneBuilder(ego_speed=3.0, k1=-0.05)
    # behind its face towards the camera, a wall in a frame 1.5 m deeper: the wall's returns lie
    # in a pocket of the hull, so the own surface's z-buffer runs (self_occlusion; on the numba
    # path at the kept candidates, one image at a time) and hides it behind the face
    grid = np.arange(-0.8, 0.81, 0.05)
    wall = np.stack(np.meshgrid([-1.0], grid, np.arange(-0.6, 0.61, 0.05)), -1).reshape(-1, 3)
    rim = np.arange(-0.95, 0.96, 0.05)
    frame = np.concatenate([np.column_stack([np.full(rim.size, -0.5), rim, np.full(rim.size, z)]) for z in (-0.7, 0.7)]
                           + [np.column_stack([np.full(rim.size, -0.5), np.full(rim.size, y), 0.7 * rim / 0.95])
                              for y in (-0.95, 0.95)])
    b.add_object("back", world_center(b, 12.0), extra_local=np.concatenate([wall, frame]))
    b.hollow.add("back")
    # driving along with the ego at the left image edge: part of it never enters the image
    b.add_object("edge", world_center(b, 8.0, y=4.0) + np.outer(3.0 * np.arange(b.t) * DT, [1, 0, 0]))
    b.add_object("spinner", world_center(b, 18.0, y=2.0), headings=1.0 * np.arange(b.t) * DT, spacing=0.25)
    start = world_center(b, 6.0, y=-3.0)
    b.add_object("front", start[None] + np.outer(2.0 * np.arange(b.t) * DT, [0, 1, 0]), size=(1.0, 0.8, 0.8),
                 spacing=0.05, extra_local=[[-0.5, 3.0, 0.0], [0.4, 0.0, 0.0]])
    # grown: the depth look-up grown by a pixel whatever the labels (exact here: the gate keeps
    # the max-of-4 by default)
    config = TrackConfig(rolling_shutter=rolling_shutter, max_camera_distance_m=30,
                         max_speed_deviation_mps=2.1, chunk_points=700, occlusion_margins=True,
                         depth_completer_options={"max_reach_px": 3.0},
                         depth_lookup_min_jitter_m=None if grown else 0.01)
    if grown:
        # an unlabelled post 7 m ahead in front of the wall's car: its outline in the completed
        # map is where the grown look-up differs
        from test_tracks import face_points, transform_points

        post = world_center(b, 7.0, y=0.3)
        for f in range(b.t):
            centre = transform_points(np.linalg.inv(b.world_from_vehicle[f]), post[None])[0]
            b.points[f].append(face_points(centre, (0.3, 0.3, 2.0), 0.0, spacing=0.05))
    scene = b.build()
    reference, fused = _both(scene, config)
    if grown:       # it hides fewer point-frames than the max-of-4 (the post's outline)
        ctx = prepare_segment(scene, replace(config, kernel="numpy", depth_lookup_px=0))
        max4 = {job.object_id: run_object_job(ctx, job) for job in object_jobs(ctx)}
        assert reference["back"].visibles.sum() > max4["back"].visibles.sum()
    assert reference["back"].num_tracks > 1000 and reference["edge"].num_dropped_invisible > 0
    assert not reference["back"].visibles.all()
    assert reference["spinner"].num_dropped_speed > 0 and reference["spinner"].num_tracks > 0
    for object_id in reference:
        _assert_same_tracks(reference[object_id], fused[object_id])


def test_rejected_object_is_the_same_with_either_kernel():
    b = SceneBuilder()
    b.lidar_origin = np.array([0.0, 0.0, 3.0])
    b.add_object("hidden", world_center(b, 14.0), size=(2.0, 1.0, 1.0))
    b.add_object("wall", world_center(b, 5.0), size=(0.2, 4.0, 2.0), spacing=0.03, type_=3)
    reference, fused = _both(b.build(), TrackConfig(rolling_shutter=False,
                                                    depth_completer_options={"max_reach_px": 3.0}))
    assert fused["hidden"].rejection == "no_visible_points" and fused["hidden"].num_tracks == 0
    assert fused["hidden"].tracks.shape == (0, b.t, 2)
    _assert_same_tracks(reference["hidden"], fused["hidden"])


def test_global_shutter_frames_are_detected_like_the_projector():
    b = SceneBuilder(t=4)
    b.add_object("car", world_center(b, 10.0))
    frames_meta = b.build().cameras[FRONT]
    frames = np.arange(4)
    assert not _any_rolling_frame(frames_meta, frames)                      # direction 0 (unknown)
    rolling = replace(frames_meta, model=camera_model(direction=1),
                      readout_done_time=frames_meta.trigger_time + 0.03)
    assert _any_rolling_frame(rolling, frames)
    assert not _any_rolling_frame(replace(rolling, model=camera_model(direction=5)), frames)
    assert not _any_rolling_frame(replace(rolling, readout_done_time=rolling.trigger_time), frames)
    nan_one = rolling.readout_done_time.copy()
    nan_one[:3] = np.nan
    assert _any_rolling_frame(replace(rolling, readout_done_time=nan_one), frames)
    assert not _any_rolling_frame(replace(rolling, readout_done_time=nan_one), frames[:3])


def test_unknown_kernel_is_refused_naming_the_field():
    with pytest.raises(ValueError, match="TrackConfig.kernel.*'cuda'"):
        TrackConfig(kernel="cuda")
    assert "kernel" in {f.name for f in fields(TrackConfig)}
    assert TrackConfig.from_dict(TrackConfig(kernel="numpy").to_dict()).kernel == "numpy"


# ---------------------------------------------------------------- streaming variants (writers)

def test_fill_positions_and_frame_variant_equal_fill_tracks_bit_for_bit():
    model, p, cam, shift, veh, _, maps = _hand_built_clip(n=1001)
    params = kernel.camera_parameters(model)
    n, t = p.shape[0], cam.shape[0]
    tracks, visibles, points3d = np.empty((n, t, 2), np.float32), np.empty((n, t), bool), np.empty((n, t, 3), np.float32)
    kernel.fill_tracks(p, np.arange(n, dtype=np.int64), cam, shift, veh, params, maps, 0.95, *OFF, tracks, visibles, points3d)
    assert np.isnan(tracks).any() and not visibles.all()          # held and never-valid positions occur
    for start, stop in ((0, n), (0, 300), (300, 1001), (1000, 1001)):
        part = np.ascontiguousarray(p[start:stop])
        got_t, got_p = np.empty((stop - start, t, 2), np.float32), np.empty((stop - start, t, 3), np.float32)
        kernel.fill_positions(part, cam, shift, veh, params, got_t, got_p)
        assert got_t.tobytes() == tracks[start:stop].tobytes() and got_p.tobytes() == points3d[start:stop].tobytes()
    only = np.empty((n, t, 3), np.float32)
    kernel.fill_positions(p, cam, shift, veh, params, np.empty((0, t, 2), np.float32), only, False, True)
    assert only.tobytes() == points3d.tobytes()
    for start, stop in ((0, t), (2, 5), (6, 7)):
        frames = np.empty((stop - start, n, 3), np.float32)
        kernel.fill_points3d_frames(p, np.ascontiguousarray(veh[start:stop]), frames)
        assert frames.tobytes() == np.ascontiguousarray(points3d[:, start:stop].swapaxes(0, 1)).tobytes()


def test_summarise_tracks_equals_the_numpy_summary():
    from drivetrack.tracks.core import _summarise_tracks

    model, p, cam, shift, veh, _, maps = _hand_built_clip(n=800)
    n, t = p.shape[0], cam.shape[0]
    tracks, visibles, points3d = np.empty((n, t, 2), np.float32), np.empty((n, t), bool), np.empty((n, t, 3), np.float32)
    kernel.fill_tracks(p, np.arange(n, dtype=np.int64), cam, shift, veh, kernel.camera_parameters(model), maps, 0.95, *OFF,
                       tracks, visibles, points3d)
    # plant the cases the sanity counts exist for: a visible NaN, a visible position outside the image
    visibles[0, :] = True
    tracks[0, 1] = np.nan
    tracks[0, 2] = (W, 5.0)
    source = np.random.default_rng(1).integers(0, t, n)
    pixels = np.empty((n, 2), np.float32)
    counts = kernel.summarise_tracks(tracks, visibles, source, float(W), float(H), pixels)
    expect_pixels, expect_counts = _summarise_tracks(tracks, visibles, source, model)
    assert counts.tolist() == expect_counts.tolist() and counts[0] >= 1 and counts[1] >= 1
    assert pixels.tobytes() == expect_pixels.tobytes()


@pytest.mark.parametrize("max_gap_m", [None, 3.0])
def test_kernel_own_and_other_boxes_equal_the_numpy_rules(max_gap_m):
    """The depth-map test with the object's own box (:func:`drivetrack.visibility.own_surface`) and
    other labelled objects' boxes (:func:`drivetrack.visibility.other_surface`: a map surface
    inside another box grown by the margin, on a ray that misses that box itself, hides nothing):
    the kernel's visibles equal the numpy rules point-frame by point-frame, and each rule decides
    some of them."""
    from drivetrack.visibility import (camera_centres_box, other_boxes, other_surface, own_box_parameters,
                                       own_surface)

    model, p, cam, shift, veh, world, maps = _hand_built_clip(seed=5)
    ratio = 0.95
    t_count = len(maps)
    rng = np.random.default_rng(11)
    own = own_box_parameters(camera_centres_box(cam, shift), np.tile([4.0, 2.0, 1.6], (t_count, 1)), 0.2, max_gap_m)
    own_points = rng.random(len(p)) < 0.7
    # per frame four or five other boxes between the camera and the object, one frame without any
    others_list = []
    for tau in range(t_count):
        m = 0 if tau == 2 else 4 + tau % 2
        centres = rng.uniform([1.5, -3.0, -1.0], [7.0, 3.0, 1.0], size=(m, 3))
        camera_from_other = box_from_center_heading(centres, rng.uniform(-np.pi, np.pi, m))
        size = rng.uniform([0.5, 0.5, 0.5], [4.0, 2.5, 2.0], size=(m, 3))
        if tau % 2:     # the part its returns fill: faces moved in by up to 15 cm, not symmetrically
            inset = rng.uniform(0.0, 0.15, size=(m, 2, 3)) * [[-1.0], [1.0]]
            others_list.append((camera_from_other, size, np.stack([-0.5 * size, 0.5 * size], axis=1) - inset))
        else:
            others_list.append((camera_from_other, size))
    others = other_boxes(cam, shift, others_list, 0.2)
    assert not np.allclose(others[1, :4, 18:21], 0.0) and np.allclose(others[0, :4, 18:21], 0.0)
    assert others.shape == (t_count, 5, 21) and (others[2, :, 12] < 0).all() and (others[0, 4, 12] < 0)
    _, vis_plain, *_, ok, surface = _reference(model, p, cam, shift, veh, world, maps, ratio, 0.6)
    points_camera_x = np.einsum("tj,nj->tn", cam[:, 0, :3], p) + cam[:, None, 0, 3] + shift[:, None, 0]
    occluded = ok & (surface > 0) & (surface < ratio * points_camera_x)
    with np.errstate(invalid="ignore", divide="ignore"):
        depth_ratio = surface / points_camera_x
    mine = own_surface(p, depth_ratio, own, where=occluded, reliable=own_points)
    # at points without a reliable normal only the ray test: fewer surfaces are their own
    assert (own_surface(p, depth_ratio, own, where=occluded) & ~mine & ~own_points[None]).sum() > 5
    assert (mine & ~own_points[None]).sum() > 5
    theirs = other_surface(p, depth_ratio, own, others, where=occluded)
    grown_only = other_surface(p, depth_ratio, own, np.concatenate([others[..., :15], np.full(others[..., 15:].shape, -1.0)], -1),
                               where=occluded)
    assert mine.sum() > 20 and (theirs & ~mine).sum() > 20
    if max_gap_m is not None:        # the gap limit decides some: surfaces in the box but far in front
        unlimited = own_surface(p, depth_ratio, own_box_parameters(camera_centres_box(cam, shift),
                                np.tile([4.0, 2.0, 1.6], (t_count, 1)), 0.2), where=occluded, reliable=own_points)
        assert (unlimited & ~mine).sum() > 5, (unlimited.sum(), mine.sum())
    assert (grown_only & ~theirs).sum() > 5        # rays through a box: the map still hides (10 here)
    expected = (ok & ~(occluded & ~mine & ~theirs)).T

    status = np.empty(len(p), np.int8)
    world_step = np.ascontiguousarray(world[1:] - world[:-1])
    kernel.screen_points(p, cam, shift, world_step, kernel.camera_parameters(model), maps, ratio, own, own_points,
                         others, 0.6, np.nan, np.nan, status, np.empty(len(p)))
    np.testing.assert_array_equal(status == kernel.KEPT, expected.any(axis=1))
    visibles = np.empty((len(p), t_count), bool)
    kernel.fill_tracks(p, np.arange(len(p), dtype=np.int64), cam, shift, veh, kernel.camera_parameters(model), maps,
                       ratio, own, own_points, others, np.empty((len(p), t_count, 2), np.float32), visibles,
                       np.empty((len(p), t_count, 3), np.float32))
    np.testing.assert_array_equal(visibles, expected)
    assert not np.array_equal(visibles, vis_plain)


def _walker_before_car(jitter_m: float):
    """A pedestrian (type 2) walking across 7 m ahead of a car 14 m ahead, its labels jittering by
    ``jitter_m`` frame by frame (sideways, and half as much in depth) while its returns are where
    it is."""
    from test_tracks import face_points, transform_points

    b = SceneBuilder(t=12)
    b.add_object("car", world_center(b, 14.0), size=(4.0, 3.0, 1.6), spacing=0.05)
    true = world_center(b, 7.0, y=-0.6)[None] + np.outer(1.0 * np.arange(b.t) * DT, [0, 1, 0])
    jitter = np.where(np.arange(b.t) % 2 == 0, jitter_m, -jitter_m)
    b.add_object("walker", true + np.outer(jitter, [0.5, 1, 0]), size=(0.4, 0.6, 1.6), type_=2, with_points=False)
    b.hollow.add("walker")                        # its returns are given as they are
    for f in range(b.t):
        centre = transform_points(np.linalg.inv(b.world_from_vehicle[f]), true[f][None])[0]
        b.points[f].append(face_points(centre, (0.3, 0.6, 1.6), 0.0, spacing=0.05))   # inside its box
    return b.build()


def _splat_counts(scene, config):
    """int [T]: the other objects' returns splatted in each of the car's images (numpy path)."""
    from drivetrack.tracks.core import _occluders, clip_poses

    ctx = prepare_segment(scene, replace(config, kernel="numpy"))
    job = next(j for j in object_jobs(ctx) if j.object_id == "car")
    rows = np.flatnonzero(scene.boxes.object_id == "car")
    frames = np.sort(scene.boxes.frame[rows]).astype(np.int64)
    poses = clip_poses(ctx.plan, job.camera, frames, rows[np.argsort(scene.boxes.frame[rows])])
    target = poses.camera_from_box[:, :3, 3] + poses.shift_camera
    return np.array([splats[1].size for splats in _occluders(ctx.plan, job, frames, target,
                                                                np.full(frames.size, 3.0))[0]])


def test_recent_returns_occluder_same_with_either_kernel_and_drawn_from_its_near_frames():
    # The walker's labels jitter 8 cm: its segment surface, carried through the other frames'
    # labels, is smeared across 16 cm, while an image's own sweep lies where that image's label
    # puts it (TrackConfig.occluder_recent_types).
    from drivetrack.tracks.core import _recent

    scene = _walker_before_car(0.08)
    # pedestrians hide with their recent returns by default; here each image's own sweep alone
    recent = TrackConfig(rolling_shutter=False, max_camera_distance_m=30, min_frames=4, occluder_recent_frames=0,
                         depth_completer_options={"max_reach_px": 3.0})
    base = replace(recent, occluder_recent_types=())          # every type from its segment's surface
    # each image is drawn from the walker's returns of its own frame, the segment's surface from all
    own, whole = _splat_counts(scene, recent), _splat_counts(scene, base)
    assert (own > 0).all() and (own < whole).all()
    reference, fused = _both(scene, recent)
    _assert_same_tracks(reference["car"], fused["car"])
    segment, _ = _both(scene, base)
    # the smeared walker hides more of the car than its own sweeps do
    assert segment["car"].visibles.sum() < reference["car"].visibles.sum()
    # too far (occluder_recent_max_m), or returns that agree over the segment: the segment's surface
    np.testing.assert_array_equal(_splat_counts(scene, replace(recent, occluder_recent_max_m=5.0)), whole)
    exact = _walker_before_car(0.0)
    np.testing.assert_array_equal(_splat_counts(exact, recent), _splat_counts(exact, base))
    assert _recent(np.array([0, 3, 5, np.iinfo(np.int64).min]), 4, 1).tolist() == [False, True, True, True]


def test_recent_returns_options_are_checked_by_name():
    with pytest.raises(ValueError, match="TrackConfig.occluder_recent_types: unknown BoxType 'WALKER'"):
        TrackConfig(occluder_recent_types=("WALKER",))
    with pytest.raises(ValueError, match="TrackConfig.occluder_recent_frames.*-1"):
        TrackConfig(occluder_recent_frames=-1)
    with pytest.raises(ValueError, match="TrackConfig.occluder_recent_max_m.*0"):
        TrackConfig(occluder_recent_max_m=0.0)
    assert TrackConfig().occluder_recent_types == ("PEDESTRIAN",)


def test_label_jitter_measured_on_the_labels_gates_the_grown_depth_lookup():
    # TrackConfig.depth_lookup_px grows the depth map's look-up only where the labels jitter
    # (drivetrack.tracks.plan.label_jitter_m: second differences of the label centres)
    from drivetrack.tracks.core import depth_lookup_grow_px
    from drivetrack.tracks.plan import label_jitter_m, plan_segment

    def built(sigma_m: float, moving: bool = False, frames=None):
        b = SceneBuilder(t=30, ego_speed=5.0)
        rng = np.random.default_rng(4)
        for k in range(4):
            centre = world_center(b, 10.0 + 4.0 * k, y=-3.0 + 2.0 * k)
            # steady motion, or braking at 1 m/s^2 for the last car (a dt^2: 1 cm, no jitter)
            speed = 3.0 * np.arange(b.t) * DT - (0.5 * (np.arange(b.t) * DT) ** 2 if k == 3 else 0.0)
            path = centre[None] + (np.outer(speed, [1, 0, 0]) if moving else 0.0)
            noise = np.column_stack([rng.normal(0.0, sigma_m, (b.t, 2)), np.zeros(b.t)])
            b.add_object(f"car{k}", path + noise, spacing=0.25, frames=frames)
        return b.build()

    exact, jittered = built(0.0), built(0.03)
    moving_exact, moving = built(0.0, moving=True), built(0.03, moving=True)
    assert label_jitter_m(exact) == 0.0 and label_jitter_m(moving_exact) < 0.002
    assert 0.02 < label_jitter_m(jittered) < 0.045          # 3 cm per axis
    assert 0.02 < label_jitter_m(moving) < 0.045
    assert np.isnan(label_jitter_m(built(0.03, frames=range(0, 30, 2))))   # no three frames in a row
    # refined boxes (smoothed) keep the labels as delivered: those count
    refined = replace(exact, box_labels=jittered.boxes)
    assert label_jitter_m(refined) == label_jitter_m(jittered)
    config = TrackConfig()
    assert depth_lookup_grow_px(plan_segment(exact, config)) == 0
    assert depth_lookup_grow_px(plan_segment(moving_exact, config)) == 0
    assert depth_lookup_grow_px(plan_segment(jittered, config)) == 1
    assert depth_lookup_grow_px(plan_segment(moving, config)) == 1
    assert depth_lookup_grow_px(plan_segment(refined, config)) == 1
    assert depth_lookup_grow_px(plan_segment(jittered, replace(config, occlusion="depth-ratio"))) == 0
    assert depth_lookup_grow_px(plan_segment(jittered, replace(config, depth_lookup_px=0))) == 0
    assert depth_lookup_grow_px(plan_segment(exact, replace(config, depth_lookup_min_jitter_m=None, depth_lookup_px=2))) == 2
    with pytest.raises(ValueError, match="depth_lookup_px must be an integer number of pixels in \\[0, 8\\], got -1"):
        TrackConfig(depth_lookup_px=-1)
    with pytest.raises(ValueError, match="depth_lookup_min_jitter_m must be >= 0 metres or None, got -0.1"):
        TrackConfig(depth_lookup_min_jitter_m=-0.1)
