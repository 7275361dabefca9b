"""Rolling-shutter projection against the official camera model's test values and invariants.

Known values come from waymo-open-dataset ``wdl_limited/camera/camera_model_test.cc``.
"""
from __future__ import annotations

import numpy as np
import pytest

from drivetrack.camera import rolling_shutter as rs
from drivetrack.camera.model import CameraModel
from drivetrack.scene import CameraFrames

EXTRINSIC = np.array([
    0.999892684989, -0.00599320840002, 0.0133678704017, 1.53891424471,
    0.00604223652133, 0.999975156055, -0.0036302411765, -0.0236339408393,
    -0.0133457814992, 0.00371062343188, 0.999904056092, 2.11527057298,
    0, 0, 0, 1]).reshape(4, 4)
POSE = np.array([
    -0.913574384152, -0.406212760482, -0.0193141875914, -4069.03497872,
    0.406637479491, -0.913082565675, -0.0304333457449, 11526.3118079,
    -0.00527303457417, -0.0356569976572, 0.999350175676, 86.504,
    0, 0, 0, 1]).reshape(4, 4)
VELOCITY = [-3.3991382122, 1.50920391083, -0.0169006548822,
            0.00158374733292, 0.00212493073195, -0.0270753838122]
POSE_TS, TRIGGER, DONE, SHUTTER = 1553640277.26, 1553640277.23, 1553640277.28, 0.000424383993959


def official_frames(direction: int = rs.LEFT_TO_RIGHT, **override) -> CameraFrames:
    model = CameraModel(2055.55614936, 2055.55614936, 939.657469886, 641.072182194,
                        0.032316008498, -0.321412482553, 0.000793258395371,
                        -0.000625749354133, 0.0, 1920, 1280, EXTRINSIC, direction)
    values = dict(world_from_vehicle=POSE[None], pose_timestamp=np.array([POSE_TS]),
                  velocity=np.array([VELOCITY]), shutter=np.array([SHUTTER]),
                  trigger_time=np.array([TRIGGER]), readout_done_time=np.array([DONE]))
    values.update({k: np.asarray(v, np.float64) for k, v in override.items()})
    return CameraFrames(model=model, jpeg=[None], **values)


PIXEL = np.array([[100.0, 1000.0]])


def test_image_to_world_rolling_shutter_known_value():
    world = rs.world_from_pixels(official_frames(), 0, PIXEL, np.array([20.0]))
    np.testing.assert_allclose(world[0], [-4091.88016, 11527.42299, 84.46667], atol=1e-3)


def test_image_to_world_global_shutter_known_values():
    frames = official_frames(rs.GLOBAL_SHUTTER)
    world = rs.world_from_pixels(frames, 0, PIXEL, np.array([20.0]))
    np.testing.assert_allclose(world[0], [-4091.97180, 11527.48092, 84.46586], atol=1e-3)
    vehicle = frames.model.vehicle_from_camera
    ray = frames.model.rays_from_pixels(PIXEL)[0]
    point_vehicle = vehicle[:3, :3] @ (ray * 20.0 / ray[0]) + vehicle[:3, 3]
    np.testing.assert_allclose(point_vehicle, [21.44064, 8.32240, -1.62938], atol=1e-3)


@pytest.mark.parametrize("direction", [rs.LEFT_TO_RIGHT, rs.GLOBAL_SHUTTER])
def test_world_to_image_round_trip_and_depth(direction):
    frames = official_frames(direction)
    world = rs.world_from_pixels(frames, 0, PIXEL, np.array([20.0]))
    p = rs.project_world(frames, 0, world)
    assert p.valid.tolist() == [True]
    np.testing.assert_allclose(p.pixels, PIXEL, atol=0.1)
    np.testing.assert_allclose(p.points_camera[:, 0], 20.0, atol=1e-3)


def test_moving_point_known_values():
    frames = official_frames()
    world = rs.world_from_pixels(frames, 0, PIXEL, np.array([20.0]))
    velocity = np.array([[1.0, 2.0, 0.1]])
    pixels, valid, capture = rs.pixels_from_world(frames, 0, world, velocity)
    assert valid[0]
    np.testing.assert_allclose(pixels[0], [94.114, 1000.0], atol=0.1)
    np.testing.assert_allclose(capture[0] - POSE_TS, -0.0272851, atol=1e-6)
    depth = rs.project_world(frames, 0, world, velocity).points_camera[0, 0]
    np.testing.assert_allclose(depth, 20.00349, atol=1e-3)
    # Same as a static point placed where the moving one is at its capture time.
    moved = world + (capture[0] - POSE_TS) * velocity
    static_pixels, _, _ = rs.pixels_from_world(frames, 0, moved)
    np.testing.assert_allclose(static_pixels, pixels, atol=0.1)


def test_point_behind_camera_is_invalid():
    for direction in (rs.LEFT_TO_RIGHT, rs.GLOBAL_SHUTTER):
        frames = official_frames(direction)
        world = rs.world_from_pixels(frames, 0, PIXEL, np.array([20.0]))
        shifted = world + [[200.0, 0.0, 0.0]]
        pixels, valid, capture = rs.pixels_from_world(frames, 0, shifted)
        assert not valid[0] and np.isnan(pixels).all() and np.isnan(capture).all()


@pytest.mark.parametrize("direction", [rs.TOP_TO_BOTTOM, rs.LEFT_TO_RIGHT, rs.BOTTOM_TO_TOP,
                                       rs.RIGHT_TO_LEFT])
def test_capture_time_is_the_readout_time_of_the_landing_pixel(direction):
    frames = official_frames(direction)
    rng = np.random.default_rng(0)
    pixels = rng.uniform([50, 50], [1870, 1230], size=(200, 2))
    depth = rng.uniform(5, 60, 200)
    world = rs.world_from_pixels(frames, 0, pixels, depth)
    p = rs.project_world(frames, 0, world)
    assert p.valid.all()
    np.testing.assert_allclose(p.pixels, pixels, atol=0.1)
    # The readout reaches the landing line when the camera sees the point (to ~1e-5 s).
    np.testing.assert_allclose(p.capture_time, rs.pixel_times(frames, 0, p.pixels), atol=2e-5)
    readout = DONE - TRIGGER - SHUTTER
    first, last = TRIGGER + SHUTTER / 2, TRIGGER + SHUTTER / 2 + readout
    assert np.all((p.capture_time > first - 1e-3) & (p.capture_time < last + 1e-3))
    axis = 0 if direction in (rs.LEFT_TO_RIGHT, rs.RIGHT_TO_LEFT) else 1
    # Capture time is linear along the readout axis (in undistorted coordinates).
    corr = np.corrcoef(p.pixels[:, axis], p.capture_time - POSE_TS)[0, 1]
    sign = 1.0 if direction in (rs.TOP_TO_BOTTOM, rs.LEFT_TO_RIGHT) else -1.0
    assert sign * corr > 0.99


def test_static_camera_rolling_equals_global():
    still = official_frames(rs.TOP_TO_BOTTOM, velocity=np.zeros((1, 6)))
    glob = official_frames(rs.GLOBAL_SHUTTER)
    pts = rs.world_from_pixels(glob, 0, np.array([[10.0, 20.0], [960.0, 640.0], [1900, 1270]]),
                               np.array([5.0, 30.0, 80.0]))
    a, va, ta = rs.pixels_from_world(still, 0, pts)
    b, vb, tb = rs.pixels_from_world(glob, 0, pts)
    assert va.all() and vb.all()
    np.testing.assert_allclose(a, b, atol=1e-9)
    np.testing.assert_allclose(tb, POSE_TS)
    assert np.ptp(ta) > 0.01  # capture times still spread over the readout


@pytest.mark.parametrize("override", [
    {"trigger_time": [np.nan]}, {"readout_done_time": [TRIGGER]}, {"velocity": [[np.nan] * 6]},
], ids=["no-trigger", "zero-readout", "no-velocity"])
def test_global_shutter_fallback_when_params_are_missing(override):
    frames = official_frames(rs.LEFT_TO_RIGHT, **override)
    state = rs.shutter_state(frames, 0)
    assert not state.rolling
    glob = official_frames(rs.GLOBAL_SHUTTER)
    world = rs.world_from_pixels(glob, 0, PIXEL, np.array([20.0]))
    pixels, valid, capture = rs.pixels_from_world(frames, 0, world)
    np.testing.assert_allclose(pixels, PIXEL, atol=1e-6)
    assert valid[0] and capture[0] == POSE_TS


def test_unknown_direction_falls_back_to_global():
    assert not rs.shutter_state(official_frames(0), 0).rolling


def test_global_shutter_matches_geometry_camera_model():
    frames = official_frames(rs.GLOBAL_SHUTTER)
    rng = np.random.default_rng(1)
    points_vehicle = rng.uniform([5, -10, -2], [50, 10, 4], size=(50, 3))
    world = points_vehicle @ POSE[:3, :3].T + POSE[:3, 3]
    pixels, valid, _ = rs.pixels_from_world(frames, 0, world)
    ref, ref_valid = frames.model.pixels_from_vehicle(points_vehicle)
    np.testing.assert_array_equal(valid, ref_valid)
    np.testing.assert_allclose(pixels[valid], ref[valid], atol=1e-6)


def test_empty_input_and_bad_shapes():
    frames = official_frames()
    pixels, valid, capture = rs.pixels_from_world(frames, 0, np.zeros((0, 3)))
    assert pixels.shape == (0, 2) and valid.shape == (0,) and capture.shape == (0,)
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        rs.pixels_from_world(frames, 0, np.zeros((4, 2)))
    with pytest.raises(ValueError, match="velocity_world"):
        rs.pixels_from_world(frames, 0, np.zeros((4, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="no pose"):
        rs.pixels_from_world(official_frames(world_from_vehicle=np.full((1, 4, 4), np.nan)), 0,
                             np.zeros((1, 3)))
