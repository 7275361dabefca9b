"""Returns that are not the object's: the road under a label drawn wider than its object, and a
neighbour inside the margins (``drivetrack.boxes.ground_under_boxes``,
``drivetrack.boxes.claimed_by_other_boxes``; ``RefineConfig.ground_ring`` / ``exclusive_returns``)."""
from __future__ import annotations

import numpy as np
import pytest

from drivetrack.boxes import (box_depth, claimed_by_other_boxes, fill_ground_over_time,
                              ground_under_boxes)
from drivetrack.refine import RefineConfig
from drivetrack.refine.kernel import gather


def _road(rng, half: float = 6.0, z: float = -2.0, count: int = 6000) -> np.ndarray:
    """float64 [count, 3]: returns of a flat road at vehicle-frame height ``z``, 1 cm of scatter."""
    xy = rng.uniform(-half, half, size=(count, 2))
    return np.column_stack([xy, z + rng.normal(0.0, 0.01, count)])


@pytest.mark.parametrize("use_kernel", [False, True])
def test_the_ground_under_a_box_is_measured_from_the_ring_round_it(use_kernel):
    """A car-sized box whose bottom lies 15 cm under the road (a loose label): the ground is
    found 15 cm above its bottom, to the scatter of the road; the car's own returns (inside
    the box) and a parked neighbour's lower half in the ring do not lift it; a box with no road
    round it (a sign above the road, no returns near its bottom) gets NaN."""
    rng = np.random.default_rng(0)
    road = _road(rng)
    car = np.column_stack([rng.uniform(-2.0, 2.0, 3000), rng.uniform(-0.9, 0.9, 3000), rng.uniform(-2.0, -0.5, 3000)])
    neighbour = np.column_stack([rng.uniform(-2.0, 2.0, 800), np.full(800, 1.6), rng.uniform(-2.0, -1.5, 800)])
    points = np.concatenate([road, car, neighbour])
    frame_offsets = np.array([0, points.shape[0]])
    laser = np.ones(points.shape[0], np.int8)
    center = np.array([[0.0, 0.0, -1.15 + 0.0], [0.0, 0.0, 3.0]])
    size = np.array([[4.3, 2.1, 2.0], [0.8, 0.1, 0.8]])            # car (bottom at -2.15), a sign
    kwargs = {"gather": gather} if use_kernel else {}
    ground = ground_under_boxes(points, laser, laser, frame_offsets, np.zeros(2, np.int64), center,
                                np.array([0.3, 0.0]), size, **kwargs)
    lift = ground[0] + size[0, 2] / 2
    assert abs(lift - 0.15) < 0.01, lift
    assert np.isnan(ground[1])


def test_a_return_another_box_holds_deeper_is_that_objects():
    """A pedestrian's box grown by a margin reaches a car's side: the car's returns there are the
    car's (its box holds them 15 cm deep: a loose label); the pedestrian's own returns stay its,
    and so does one inside both boxes but deeper in its own; a return exactly on a label's face
    counts as inside; boxes of other frames, or of the same object, claim nothing."""
    size = np.array([[4.3, 2.1, 1.6], [0.8, 0.8, 1.9], [0.8, 0.8, 1.9]])
    center = np.array([[0.0, 0.0, 0.8], [0.0, 1.65, 0.95], [0.0, 1.65, 0.95]])
    frame = np.array([0, 0, 1])
    obj = np.array(["car", "ped", "ped"])
    points = np.array([[0.0, 0.9, 0.8],       # the car's side face (0.15 inside its loose box), in the ped's margin
                       [0.1, 1.30, 1.0],      # the pedestrian's front (25 cm off the car's box)
                       [0.0, 1.65, 1.5],      # the pedestrian's middle
                       [0.0, 1.05, 0.8],      # on the car's label face exactly
                       [0.0, 0.9, 0.8],       # the car's side, frame 1 (no car box there)
                       [0.0, 1.00, 0.2]])     # both boxes (ped grown down: 5 cm in the car, 10 cm in it)
    size = np.vstack([size, [[0.8, 0.8, 1.9]]])
    size[3, 1] = 1.5
    center = np.vstack([center, [[0.0, 1.65, 0.95]]])
    frame = np.append(frame, 0)
    obj = np.append(obj, "ped")
    owner = np.array([1, 1, 1, 1, 2, 3])
    claimed = claimed_by_other_boxes(points, owner, frame, obj, center, np.zeros(4), size)
    np.testing.assert_array_equal(claimed, [True, False, False, True, False, False])
    np.testing.assert_allclose(box_depth(points[:1] - center[0], size[0] / 2), [0.15])
    assert not claimed_by_other_boxes(points[:1], np.array([0]), frame, obj, center, np.zeros(4), size).any()


def test_a_frame_without_road_round_the_box_takes_the_ground_of_the_frames_round_it():
    """Three boxes of one object on a road climbing 2 m a frame in the world, seen from an ego
    that climbs with it halfway: the middle frame's ground (unmeasured) is the world height
    between its neighbours', in its own box frame; an object never measured stays NaN."""
    world_from_vehicle = np.tile(np.eye(4), (3, 1, 1))
    world_from_vehicle[:, 2, 3] = [0.0, 0.5, 1.0]
    center = np.array([[10.0, 0, 1.0], [12.0, 0, 1.5], [14.0, 0, 2.0], [5.0, 3.0, 1.0]])
    ground = np.array([-1.1, np.nan, 0.9, np.nan])             # world heights -0.1 and 3.9
    filled = fill_ground_over_time(ground, np.array([0, 1, 2, 1]), np.array(["a", "a", "a", "b"]), center,
                                   world_from_vehicle)
    np.testing.assert_allclose(filled[[0, 2]], ground[[0, 2]])
    np.testing.assert_allclose(filled[1], 1.9 - 0.5 - 1.5)    # world 1.9, ego at 0.5, centre 1.5 up
    assert np.isnan(filled[3])


def test_the_rules_are_on_by_default_and_can_be_turned_off():
    config = RefineConfig()
    assert config.ground_ring and config.exclusive_returns
    off = RefineConfig(ground_ring=False, exclusive_returns=False)
    assert not (off.ground_ring or off.exclusive_returns)
    with pytest.raises(ValueError, match="ground_ring must be True or False"):
        RefineConfig(ground_ring="yes")


@pytest.fixture(scope="module")
def loose(tmp_path_factory):
    """A small hard world whose labels are drawn 30 cm wider than their objects (reaching under
    the road and round their neighbours) and carry 5 cm of noise."""
    from drivetrack.synth import SynthConfig, generate_segment

    src = str(tmp_path_factory.mktemp("loose") / "src")
    seg = generate_segment(src, SynthConfig(seed=7, frames=10, preset="small", cameras=("FRONT", "SIDE_RIGHT"),
                                            world="hard", box_noise_m=0.05, box_slack_m=0.3), 0)["segment"]
    return src, seg


def _candidate_owners(src: str, seg: str, config: RefineConfig) -> dict[str, np.ndarray]:
    """{"role k": int64 [P]}: for each object k, the truth object of each of its refinement
    candidates inside its label box grown by the registration's margin and above its clearance
    (1: its own, 2: another object's, -1: the road or the static background)."""
    from drivetrack.annotate import AnnotateConfig, load_scene_for
    from drivetrack.evaluation import TruthIndex
    from drivetrack.geometry import vectors_to_box
    from drivetrack.refine.scene import _own_candidates
    from drivetrack.tracks import TrackConfig

    scene = load_scene_for(src, "training", seg, AnnotateConfig(track=TrackConfig(cameras=("FRONT",))), refine=False)
    index = TruthIndex.load(src, "training", seg)
    objects = index.truth.objects
    lidar, boxes = scene.lidar, scene.boxes
    ids = boxes.object_id.astype(str)
    out = {}
    for k, (oid, role) in enumerate(zip(objects["object_id"].astype(str), objects["role"].astype(str))):
        role = f"{role} {k}"
        rows = np.flatnonzero(ids == oid)
        radius = 0.5 * np.linalg.norm(boxes.size[rows], axis=-1) + config.candidate_margin_m
        cand, owner = gather(lidar.points_vehicle, lidar.laser, lidar.return_index, None, None, lidar.frame_offsets,
                             boxes.frame[rows], boxes.center[rows], radius)
        cand, owner = _own_candidates(lidar, boxes, scene.world_from_vehicle, rows, cand, owner, None, None, config,
                                      use_kernel=True)
        r = rows[owner]
        q = vectors_to_box(lidar.points_vehicle[cand] - boxes.center[r], boxes.heading, rows=r)
        half = boxes.size[r] / 2
        near = (np.all(np.abs(q) <= half + config.inlier_margin_m, axis=-1)
                & (q[:, 2] >= -half[:, 2] + config.ground_clearance_m))
        cand = cand[near]
        sources = np.column_stack([lidar.laser[cand], lidar.return_index[cand], lidar.row[cand], lidar.col[cand]])
        hit = index.match(lidar.frame[cand], sources, seg)
        truth = np.where(hit >= 0, index.truth.hits["object_index"][np.maximum(hit, 0)], -1)
        out[role] = np.select([truth == k, truth >= 0], [1, 2], -1)     # 1 its own, 2 another object's
    return out


def test_loose_labels_leave_the_road_and_the_neighbours_out_of_the_registration(loose):
    """Without the rules the registration takes road returns (the labels reach under the road) and
    neighbours' (a pole's box takes the car behind it, a pedestrian's the parked car beside it);
    with them (the default) neither, and each object keeps at least 90% of its own (those it
    loses lie within 10 cm of the road: ``GROUND_BAND_M``)."""
    src, seg = loose
    before = _candidate_owners(src, seg, RefineConfig(ground_ring=False, exclusive_returns=False))
    after = _candidate_owners(src, seg, RefineConfig())
    road = {role: int((v == -1).sum()) for role, v in before.items()}
    other = {role: int((v == 2).sum()) for role, v in before.items()}
    assert sum(road.values()) > 1000 and sum(other.values()) > 300, (road, other)
    for role, v in after.items():
        assert not np.any(v == -1), (role, int((v == -1).sum()))
        assert not np.any(v == 2), (role, int((v == 2).sum()))
        assert (v == 1).sum() >= 0.9 * (before[role] == 1).sum(), role   # less the band over the road


def test_the_ground_kernel_gives_the_numpy_references_values():
    """``drivetrack.refine.kernel.ground_under_boxes`` (returns bucketed by x per frame, the ring
    tested as it goes) gives exactly the values of ``drivetrack.boxes.ground_under_boxes``: boxes
    in any order and heading over several frames, a laser / return filter, a box whose ring
    holds too few returns, a box beyond every return, run serially and on a pool of two."""
    from concurrent.futures import ThreadPoolExecutor

    from drivetrack import parallel
    from drivetrack.refine.kernel import ground_under_boxes as ground_kernel

    rng = np.random.default_rng(3)
    t_count, per_frame = 5, 20000
    points = np.concatenate([np.column_stack([rng.uniform(-30.0, 30.0, (per_frame, 2)),
                                              rng.normal(-2.0, 0.3, per_frame)]) for _ in range(t_count)])
    offsets = np.arange(t_count + 1) * per_frame
    laser = rng.integers(1, 6, points.shape[0]).astype(np.int8)
    return_index = rng.integers(1, 3, points.shape[0]).astype(np.int8)
    count = 40
    box_frame = rng.integers(0, t_count, count)
    center = np.column_stack([rng.uniform(-28.0, 28.0, (count, 2)), rng.uniform(-1.5, -0.5, count)])
    center[0] = (80.0, 0.0, -1.0)                                                  # nothing round it
    size = np.column_stack([rng.uniform(0.5, 5.0, count), rng.uniform(0.5, 2.5, count), rng.uniform(0.8, 2.0, count)])
    size[1] = (0.3, 0.3, 0.3)
    center[1, 2] = 4.0                                                             # too few returns
    heading = rng.uniform(-np.pi, np.pi, count)
    for lasers, returns in ((None, None), ((1, 3), (1,))):
        args = (points, laser, return_index, offsets, box_frame, center, heading, size, lasers, returns)
        expect = ground_under_boxes(*args)
        assert np.isnan(expect[:2]).all() and np.isfinite(expect[2:]).sum() > 30
        np.testing.assert_array_equal(ground_kernel(*args), expect)
        with ThreadPoolExecutor(2) as pool, parallel.using(pool.map):
            np.testing.assert_array_equal(ground_kernel(*args), expect)


def test_the_claim_kernel_gives_the_numpy_references_values():
    """``drivetrack.refine.kernel.claimed_by_other_boxes`` gives exactly the claims of
    ``drivetrack.boxes.claimed_by_other_boxes``: overlapping boxes of several objects over several
    frames, points of unsorted owners, two boxes of one object in a frame, serially and on a pool."""
    from concurrent.futures import ThreadPoolExecutor

    from drivetrack import parallel
    from drivetrack.refine.kernel import claimed_by_other_boxes as claim_kernel

    rng = np.random.default_rng(4)
    count = 60
    box_frame = rng.integers(0, 4, count)
    box_object = rng.choice(np.array(["a", "b", "c", "d", "e", "f", "g"]), count)
    center = np.column_stack([rng.uniform(-6.0, 6.0, (count, 2)), rng.uniform(-1.5, -0.5, count)])
    size = np.column_stack([rng.uniform(0.5, 5.0, count), rng.uniform(0.5, 2.5, count), rng.uniform(0.8, 2.0, count)])
    heading = rng.uniform(-np.pi, np.pi, count)
    owner = rng.integers(0, count, 30000)
    points = center[owner] + rng.normal(0.0, 1.5, (owner.size, 3))
    expect = claimed_by_other_boxes(points, owner, box_frame, box_object, center, heading, size)
    assert 0.05 < expect.mean() < 0.95
    np.testing.assert_array_equal(claim_kernel(points, owner, box_frame, box_object, center, heading, size), expect)
    with ThreadPoolExecutor(2) as pool, parallel.using(pool.map):
        np.testing.assert_array_equal(claim_kernel(points, owner, box_frame, box_object, center, heading, size,
                                                   tolerance_m=0.1),
                                      claimed_by_other_boxes(points, owner, box_frame, box_object, center, heading,
                                                             size, tolerance_m=0.1))
