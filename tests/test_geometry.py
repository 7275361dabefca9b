"""drivetrack.geometry: known values from METHOD.md, inverses, round trips, shapes, empty input."""
from __future__ import annotations

import math

import numpy as np
import pytest

from drivetrack import geometry as g
from drivetrack.camera.model import CameraModel


def _camera(**kw):
    base = dict(f_u=2000.0, f_v=1990.0, c_u=960.0, c_v=640.0, k1=0.03, k2=-0.3, p1=8e-4,
                p2=-6e-4, k3=0.0, width=1920, height=1280, vehicle_from_camera=np.eye(4))
    base.update(kw)
    return CameraModel(**base)


def test_matrix_from_flat_is_row_major_with_translation_at_3_7_11():
    flat = np.arange(16.0)
    m = g.matrix_from_flat(flat)
    assert m.shape == (4, 4)
    assert (m[0, 3], m[1, 3], m[2, 3]) == (3.0, 7.0, 11.0)
    assert g.matrix_from_flat(np.zeros((2, 5, 16))).shape == (2, 5, 4, 4)
    with pytest.raises(ValueError, match="16"):
        g.matrix_from_flat(np.zeros(12))


def test_transform_points_known_value_and_broadcast():
    m = g.rigid_from_rotation_translation(g.rotation_z(math.pi / 2), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(g.transform_points(m, [[1.0, 0.0, 0.0]]), [[1.0, 3.0, 3.0]],
                               atol=1e-12)
    batch = np.stack([m, np.eye(4)])                        # [2, 4, 4]
    pts = np.ones((2, 5, 3))
    out = g.transform_points(batch, pts)
    assert out.shape == (2, 5, 3)
    np.testing.assert_allclose(out[1], pts[1])
    assert g.transform_points(m, np.zeros((0, 3))).shape == (0, 3)
    with pytest.raises(ValueError, match="4, 4"):
        g.transform_points(np.eye(3), pts)
    with pytest.raises(ValueError, match="N, 3"):
        g.transform_points(m, np.zeros((5, 2)))


def test_invert_rigid_is_the_inverse():
    rng = np.random.default_rng(0)
    rot = g.rotation_from_rpy(*rng.uniform(-1, 1, (3, 6)))
    m = g.rigid_from_rotation_translation(rot, rng.normal(size=(6, 3)))
    inv = g.invert_rigid(m)
    np.testing.assert_allclose(inv @ m, np.broadcast_to(np.eye(4), (6, 4, 4)), atol=1e-12)
    np.testing.assert_allclose(inv, np.linalg.inv(m), atol=1e-12)
    pts = rng.normal(size=(6, 10, 3))
    np.testing.assert_allclose(g.transform_points(inv, g.transform_points(m, pts)), pts, atol=1e-12)


def test_rotation_from_rpy_is_rz_ry_rx():
    roll, pitch, yaw = 0.1, -0.2, 0.3
    rx = np.array([[1, 0, 0], [0, math.cos(roll), -math.sin(roll)], [0, math.sin(roll), math.cos(roll)]])
    ry = np.array([[math.cos(pitch), 0, math.sin(pitch)], [0, 1, 0],
                   [-math.sin(pitch), 0, math.cos(pitch)]])
    rz = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
    np.testing.assert_allclose(g.rotation_from_rpy(roll, pitch, yaw), rz @ ry @ rx, atol=1e-15)
    np.testing.assert_allclose(g.rotation_z(yaw), rz, atol=1e-15)
    batch = g.rotation_from_rpy(np.zeros((4, 2)), np.zeros((4, 2)), np.full((4, 2), yaw))
    assert batch.shape == (4, 2, 3, 3)
    r = g.rotation_from_rpy(*np.random.default_rng(1).uniform(-3, 3, (3, 20)))
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), np.broadcast_to(np.eye(3), r.shape),
                               atol=1e-12)
    assert g.rotation_from_rpy(np.zeros(0), np.zeros(0), np.zeros(0)).shape == (0, 3, 3)


def test_box_frame_and_points_in_box():
    parent_from_box = g.box_from_center_heading(np.array([10.0, 5.0, 1.0]), math.pi / 2)
    # The box's +x (length) points along the parent's +y.
    np.testing.assert_allclose(g.transform_points(parent_from_box, [[2.0, 0.0, 0.0]]),
                               [[10.0, 7.0, 1.0]], atol=1e-12)
    pts_box = np.array([[1.9, 0.9, 0.7], [2.1, 0.0, 0.0], [0.0, -1.0, 0.0]])
    size = np.array([4.0, 2.0, 1.5])
    np.testing.assert_array_equal(g.points_in_box_mask(pts_box, size), [True, False, True])
    np.testing.assert_array_equal(g.points_in_box_mask(pts_box, size, margin=0.2), [True] * 3)
    np.testing.assert_array_equal(g.points_in_box_mask(pts_box, size, margin=-0.2), [False] * 3)
    assert g.points_in_box_mask(np.zeros((0, 3)), size).shape == (0,)


def test_projection_known_value_from_method_formula():
    cam = _camera()
    x, y, z = 10.0, 1.0, -0.5
    u, v = -y / x, -z / x
    r2 = u * u + v * v
    d = 1 + 0.03 * r2 - 0.3 * r2 ** 2
    u_d = u * d + 2 * 8e-4 * u * v + -6e-4 * (r2 + 2 * u * u)
    v_d = v * d + 8e-4 * (r2 + 2 * v * v) + 2 * -6e-4 * u * v
    expected = [2000.0 * u_d + 960.0, 1990.0 * v_d + 640.0]
    pixels, valid = cam.pixels_from_camera(np.array([[x, y, z]]))
    assert valid[0]
    np.testing.assert_allclose(pixels[0], expected, rtol=0, atol=1e-9)
    # Optical axis lands on the principal point; +y (left) goes to smaller columns.
    on_axis, _ = cam.pixels_from_camera(np.array([[5.0, 0.0, 0.0], [5.0, 1.0, 0.0]]))
    np.testing.assert_allclose(on_axis[0], [960.0, 640.0])
    assert on_axis[1, 0] < 960.0


def test_projection_invalid_behind_and_untrusted_distortion():
    cam = _camera()
    pixels, valid = cam.pixels_from_camera(np.array([[-1.0, 0, 0], [0.0, 1, 0], [1.0, 3, 0]]))
    assert not valid.any() and np.isnan(pixels).all()  # r2 = 9: d = 1 + 0.27 - 24.3, untrusted


def test_pixels_from_vehicle_uses_camera_from_vehicle():
    vehicle_from_camera = g.rigid_from_rotation_translation(g.rotation_z(0.2), [1.5, 0.1, 2.0])
    cam = _camera(vehicle_from_camera=vehicle_from_camera)
    pts_camera = np.array([[10.0, 1.0, -0.5], [20.0, -2.0, 1.0]])
    pts_vehicle = g.transform_points(vehicle_from_camera, pts_camera)
    a, _ = cam.pixels_from_vehicle(pts_vehicle)
    b, _ = cam.pixels_from_camera(pts_camera)
    np.testing.assert_allclose(a, b, atol=1e-9)


def test_pixels_rays_pixels_round_trip_and_shapes():
    cam = _camera()
    rng = np.random.default_rng(2)
    pixels = rng.uniform([0, 0], [1920, 1280], size=(3, 40, 2))
    rays = cam.rays_from_pixels(pixels)
    assert rays.shape == (3, 40, 3)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0)
    back, valid = cam.pixels_from_camera(rays * 7.0)
    assert valid.all()
    np.testing.assert_allclose(back, pixels, atol=1e-6)
    assert cam.rays_from_pixels(np.zeros((0, 2))).shape == (0, 3)
    empty_pixels, empty_valid = cam.pixels_from_camera(np.zeros((0, 3)))
    assert empty_pixels.shape == (0, 2) and empty_valid.shape == (0,)


def test_inside_image_half_open_pixel_convention():
    cam = _camera()
    pix = np.array([[0.0, 0.0], [1919.999, 1279.999], [1920.0, 5.0], [-0.001, 5.0], [np.nan, 1.0]])
    np.testing.assert_array_equal(cam.inside_image(pix), [True, True, False, False, False])


def test_vectors_to_and_from_box_are_the_box_rotation_and_its_inverse():
    rng = np.random.default_rng(3)
    v = rng.normal(size=(7, 3))
    heading, pitch, roll = rng.uniform(-3, 3, 7), rng.uniform(-1, 1, 7), rng.uniform(-1, 1, 7)
    rotation = g.rotation_from_rpy(roll, pitch, heading)                          # [7, 3, 3]
    np.testing.assert_allclose(g.vectors_from_box(v, heading, pitch, roll), np.einsum("nij,nj->ni", rotation, v),
                               atol=1e-12)
    np.testing.assert_allclose(g.vectors_to_box(v, heading, pitch, roll), np.einsum("nji,nj->ni", rotation, v),
                               atol=1e-12)
    np.testing.assert_allclose(g.vectors_from_box(g.vectors_to_box(v, heading, pitch, roll), heading, pitch, roll),
                               v, atol=1e-12)
    # yaw only: exactly the tilt-free rotation, and a missing pitch or roll is 0
    yaw_only = g.vectors_to_box(v, heading)
    np.testing.assert_array_equal(yaw_only, g.vectors_to_box(v, heading, np.zeros(7), np.zeros(7)))
    np.testing.assert_array_equal(g.vectors_to_box(v, heading, pitch), g.vectors_to_box(v, heading, pitch, np.zeros(7)))
    np.testing.assert_allclose(yaw_only, np.einsum("nji,nj->ni", g.rotation_z(heading), v), atol=1e-12)
    np.testing.assert_allclose(g.vectors_to_box(np.array([[1.0, 0.0, 0.0]]), np.array([math.pi / 2])),
                               [[0.0, -1.0, 0.0]], atol=1e-15)
    assert g.vectors_to_box(np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0)).shape == (0, 3)
    assert g.vectors_from_box(np.zeros((0, 3)), np.zeros(0)).shape == (0, 3)


def test_pose_helpers_round_trip_and_wrap_angle():
    center, heading = np.array([[1.0, 2.0, 3.0], [-4.0, 0.5, 0.0]]), np.array([0.3, -2.9])
    poses = g.poses_from_center_heading(center, heading)
    c, h = g.center_heading_from_poses(poses)
    np.testing.assert_allclose(c, center)
    np.testing.assert_allclose(h, heading, atol=1e-15)
    np.testing.assert_array_equal(g.tilt_from_poses(poses), np.zeros((2, 2)))
    tilted = g.box_from_center_heading(center, heading, np.array([0.1, -0.2]), np.array([0.05, 0.3]))
    np.testing.assert_allclose(g.tilt_from_poses(tilted), [[0.1, 0.05], [-0.2, 0.3]], atol=1e-12)
    np.testing.assert_allclose(g.center_heading_from_poses(tilted)[1], heading, atol=1e-12)
    np.testing.assert_allclose(g.wrap_angle(np.array([0.0, math.pi, -math.pi, 1.5 * math.pi, -4.0])),
                               [0.0, math.pi, math.pi, -0.5 * math.pi, 2 * math.pi - 4.0], atol=1e-12)


def test_vectors_to_box_with_per_pose_angles_equals_repeated_angles():
    """``rows=``: sines and cosines once per pose, the same values as the angles repeated."""
    vectors_to_box = g.vectors_to_box
    rng = np.random.default_rng(4)
    heading, pitch, roll = (rng.uniform(-3.0, 3.0, 5) for _ in range(3))
    rows = rng.integers(0, 5, 200)
    v = rng.normal(size=(200, 3))
    np.testing.assert_array_equal(vectors_to_box(v, heading, rows=rows), vectors_to_box(v, heading[rows]))
    np.testing.assert_array_equal(vectors_to_box(v, heading, pitch, roll, rows=rows),
                                  vectors_to_box(v, heading[rows], pitch[rows], roll[rows]))
    np.testing.assert_array_equal(vectors_to_box(v, heading, None, roll, rows=rows),
                                  vectors_to_box(v, heading[rows], None, roll[rows]))
