"""The extent term (``RefineConfig.extent_sigma_m``, :mod:`drivetrack.refine.extent`): where a
side face's returns end measures a box car's position along its heading, which the face itself
(a plane) does not."""
from __future__ import annotations

import numpy as np
import pytest

from drivetrack.refine import RefineConfig
from drivetrack.refine.extent import end_candidates, extent_shifts

SIZE = np.array([4.6, 1.9, 1.6])


def _side_returns(shift: np.ndarray, heading: np.ndarray, cut: dict | None = None, seed: int = 0):
    """Vehicle-frame returns on the left face (body y = +0.95) of a box whose true centre in frame
    t is ``shift[t]`` ahead of the box ``(0, -5, 0.8)`` with ``heading[t]``, on a 1.2 cm grid along
    the face starting at a random phase (the beams do not meet the ends), 6 cm rows up it;
    ``cut`` {frame: x}: that frame's returns behind body x are missing (an occluder)."""
    rng = np.random.default_rng(seed)
    points, frame = [], []
    for t, (s, h) in enumerate(zip(shift, heading)):
        x = np.arange(-SIZE[0] / 2 + rng.uniform(0, 0.012), SIZE[0] / 2, 0.012)
        if cut and t in cut:
            x = x[x > cut[t]]
        z = np.arange(-0.6, 0.8, 0.06)
        gx, gz = np.meshgrid(x, z)
        body = np.stack([gx.ravel() + s, np.full(gx.size, 0.95), gz.ravel()], -1)
        rot = np.array([[np.cos(h), -np.sin(h), 0], [np.sin(h), np.cos(h), 0], [0, 0, 1]])
        points.append(body @ rot.T + [0.0, -5.0, 0.8])
        frame.append(np.full(gx.size, t))
    return np.concatenate(points), np.concatenate(frame)


def test_extent_shifts_measure_each_frames_offset_along_the_heading():
    t_count = 8
    rng = np.random.default_rng(3)
    shift = rng.normal(0.0, 0.03, t_count)                 # the boxes' errors along the heading
    heading = np.linspace(0.0, 0.2, t_count)
    points, frame = _side_returns(shift, heading)
    center = np.tile([0.0, -5.0, 0.8], (t_count, 1))
    half = np.tile(SIZE / 2, (t_count, 1))
    measured, used = extent_shifts(points, frame, center, heading, None, half, t_count, 0.15, 0.2)
    assert used.all()
    # relative to the frames' median ends (the gauge): within a grid spacing
    want = shift - np.median(shift)
    assert np.abs((measured - np.median(measured)) - want).max() < 0.012
    # the candidates of end_candidates give the same answer as all returns
    ends = end_candidates(points, frame, center, heading, None, half, 0.45)
    assert ends.size < points.shape[0] / 2
    again, used_again = extent_shifts(points[ends], frame[ends], center, heading, None, half, t_count, 0.15, 0.2)
    np.testing.assert_array_equal(again, measured)
    np.testing.assert_array_equal(used_again, used)


def test_a_frame_whose_end_is_cut_short_is_not_used():
    t_count = 6
    points, frame = _side_returns(np.zeros(t_count), np.zeros(t_count), cut={2: -1.5})
    center = np.tile([0.0, -5.0, 0.8], (t_count, 1))
    half = np.tile(SIZE / 2, (t_count, 1))
    shift, used = extent_shifts(points, frame, center, np.zeros(t_count), None, half, t_count, 0.15, 0.2)
    assert used.tolist() == [True, True, False, True, True, True]
    assert shift[2] == 0.0 and np.abs(shift).max() < 0.012
    # too few frames agree: nothing is used
    few = frame < 2
    shift, used = extent_shifts(points[few], frame[few], center, np.zeros(t_count), None, half, t_count, 0.15, 0.2)
    assert not used.any() and not shift.any()


@pytest.mark.parametrize("value", [0.0, -0.01, float("nan"), True, "0.01"])
def test_extent_sigma_must_be_none_or_positive(value):
    with pytest.raises(ValueError, match="extent_sigma_m"):
        RefineConfig(extent_sigma_m=value)
    assert RefineConfig(extent_sigma_m=None).extent_sigma_m is None
