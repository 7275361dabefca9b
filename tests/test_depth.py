"""Depth stage: sparse projection, CPU completers and the max-of-4 look-up, on known values."""
from __future__ import annotations

import math

import numpy as np
import pytest

from drivetrack.depth import (get_completer, lookup_max4, sparse_depth_from_points)
from _analytic_depth import default_scene, exact_depth, front_camera, lidar_points
from drivetrack.camera.model import CameraModel
from drivetrack.geometry import rigid_from_rotation_translation

CPU_COMPLETERS = ["nearest", "ipbasic"]
KERNELS = ["numba", "numpy"]


def make_camera(width=40, height=30, k1=0.0, f=20.0) -> CameraModel:
    """Camera at the vehicle origin looking along +x (Waymo camera frame = vehicle frame)."""
    return CameraModel(f_u=f, f_v=f, c_u=width / 2, c_v=height / 2, k1=k1, k2=0.0, p1=0.0,
                       p2=0.0, k3=0.0, width=width, height=height,
                       vehicle_from_camera=np.eye(4))


def point_at_pixel(camera, x, y, depth):
    """Vehicle-frame point (no distortion camera at the origin) that projects to pixel (x, y)."""
    return [depth, -(x - camera.c_u) / camera.f_u * depth, -(y - camera.c_v) / camera.f_v * depth]


# ---------------------------------------------------------------- sparse_depth_from_points

@pytest.mark.parametrize("kernel", KERNELS)
def test_sparse_min_depth_wins_and_pixel_convention(kernel):
    camera = make_camera()
    points = np.array([point_at_pixel(camera, 5.5, 7.5, 10.0),
                       point_at_pixel(camera, 5.9, 7.1, 4.0),    # same pixel, nearer: wins
                       point_at_pixel(camera, 5.2, 7.8, 12.0),
                       point_at_pixel(camera, 30.01, 2.99, 3.0)])  # pixel (30, 2)
    sparse = sparse_depth_from_points(points, camera, kernel=kernel)
    assert sparse.dtype == np.float32 and sparse.shape == (30, 40)
    assert sparse[7, 5] == pytest.approx(4.0)
    assert sparse[2, 30] == pytest.approx(3.0)
    assert np.count_nonzero(sparse) == 2


def test_sparse_z_depth_is_camera_x_not_range():
    camera = CameraModel(**{**make_camera().__dict__,
                            "vehicle_from_camera": rigid_from_rotation_translation(
                                np.eye(3), np.array([1.5, 0.0, 2.0]))})
    # 10 m ahead of the camera, 3 m to its left: z-depth 10, range sqrt(109)
    sparse = sparse_depth_from_points(np.array([[11.5, 3.0, 2.0]]), camera)
    assert sparse[np.nonzero(sparse)] == pytest.approx([10.0])


@pytest.mark.parametrize("kernel", KERNELS)
def test_sparse_ignores_points_behind_outside_and_nan(kernel):
    camera = make_camera()
    points = np.array([[-5.0, 0.0, 0.0],                       # behind the camera
                       [5.0, 100.0, 0.0],                      # far outside the image
                       [np.nan, 0.0, 0.0], [5.0, np.nan, 0.0],
                       point_at_pixel(camera, 39.999, 29.999, 2.0),  # last pixel, inside
                       point_at_pixel(camera, 40.0, 10.0, 2.0)])     # x = width: outside
    sparse = sparse_depth_from_points(points, camera, kernel=kernel)
    assert np.count_nonzero(sparse) == 1 and sparse[29, 39] == pytest.approx(2.0)


@pytest.mark.parametrize("kernel", KERNELS)
def test_sparse_uses_distortion(kernel):
    plain, barrel = make_camera(), make_camera(k1=0.05)
    point = np.array([point_at_pixel(plain, 35.5, 25.5, 5.0)])  # u = -0.775, v = -0.525
    assert sparse_depth_from_points(point, plain, kernel=kernel)[25, 35] == pytest.approx(5.0)
    pixels, valid = barrel.pixels_from_vehicle(point)
    expected_col, expected_row = np.floor(pixels[0]).astype(int)
    assert valid[0] and (expected_col, expected_row) != (35, 25)
    sparse = sparse_depth_from_points(point, barrel, kernel=kernel)
    assert sparse[expected_row, expected_col] == pytest.approx(5.0)
    assert np.count_nonzero(sparse) == 1


def test_sparse_kernel_is_bit_identical_to_the_numpy_reference():
    """The fused kernel against the numpy reference: distortion, a rotated and shifted camera, a
    move into another vehicle frame first, the subset map, many returns sharing pixels."""
    rng = np.random.default_rng(3)
    angle = 0.3
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    camera = CameraModel(f_u=90.0, f_v=91.0, c_u=61.3, c_v=40.7, k1=-0.08, k2=0.02, p1=0.001, p2=-0.002, k3=0.001,
                         width=120, height=80,
                         vehicle_from_camera=rigid_from_rotation_translation(rotation, np.array([1.5, -0.1, 2.0])))
    points = np.concatenate([rng.uniform([-20, -30, -3], [60, 30, 6], size=(20000, 3)),
                             np.repeat(rng.uniform([5, -3, 0], [30, 3, 2], size=(50, 3)), 40, axis=0)
                             + rng.normal(0.0, 1e-3, size=(2000, 3))])
    subset = rng.random(len(points)) < 0.4
    moved = rigid_from_rotation_translation(rotation.T, np.array([0.4, 0.05, -0.02]))
    for first in (None, moved):
        full_k, sub_k = sparse_depth_from_points(points, camera, subset, vehicle_from_points=first, kernel="numba")
        full_n, sub_n = sparse_depth_from_points(points, camera, subset, vehicle_from_points=first, kernel="numpy")
        assert np.count_nonzero(full_n) > 500 and np.count_nonzero(sub_n) > 200
        assert full_k.dtype == sub_k.dtype == np.float32
        assert np.array_equal(full_k, full_n) and np.array_equal(sub_k, sub_n)
        assert np.array_equal(sparse_depth_from_points(points, camera, vehicle_from_points=first), full_n)
    with pytest.raises(ValueError, match="kernel must be 'numba' or 'numpy', found 'gpu'"):
        sparse_depth_from_points(points, camera, kernel="gpu")
    with pytest.raises(ValueError, match=r"vehicle_from_points: expected float \[4, 4\], found shape \(3, 3\)"):
        sparse_depth_from_points(points, camera, vehicle_from_points=np.eye(3))


def test_sparse_with_replaced_returns_equals_the_moved_copy():
    """``replace=(rows, points, skip)``: the map (and the subset's) of the returns with ``rows``
    moved to ``points``, as if a copy were moved, by both kernels, with the mask given or not,
    in front of and behind the others."""
    rng = np.random.default_rng(9)
    camera = CameraModel(f_u=90.0, f_v=91.0, c_u=61.3, c_v=40.7, k1=-0.08, k2=0.02, p1=0.001, p2=-0.002, k3=0.001,
                         width=120, height=80, vehicle_from_camera=np.eye(4))
    points = rng.uniform([2, -20, -8], [40, 20, 8], size=(6000, 3))
    subset = rng.random(len(points)) < 0.4
    rows = np.sort(rng.choice(len(points), 900, replace=False))
    moved = points[rows] * rng.uniform(0.7, 1.3, (rows.size, 1)) + rng.normal(0.0, 0.5, (rows.size, 3))
    copy = points.copy()
    copy[rows] = moved
    skip = np.zeros(len(points), dtype=bool)
    skip[rows] = True
    want = sparse_depth_from_points(copy, camera, subset, kernel="numpy")
    for kernel in ("numba", "numpy"):
        for mask in (skip, None):
            got = sparse_depth_from_points(points, camera, subset, kernel=kernel, replace=(rows, moved, mask))
            assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    assert not np.array_equal(sparse_depth_from_points(points, camera), want[0])


def test_sparse_empty_and_bad_input():
    camera = make_camera()
    empty = sparse_depth_from_points(np.zeros((0, 3)), camera)
    assert empty.shape == (30, 40) and not empty.any()
    with pytest.raises(ValueError, match=r"expected float \[M, 3\], found shape \(4, 2\)"):
        sparse_depth_from_points(np.zeros((4, 2)), camera)
    with pytest.raises(TypeError, match="found int64"):
        sparse_depth_from_points(np.zeros((4, 3), dtype=np.int64), camera)


# ---------------------------------------------------------------- completers (CPU)

def test_nearest_single_return_fills_its_reach_disc():
    sparse = np.zeros((41, 41), np.float32)
    sparse[20, 20] = 7.5
    dense = get_completer("nearest", max_reach_px=10)(sparse)
    rows, cols = np.mgrid[0:41, 0:41]
    distance = np.hypot(rows - 20, cols - 20)
    assert np.all(dense[distance <= 9.9] == np.float32(7.5))
    assert np.all(dense[distance > 10.5] == 0)  # beyond reach: unknown, not extrapolated
    assert dense.dtype == np.float32


def test_nearest_two_returns_split_at_bisector():
    sparse = np.zeros((20, 40), np.float32)
    sparse[10, 10] = 5.0
    sparse[10, 29] = 30.0  # bisector between columns 19 and 20
    dense = get_completer("nearest", max_reach_px=math.inf)(sparse)
    assert np.all(dense[:, :20] == 5.0) and np.all(dense[:, 20:] == 30.0)


def test_nearest_backends_agree_up_to_ties():
    rng = np.random.default_rng(5)
    sparse = np.zeros((60, 90), np.float32)
    known = rng.random(sparse.shape) < 0.04
    sparse[known] = rng.uniform(1, 60, known.sum())
    fast = get_completer("nearest", max_reach_px=8)(sparse)
    exact = get_completer("nearest", max_reach_px=8, backend="scipy")(sparse)
    np.testing.assert_array_equal(fast > 0, exact > 0)
    assert np.mean(fast == exact) > 0.95
    with pytest.raises(ValueError, match="backend: expected 'opencv' or 'scipy', found 'gpu'"):
        get_completer("nearest", backend="gpu")


def test_nearest_default_reach_scales_with_width_and_sky_stays_zero():
    width = 960  # default reach 10 px
    sparse = np.zeros((200, width), np.float32)
    sparse[150:, ::4] = 12.0  # returns only in the lower part; "sky" above
    dense = get_completer("nearest")(sparse)
    assert np.all(dense[141:] == 12.0)
    assert not dense[:139].any()


@pytest.mark.parametrize("name", CPU_COMPLETERS)
def test_batches_and_empty_input(name):
    completer = get_completer(name)
    assert completer.name == name
    rng = np.random.default_rng(0)
    batch = np.where(rng.random((3, 24, 32)) < 0.1, rng.uniform(2, 50, (3, 24, 32)), 0).astype(np.float32)
    batch[1] = 0.0  # a frame without returns
    dense = completer(batch)
    assert dense.shape == batch.shape and dense.dtype == np.float32
    assert not dense[1].any()
    np.testing.assert_array_equal(dense[2], completer(batch[2]))
    assert not completer(np.zeros((0, 24, 32), np.float32)).size


@pytest.mark.parametrize("name", CPU_COMPLETERS)
def test_completer_input_errors(name):
    completer = get_completer(name)
    with pytest.raises(TypeError, match="expected dtype float32.*found float64"):
        completer(np.zeros((4, 4)))
    with pytest.raises(ValueError, match=r"found shape \(2, 3, 4, 5\)"):
        completer(np.zeros((2, 3, 4, 5), np.float32))
    bad = np.zeros((4, 4), np.float32)
    bad[1, 1] = -3.0
    with pytest.raises(ValueError, match="finite depths >= 0.*-3.0"):
        completer(bad)
    with pytest.raises(ValueError, match="max_reach_px"):
        get_completer(name, max_reach_px=0)


def test_ipbasic_fills_holes_and_keeps_returns_near_their_values():
    # a tilted plane with returns on every 4th row and 3rd column (holes in between)
    rows, cols = np.mgrid[0:60, 0:80]
    truth = (10.0 + 0.1 * rows + 0.05 * cols).astype(np.float32)
    sparse = np.where((rows % 4 == 0) & (cols % 3 == 0), truth, 0).astype(np.float32)
    dense = get_completer("ipbasic", max_reach_px=6)(sparse)
    inner = (slice(4, 56), slice(4, 76))
    assert np.all(dense[inner] > 0)  # every hole filled
    known = sparse > 0
    assert np.max(np.abs(dense[known] - sparse[known]) / sparse[known]) < 0.05
    assert np.max(np.abs(dense[inner] - truth[inner]) / truth[inner]) < 0.05
    # beyond reach stays unknown, unless extending to the top is asked for
    lower = sparse.copy()
    lower[:40] = 0
    assert not get_completer("ipbasic", max_reach_px=5)(lower)[:30].any()
    assert get_completer("ipbasic", max_reach_px=5, extend_to_top=True)(lower)[:30].all()


def test_ipbasic_prefers_the_nearer_surface():
    sparse = np.zeros((30, 30), np.float32)
    sparse[::2, ::2] = 40.0        # background
    sparse[10:20:2, 10:20:2] = 8.0  # a near object with a leaked background return inside it
    sparse[14, 14] = 40.0
    dense = get_completer("ipbasic", max_reach_px=6)(sparse)
    assert dense[14, 14] == pytest.approx(8.0, rel=0.05)


def test_completers_on_analytic_scene_against_exact_depth():
    camera = front_camera(width=240, height=160)
    scene = default_scene()
    truth = exact_depth(scene, camera)
    sparse = sparse_depth_from_points(lidar_points(scene, beams=64, azimuths=1000), camera)
    assert 0.01 < np.mean(sparse > 0) < 0.2
    evaluable = (truth > 0) & (truth < 60)
    for name, min_within in (("nearest", 0.9), ("ipbasic", 0.85)):
        dense = get_completer(name, max_reach_px=6)(sparse)
        filled = evaluable & (dense > 0)
        assert filled.sum() > 0.8 * evaluable.sum(), name
        within = np.abs(dense[filled] - truth[filled]) < 0.05 * truth[filled]
        print(name, within.mean(), filled.sum() / evaluable.sum())
        assert within.mean() > min_within, (name, within.mean())


# ---------------------------------------------------------------- lookup_max4

def test_lookup_known_values_centres_edges_corners():
    depth = np.array([[1, 2, 3],
                      [4, 0, 6],
                      [7, 8, 9]], np.float32)
    pixels = np.array([
        [0.5, 0.5],   # centre of (0, 0): itself
        [1.5, 1.5],   # centre of an unknown pixel: unknown
        [1.0, 1.0],   # corner between (0,0), (1,0), (0,1), (1,1): max(1, 2, 4, 0)
        [2.0, 2.0],   # max(0, 6, 8, 9)
        [1.0, 0.5],   # between centres of (0,0) and (1,0) on a centre row: max(1, 2)
        [0.2, 0.2],   # inside the border, outer neighbours outside: only (0,0)
        [2.9, 2.9],   # only (2,2)
        [1.5, 1.2],   # between rows 0 and 1 in column 1: max(2, 0)
        [-0.1, 1.0], [3.0, 1.0], [1.0, 3.0], [np.nan, 1.0],  # outside / NaN
    ])
    expected = [1, 0, 4, 9, 2, 1, 9, 2, 0, 0, 0, 0]
    result = lookup_max4(depth, pixels)
    assert result.dtype == np.float32
    np.testing.assert_array_equal(result, np.array(expected, np.float32))


def test_lookup_shapes_and_batch():
    rng = np.random.default_rng(1)
    depth = rng.uniform(1, 10, (2, 5, 6)).astype(np.float32)
    pixels = rng.uniform(0, 5, (2, 7, 3, 2))
    batched = lookup_max4(depth, pixels)
    assert batched.shape == (2, 7, 3)
    np.testing.assert_array_equal(batched[1], lookup_max4(depth[1], pixels[1]))
    assert lookup_max4(depth[0], np.zeros((0, 2))).shape == (0,)
    # never below the bilinear interpolation of the same four pixels
    x, y = pixels[0, :, 0, 0], pixels[0, :, 0, 1]
    x0 = np.clip(np.floor(x - 0.5), 0, 5).astype(int)
    y0 = np.clip(np.floor(y - 0.5), 0, 4).astype(int)
    assert np.all(lookup_max4(depth[0], pixels[0, :, 0]) >= depth[0][y0, x0])


def test_lookup_grown_is_the_max_of_4_of_the_map_dilated_by_as_many_pixels():
    # grow_px g: the max over the four pixels and every pixel within g of them, i.e. the max-of-4
    # of the map whose every pixel took the farthest depth within g (outside the image unknown)
    from scipy.ndimage import maximum_filter

    from drivetrack.tracks import kernel

    rng = np.random.default_rng(3)
    depth = rng.uniform(1, 50, (2, 9, 11)).astype(np.float32)
    depth[rng.uniform(size=depth.shape) < 0.3] = 0.0          # unknown pixels never win
    pixels = np.concatenate([rng.uniform(-0.5, 11.5, (2, 60, 1)), rng.uniform(-0.5, 9.5, (2, 60, 1))], axis=-1)
    pixels[:, :5] = np.floor(pixels[:, :5]) + 0.5               # on pixel centres: one column and row
    for grow in (1, 2):
        dilated = maximum_filter(depth, size=(1, 2 * grow + 1, 2 * grow + 1), mode="constant", cval=0.0)
        want = lookup_max4(dilated, pixels)
        np.testing.assert_array_equal(lookup_max4(depth, pixels, grow_px=grow), want)
        # the track kernel's look-up is the same (-1 outside the image: 0 here)
        got = np.array([[kernel._max4(depth, b, 9, 11, x, y, grow) for x, y in pixels[b]] for b in range(2)])
        np.testing.assert_array_equal(np.maximum(got, 0), want)
    np.testing.assert_array_equal(lookup_max4(depth, pixels, grow_px=0), lookup_max4(depth, pixels))
    with pytest.raises(ValueError, match="grow_px: expected an integer >= 0, found -1"):
        lookup_max4(depth, pixels, grow_px=-1)


def test_lookup_errors():
    with pytest.raises(ValueError, match=r"expected float \[\.\.\., 2\].*found shape \(4, 3\)"):
        lookup_max4(np.zeros((3, 3), np.float32), np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"expected float32 \[H, W\] or \[B, H, W\], found shape \(3,\)"):
        lookup_max4(np.zeros(3, np.float32), np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"batch of 2 depth maps expected shape \[2, \.\.\., 2\]"):
        lookup_max4(np.zeros((2, 3, 3), np.float32), np.zeros((3, 4, 2)))


# ---------------------------------------------------------------- see_through_returns

def test_see_through_returns_flags_leaks_not_edges_or_slopes():
    from drivetrack.depth import see_through_returns

    sparse = np.zeros((200, 300), np.float32)
    sparse[::6, ::4] = 20.0                                # background scan pattern
    sparse[60:140:3, 100:200:2] = 2.0                      # a near surface, densely sampled
    leak = np.zeros(sparse.shape, bool)
    leak[90:110:6, 120:180:4] = True                       # background returns inside it
    sparse[leak] = 20.0
    flagged = see_through_returns(sparse, 24, 0.95, 3)
    assert flagged[leak].all()
    assert not flagged[sparse == 2.0].any()
    background = (sparse == 20.0) & ~leak
    assert flagged[background].mean() < 0.01                # only returns at the square's corners
    assert not flagged[sparse == 0].any()
    # 4 of 4 quadrants: the leaks are still surrounded
    assert see_through_returns(sparse, 24, 0.95, 4)[leak].all()
    # a surface whose depth falls row by row (the ground): nearer returns below only, kept
    ground = np.zeros((200, 300), np.float32)
    rows = np.arange(200, dtype=np.float32)[:, None]
    ground[::5, ::3] = np.broadcast_to(2000.0 / (rows + 20.0), (200, 300))[::5, ::3]
    assert not see_through_returns(ground, 24).any()
    # batches: same as one by one
    both = see_through_returns(np.stack([sparse, ground]), 24)
    np.testing.assert_array_equal(both[0], flagged)


def test_see_through_returns_on_analytic_scene_removes_returns_the_camera_cannot_see():
    """A LiDAR above the camera sees the ground behind a car right in front; those returns sit
    inside the car in the image. The filter removes them and keeps what the camera sees."""
    from drivetrack.depth import see_through_returns
    from _analytic_depth import AnalyticScene

    base = default_scene()
    near_car = np.array([[[3.5, -1.0, 0.0], [7.5, 1.0, 1.9]]])
    scene = AnalyticScene(ground_z=0.0, boxes=np.concatenate([near_car, base.boxes]))
    camera = front_camera(width=480, height=320)
    truth = exact_depth(scene, camera)
    sparse = sparse_depth_from_points(lidar_points(scene, origin=(0.0, 0.0, 2.6), beams=64, azimuths=1325), camera)
    known = sparse > 0
    behind = known & (sparse > 1.10 * np.maximum(truth, 1e-3)) & (truth > 0)  # past what the camera sees
    assert behind.sum() > 30, behind.sum()
    window = int(round(camera.f_u * np.tan(np.radians(1.0))))
    flagged = see_through_returns(sparse, window, 0.95, 3)
    assert flagged[behind].mean() > 0.9, flagged[behind].mean()
    seen = known & ~behind
    assert flagged[seen].mean() < 0.02, flagged[seen].mean()


def test_see_through_returns_bad_arguments():
    from drivetrack.depth import see_through_returns

    with pytest.raises(ValueError, match="window_px"):
        see_through_returns(np.zeros((4, 4), np.float32), 0)
    with pytest.raises(ValueError, match="min_quadrants"):
        see_through_returns(np.zeros((4, 4), np.float32), 3, min_quadrants=5)
    with pytest.raises(ValueError, match=r"\[\.\.\., H, W\]"):
        see_through_returns(np.zeros(4, np.float32), 3)


# ---------------------------------------------------------------- bound_blind_zone

def test_bound_blind_zone_bounds_below_the_reference_lidars_lowest_scan_line():
    from drivetrack.depth import bound_blind_zone

    sparse = np.zeros((100, 40), np.float32)
    reference = np.zeros_like(sparse)
    reference[10:41:10, 0:20:2] = 8.0                      # the roof lidar's far lines
    reference[60, 0:20:2] = 3.0                            # its lowest line hits a near car at 3 m
    reference[56, 0:20:2] = 2.5                            # the line above, still within the cell
    sparse[:] = reference
    sparse[70, 4] = 9.0                                    # a bumper lidar seen under the car: farther
    sparse[80, 6] = 1.0                                    # a bumper lidar's return nearer than the car
    sparse[30, 30] = 12.0                                  # a column with no reference return at all
    out = bound_blind_zone(sparse, reference, cell_px=10, ratio=0.95)
    # above and on the lowest line: untouched; below it, in columns 0..19: bounded by 3 m (the
    # farthest return of the lowest line), encoded -3; the far return dropped, the nearer one kept
    np.testing.assert_array_equal(out[:61], sparse[:61])
    assert (out[61:, :20][out[61:, :20] != 1.0] == -3.0).all()
    assert out[70, 4] == -3.0 and out[80, 6] == 1.0
    # columns 20..39 have no reference return: unchanged
    np.testing.assert_array_equal(out[:, 20:], sparse[:, 20:])
    # a return within the ratio of the bound is kept
    sparse[75, 8] = 3.1
    assert bound_blind_zone(sparse, reference, 10, 0.95)[75, 8] == np.float32(3.1)
    # no reference return anywhere: nothing changes
    np.testing.assert_array_equal(bound_blind_zone(sparse, np.zeros_like(sparse), 10), sparse)
    # reference returns the map no longer holds (removed as seen through) do not count: the line
    # above becomes the lowest
    hidden = sparse.copy()
    hidden[60, 0:20:2] = 0.0
    out = bound_blind_zone(hidden, reference, 10)
    assert out[58, 1] == -2.5 and out[60, 0] == -2.5 and out[56, 0] == 2.5


@pytest.mark.parametrize("with_scale", [False, True])
def test_bound_blind_zone_kernel_equals_the_numpy_form(with_scale):
    """The one-kernel blind-zone bound gives the numpy form's map bit for bit."""
    from drivetrack.depth import bound_blind_zone
    from drivetrack.depth.sparse import _bound_blind_zone_numpy

    rng = np.random.default_rng(6)
    h, w = 120, 203
    sparse = np.where(rng.uniform(size=(h, w)) < 0.15, rng.uniform(0.5, 60.0, (h, w)), 0.0).astype(np.float32)
    reference = np.where((rng.uniform(size=(h, w)) < 0.5) & (np.arange(h)[:, None] < rng.integers(20, h, w)),
                         sparse, 0.0).astype(np.float32)
    reference[5, 7] = 99.0                               # behind the map's own return: does not count
    scale = rng.uniform(0.7, 1.3, (h, w)).astype(np.float32) if with_scale else None
    for cell, ratio in ((4, 0.95), (7, 0.8), (1, 1.0)):
        got = bound_blind_zone(sparse, reference, cell, ratio, scale)
        want = _bound_blind_zone_numpy(sparse, reference, cell, ratio, scale)
        np.testing.assert_array_equal(got, want)
        assert (got < 0).any()


def test_apply_depth_bounds_after_completion():
    from drivetrack.depth import apply_depth_bounds

    sparse = np.array([[5.0, 0.0, -3.0, -3.0, -3.0]], np.float32)
    dense = np.array([[5.0, 5.0, 5.0, 2.0, 0.0]], np.float32)   # completion of max(sparse, 0)
    np.testing.assert_array_equal(apply_depth_bounds(dense, sparse), [[5.0, 5.0, 3.0, 2.0, 3.0]])
    np.testing.assert_array_equal(dense, [[5.0, 5.0, 5.0, 2.0, 0.0]])           # not modified
    unbounded = np.maximum(sparse, 0)
    assert apply_depth_bounds(dense, unbounded) is dense
    batch = apply_depth_bounds(np.stack([dense, dense]), np.stack([sparse, unbounded]))
    np.testing.assert_array_equal(batch[1], dense)
    np.testing.assert_array_equal(batch[0], [[5.0, 5.0, 3.0, 2.0, 3.0]])
    with pytest.raises(ValueError, match=r"apply_depth_bounds: completed maps \(1, 4\) and sparse maps \(1, 5\)"):
        apply_depth_bounds(dense[:, :4], sparse)



def test_apply_depth_bounds_in_place_matches_the_mask_form():
    """The one-pass kernel (in place, as the depth stage uses it) equals the mask form of the
    bound on random maps, bit for bit; a copy is refused as a target when it cannot be written."""
    from drivetrack.depth import apply_depth_bounds

    rng = np.random.default_rng(5)
    sparse = np.where(rng.random((3, 40, 60)) < 0.3, -rng.uniform(1, 30, (3, 40, 60)),
                      np.where(rng.random((3, 40, 60)) < 0.2, rng.uniform(1, 30, (3, 40, 60)), 0)).astype(np.float32)
    dense = np.where(rng.random(sparse.shape) < 0.7, rng.uniform(0.5, 40, sparse.shape), 0).astype(np.float32)
    bounded = sparse < 0
    expected = dense.copy()
    expected[bounded] = np.where(dense[bounded] > 0, np.minimum(dense[bounded], -sparse[bounded]), -sparse[bounded])
    assert bounded.sum() > 1000 and (dense[bounded] > -sparse[bounded]).sum() > 100
    target = dense.copy()
    assert apply_depth_bounds(target, sparse, in_place=True) is target
    np.testing.assert_array_equal(target, expected)
    np.testing.assert_array_equal(apply_depth_bounds(dense, sparse), expected)
    with pytest.raises(ValueError, match="writeable C-contiguous float32"):
        apply_depth_bounds(dense[:, :, ::2], sparse[:, :, ::2], in_place=True)


def test_nearest_read_out_matches_the_mask_form():
    """NearestCompleter's one-pass read-out of the labelled distance transform gives the maps
    of the numpy mask form it replaced (take, reset past reach + margin, exact distance inside
    the margin), bit for bit, with a reach small enough that many pixels are decided exactly."""
    import cv2

    rng = np.random.default_rng(11)
    sparse = np.where(rng.random((90, 140)) < 0.01, rng.uniform(2, 60, (90, 140)), 0).astype(np.float32)
    for reach in (3.0, 7.5, math.inf):
        known = sparse > 0
        seed_index = np.flatnonzero(known)
        distance, labels = cv2.distanceTransformWithLabels(
            np.logical_not(known).view(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
        depth_of_label = np.concatenate([[0.0], sparse.reshape(-1)[seed_index]]).astype(np.float32)
        expected = np.take(depth_of_label, labels)
        decided_exactly = 0
        if math.isfinite(reach):
            margin = 0.05 * reach + 0.5
            expected[distance > reach + margin] = 0.0
            near = np.flatnonzero(cv2.inRange(distance, reach - margin, reach + margin))
            seed = seed_index[labels.reshape(-1)[near] - 1]
            w = known.shape[1]
            too_far = np.hypot(seed // w - near // w, seed % w - near % w) > reach
            expected.reshape(-1)[near[too_far]] = 0.0
            decided_exactly = int(too_far.sum())
        got = get_completer("nearest", max_reach_px=reach)(sparse)
        np.testing.assert_array_equal(got, expected)
        assert decided_exactly > 20 or not math.isfinite(reach)

def test_horizontal_depth_scale_gives_z_depth_from_horizontal_distance():
    from drivetrack.depth import horizontal_depth_scale
    from drivetrack.camera.model import CameraModel
    from drivetrack.geometry import rigid_from_rotation_translation, rotation_from_rpy

    camera = CameraModel(f_u=500.0, f_v=500.0, c_u=240.0, c_v=160.0, k1=0.04, k2=-0.02, p1=0.0005, p2=-0.0003,
                         k3=0.0, width=480, height=320, vehicle_from_camera=rigid_from_rotation_translation(
                             rotation_from_rpy(0.0, np.radians(12.0), np.radians(-30.0)), np.array([1.5, -0.9, 2.1])))
    scale = horizontal_depth_scale(camera)
    assert scale.shape == (320, 480) and scale.dtype == np.float32
    rng = np.random.default_rng(3)
    pixels = rng.uniform([2, 2], [478, 318], size=(200, 2))
    rays = camera.rays_from_pixels(pixels)
    points_camera = rays * rng.uniform(2, 40, size=(200, 1))
    horizontal = np.linalg.norm((points_camera @ camera.vehicle_from_camera[:3, :3].T)[:, :2], axis=-1)
    z = points_camera[:, 0]
    at = scale[np.floor(pixels[:, 1]).astype(int), np.floor(pixels[:, 0]).astype(int)]
    np.testing.assert_allclose(horizontal * at, z, rtol=2e-3)
    # kept per calibration (read-only): the same camera again gets the same map, another camera its own
    assert horizontal_depth_scale(camera) is scale and not scale.flags.writeable
    import dataclasses
    other = horizontal_depth_scale(dataclasses.replace(camera, c_v=150.0))
    assert other is not scale and not np.array_equal(other, scale)


def test_bound_blind_zone_on_analytic_scene_never_brings_surfaces_nearer():
    """A camera pitched down sees the ground and a car inside the roof LiDAR's blind zone: the
    bound fills that region, and nowhere puts a surface nearer than the truth (no false occlusion),
    while far returns of a bumper lidar seen round the car there are replaced."""
    from drivetrack.depth import bound_blind_zone, horizontal_depth_scale
    from _analytic_depth import AnalyticScene
    from drivetrack.camera.model import CameraModel
    from drivetrack.geometry import rigid_from_rotation_translation, rotation_from_rpy

    near_car = np.array([[[3.2, -1.2, 0.0], [7.2, 1.2, 1.6]]])
    scene = AnalyticScene(ground_z=0.0, boxes=np.concatenate([near_car, default_scene().boxes]))
    camera = CameraModel(f_u=514.0, f_v=514.0, c_u=240.0, c_v=160.0, k1=0.04, k2=-0.02, p1=0.0, p2=0.0, k3=0.0,
                         width=480, height=320, vehicle_from_camera=rigid_from_rotation_translation(
                             rotation_from_rpy(0.0, np.radians(15.0), 0.0), np.array([1.5, 0.0, 2.1])))
    truth = exact_depth(scene, camera)
    top = lidar_points(scene, origin=(0.0, 0.0, 2.2), azimuths=1325)
    side = lidar_points(scene, origin=(2.6, 1.1, 0.5), beams=32, azimuths=600, inclination_deg=(-60.0, 30.0),
                        max_range=20.0)
    sparse, reference = sparse_depth_from_points(np.concatenate([top, side]), camera,
                                                 subset=np.arange(len(top) + len(side)) < len(top))
    out = bound_blind_zone(sparse, reference, 4, 0.95, horizontal_depth_scale(camera))
    bounded = out < 0
    assert (bounded & (sparse == 0)).sum() > 5000            # the blind zone is bounded
    seen = bounded & (truth > 0)
    assert (-out[seen] >= 0.95 * truth[seen]).mean() > 0.999  # and never nearer than what is there
    np.testing.assert_array_equal(out[~bounded], sparse[~bounded])
    leaked = (sparse > 1.1 * np.maximum(truth, 1e-3)) & (truth > 0) & bounded
    assert leaked.sum() >= 10, leaked.sum()
    assert (-out[leaked] <= 1.05 * truth[leaked]).all()      # far returns seen round the car: replaced
