"""The synthetic world's bodies never drive through each other (nor through the ego), so every
return, z-buffer surface and track belongs to one object."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from drivetrack.synth.config import FRAME_PERIOD_S, SynthConfig
from drivetrack.synth.world import (CLEARANCE_M, EGO_BOX, EGO_LANES, Motion, SynthObject, World, make_world,
                                    world_overlaps)

HARD_ROLES = ("oblique", "occluder", "hidden", "pole", "low_sign", "pedestrian_near_car", "close_pass",
              "overtaken_right", "turning", "crossing_cyclist")


def _world(seed: int, frames: int, kind: str) -> World:
    return make_world(np.random.default_rng(np.random.SeedSequence([seed, 0]).spawn(3)[0]),
                      frames * FRAME_PERIOD_S, kind)


@pytest.mark.parametrize("kind", ["default", "hard"])
@pytest.mark.parametrize("frames", [6, 20, 40])
def test_no_two_bodies_come_closer_than_the_clearance(kind, frames):
    """Before the placement, every one of these worlds had overlapping boxes: the ego drove
    through the overtaking car (both worlds, every seed), the lead car through the crossing one,
    the hard world's overtaking car through the overtaken one."""
    for seed in (1, 3, 7, 11):
        world = _world(seed, frames, kind)
        assert world_overlaps(world, frames * FRAME_PERIOD_S) == [], (seed, frames, kind)
        roles = [o.role for o in world.objects]
        assert roles.count("parked") == 3 and roles.count("pedestrian") == 3, roles
        if kind == "hard":
            assert all(r in roles for r in HARD_ROLES), (seed, frames, sorted(set(HARD_ROLES) - set(roles)))
            assert "overtaking" not in roles       # its lane is the overtaken car's
        else:
            assert "overtaking" in roles


def test_the_hard_world_keeps_the_default_objects_where_they_are():
    """The hard world's objects are placed after the default ones, around them; the default ones
    (but the overtaking car) are the default world's, the same ids and motions."""
    for seed in (3, 7):
        default, hard = _world(seed, 40, "default"), _world(seed, 40, "hard")
        kept = [o for o in default.objects if o.role != "overtaking"]
        assert [(o.object_id, o.motion) for o in hard.objects[:len(kept)]] == [(o.object_id, o.motion) for o in kept]
        assert hard.ego == default.ego


def _car(role: str, motion: Motion, size=(4.5, 2.0, 1.5)) -> SynthObject:
    return SynthObject(object_id=role, type=1, size=size, z_center=size[2] / 2, motion=motion, color=(0.5, 0.5, 0.5),
                       pattern=0, texture_scale=0.3, seed=0, role=role)


def test_world_overlaps_names_the_pair_and_the_first_instant():
    ego = Motion((0.0, EGO_LANES[0]), 0.0, s=8.0)
    gap = 1.0 + CLEARANCE_M / 2                   # rear of the parked car to the ego's front at t = 0
    front = EGO_BOX[0] + EGO_BOX[1] / 2
    parked = _car("parked", Motion((front + gap + 2.25, EGO_LANES[0]), 0.0))
    beside = _car("beside", Motion((EGO_BOX[0], EGO_LANES[0] - 3.5), 0.0, s=8.0))      # 1.45 m between sides
    above = _car("sign", Motion((front + gap + 2.25, EGO_LANES[0]), 0.0), size=(0.2, 0.9, 0.9))
    above = dataclasses.replace(above, z_center=2.5)                                  # over the parked car
    world = World(ego=ego, pitch_amplitude=0.0, roll_amplitude=0.0, objects=(parked, beside, above), ground_seed=0)
    found = world_overlaps(world, 1.0)
    assert [(a, b) for a, b, _ in found] == [("ego", "parked")]
    # the ego closes 1.1 m at 8 m/s; it comes within the clearance (0.1 m) after 1.0 / 8 s
    assert found[0][2] == pytest.approx(1.0 / 8.0, abs=0.021)
    assert world_overlaps(world, 0.05) == []


def test_an_object_in_the_way_is_moved_along_its_path_or_the_road():
    """make_world's placement: a mover that would run into a body comes later or earlier (moved
    along its heading), a static one is moved along the road; each by the first clear shift."""
    from drivetrack.synth.world import _check_times, _ego_body, _object_body, _place

    times = _check_times(2.0)
    ego = Motion((0.0, EGO_LANES[0]), 0.0, s=8.0)
    bodies = [_ego_body(ego, times)]
    parked = _car("parked", Motion((20.0, -8.0), 0.0))
    bodies.append(_object_body(parked, times))
    crossing = _car("crossing", Motion((20.0, -20.0), np.pi / 2, s=6.0))     # meets the parked car at t ~ 2 s
    moved = _place(crossing, bodies, times)
    assert moved.motion.p0[0] == 20.0 and moved.motion.p0[1] != -20.0
    assert world_overlaps(World(ego, 0.0, 0.0, (parked, moved), 0), 2.0) == []
    assert _object_body(crossing, times).clash(bodies[1]).any()
    blocking = _car("parked2", Motion((21.0, -8.0), 0.0))
    moved = _place(blocking, bodies, times)
    assert moved.motion.p0[1] == -8.0 and abs(moved.motion.p0[0] - 21.0) == pytest.approx(
        np.ceil(4.5 + CLEARANCE_M - 1.0))


def test_a_surging_mover_brakes_and_speeds_up_with_consistent_derivatives():
    """``Motion.surge``: the along-track acceleration ``g cos(W t + phi)``; velocity, acceleration,
    heading and yaw rate are the derivatives of the closed-form position (checked by central
    differences), and the surge leaves t = 0 where it was."""
    m = Motion((3.0, -1.0), 0.3, s=8.0, a=-1.5, w=2 * np.pi / 6.0, surge=1.8, surge_w=2 * np.pi / 5.0, surge_phase=1.1)
    flat = dataclasses.replace(m, surge=0.0)
    t = np.linspace(-0.05, 4.05, 83)
    h = 1e-5
    np.testing.assert_allclose(m.velocity_xy(t), (m.position_xy(t + h) - m.position_xy(t - h)) / (2 * h), atol=1e-6)
    np.testing.assert_allclose(m.acceleration_xy(t), (m.velocity_xy(t + h) - m.velocity_xy(t - h)) / (2 * h), atol=1e-6)
    np.testing.assert_allclose(m.yaw_rate(t), (m.heading(t + h) - m.heading(t - h)) / (2 * h), atol=1e-6)
    v = m.velocity_xy(t)
    np.testing.assert_allclose(m.heading(t), np.arctan2(v[:, 1], v[:, 0]), atol=1e-12)
    np.testing.assert_allclose(m.position_xy(np.zeros(1)), flat.position_xy(np.zeros(1)), atol=1e-12)
    along = np.einsum("ti,i->t", m.acceleration_xy(t) - flat.acceleration_xy(t), [np.cos(0.3), np.sin(0.3)])
    np.testing.assert_allclose(along, 1.8 * np.cos(2 * np.pi / 5.0 * t + 1.1), atol=1e-9)
    with pytest.raises(ValueError, match="surge"):
        Motion((0.0, 0.0), 0.0, s=0.0, surge=1.0, surge_w=1.0)
    with pytest.raises(ValueError, match="surge"):
        Motion((0.0, 0.0), 0.0, s=5.0, turn=0.2, surge=1.0, surge_w=1.0)


@pytest.mark.parametrize("kind", ["default", "hard"])
def test_speed_changes_leave_the_rest_of_the_world_as_it_was(kind):
    """``make_world(speed_changes_mps2=...)``: moving vehicles and cyclists that do not turn brake
    and speed up (acceleration amplitude within [0.5, 1] of the setting, speed above half its
    mean); every object keeps its id, size and colour, nothing else surges, and nothing drives
    through anything."""
    for seed in (1, 7):
        rng = lambda: np.random.default_rng(np.random.SeedSequence([seed, 0]).spawn(3)[0])  # noqa: E731
        plain = make_world(rng(), 4.0, kind)
        surging = make_world(rng(), 4.0, kind, 2.0, np.random.default_rng(seed))
        assert [(o.object_id, o.size, o.color, o.role) for o in surging.objects] == \
            [(o.object_id, o.size, o.color, o.role) for o in plain.objects]
        assert world_overlaps(surging, 4.0) == []
        t = np.linspace(0.0, 4.0, 41)
        for o in surging.objects:
            m = o.motion
            eligible = o.type in (1, 4) and m.turn == 0.0 and m.s > 0.0        # VEHICLE, CYCLIST
            assert (m.surge != 0.0) == eligible, (o.role, m)
            if eligible:
                assert m.surge <= 2.0 and (m.surge >= 1.0 or m.surge == pytest.approx(0.25 * m.s * m.surge_w))
                assert 2 * np.pi / 8.0 <= m.surge_w <= 2 * np.pi / 4.0
                assert np.linalg.norm(m.velocity_xy(t), axis=-1).min() >= 0.5 * m.s
    with pytest.raises(ValueError, match="speed_changes_mps2"):
        make_world(np.random.default_rng(0), 4.0, kind, -1.0)
    with pytest.raises(ValueError, match="speed_changes_mps2"):
        SynthConfig(speed_changes_mps2=-1.0)


@pytest.mark.parametrize("kind", ["default", "hard"])
def test_rear_axles_make_the_centres_of_turning_movers_slip_sideways(kind):
    """``make_world(rear_axle_fraction=0.3)``: every moving vehicle and cyclist drives on the point
    0.3 of its length behind its centre (no lateral velocity there, checked by central differences
    of the closed-form centre and heading), its centre slips sideways by ``yaw rate x offset``, its
    velocity and acceleration stay the derivatives of its centre; the same objects, nothing drives
    through anything, and the default (0) is the world as before."""
    for seed in (1, 7):
        rng = lambda: np.random.default_rng(np.random.SeedSequence([seed, 0]).spawn(3)[0])  # noqa: E731
        plain = make_world(rng(), 4.0, kind)
        same = make_world(rng(), 4.0, kind, rear_axle_fraction=0.0)
        axled = make_world(rng(), 4.0, kind, rear_axle_fraction=0.3)
        assert same == plain
        assert [(o.object_id, o.size, o.role) for o in axled.objects] == [(o.object_id, o.size, o.role)
                                                                          for o in plain.objects]
        assert world_overlaps(axled, 4.0) == []
        t, h = np.linspace(0.0, 4.0, 41), 1e-5
        slipping = 0
        for o in axled.objects:
            m = o.motion
            wheeled_mover = o.type in (1, 4) and (m.s > 0.0 or m.turn != 0.0)
            assert o.axle_offset_m == (pytest.approx(0.3 * o.size[0]) if wheeled_mover else 0.0), o.role
            if not wheeled_mover:
                continue
            np.testing.assert_allclose(o.velocity(t), (o.center(t + h) - o.center(t - h)) / (2 * h), atol=1e-5)
            np.testing.assert_allclose(o.acceleration(t), (o.velocity(t + h) - o.velocity(t - h)) / (2 * h),
                                       atol=1e-4)

            def axle(tt, o=o):
                head = o.heading(tt)
                return o.center(tt)[..., :2] - o.axle_offset_m * np.stack([np.cos(head), np.sin(head)], -1)

            left = np.stack([-np.sin(o.heading(t)), np.cos(o.heading(t))], -1)
            axle_lateral = np.einsum("ti,ti->t", (axle(t + h) - axle(t - h)) / (2 * h), left)
            np.testing.assert_allclose(axle_lateral, 0.0, atol=1e-6)
            centre_lateral = np.einsum("ti,ti->t", o.velocity(t)[:, :2], left)
            np.testing.assert_allclose(centre_lateral, o.axle_offset_m * m.yaw_rate(t), atol=1e-6)
            slipping += int(np.abs(centre_lateral).max() > 0.05)
        assert slipping >= (1 if kind == "hard" else 0)      # the default world's movers drive straight
    with pytest.raises(ValueError, match="rear_axle_fraction"):
        make_world(np.random.default_rng(0), 4.0, kind, rear_axle_fraction=0.5)
    with pytest.raises(ValueError, match="rear_axle_fraction"):
        SynthConfig(rear_axle_fraction=-0.1)
