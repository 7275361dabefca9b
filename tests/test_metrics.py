"""TAP-Vid metrics checked against values computed by hand."""
from __future__ import annotations

import numpy as np
import pytest

from drivetrack.evaluation.metrics import (compute_tapvid_metrics, evaluation_mask, queries_first, queries_strided,
                                rescale_points, to_tapvid)


def one_track_case():
    """One track, 4 frames, truth visible at (10, 10) everywhere.

    Prediction: frame 0 exact; frame 1 off by 0.5 px; frame 2 off by 3 px; frame 3 exact but
    predicted occluded.
    """
    gt_tracks = np.full((1, 1, 4, 2), 10.0)
    pred_tracks = gt_tracks.copy()
    pred_tracks[0, 0, 1, 0] += 0.5
    pred_tracks[0, 0, 2, 0] += 3.0
    gt_occluded = np.zeros((1, 1, 4), bool)
    pred_occluded = np.array([[[False, False, False, True]]])
    return gt_occluded, gt_tracks, pred_occluded, pred_tracks


def test_first_mode_known_values():
    gt_occ, gt, pred_occ, pred = one_track_case()
    query = np.array([[[0.0, 10.0, 10.0]]])   # (t, y, x): frames 1, 2, 3 are scored
    m = compute_tapvid_metrics(query, gt_occ, gt, pred_occ, pred, "first")
    assert m["occlusion_accuracy"][0] == pytest.approx(2 / 3)
    # within 1 and 2 px: frames 1 and 3 (occlusion prediction ignored); 4+ px: all three
    assert m["pts_within_1"][0] == pytest.approx(2 / 3)
    assert m["pts_within_2"][0] == pytest.approx(2 / 3)
    for d in (4, 8, 16):
        assert m[f"pts_within_{d}"][0] == pytest.approx(1.0)
    # d = 1, 2: TP = frame 1; FP = frame 2 (visible but too far); 3 ground-truth positives
    assert m["jaccard_1"][0] == pytest.approx(1 / 4)
    assert m["jaccard_2"][0] == pytest.approx(1 / 4)
    # d >= 4: TP = frames 1, 2; frame 3 is a false negative only
    for d in (4, 8, 16):
        assert m[f"jaccard_{d}"][0] == pytest.approx(2 / 3)
    assert m["average_jaccard"][0] == pytest.approx((1 / 4 + 1 / 4 + 3 * 2 / 3) / 5)
    assert m["average_pts_within_thresh"][0] == pytest.approx((2 / 3 + 2 / 3 + 3) / 5)


def test_query_modes_choose_the_scored_frames():
    gt_occ, gt, pred_occ, pred = one_track_case()
    query = np.array([[[2.0, 10.0, 10.0]]])
    first = compute_tapvid_metrics(query, gt_occ, gt, pred_occ, pred, "first")       # frame 3 only
    strided = compute_tapvid_metrics(query, gt_occ, gt, pred_occ, pred, "strided")   # frames 0, 1, 3
    assert first["occlusion_accuracy"][0] == 0.0
    assert first["jaccard_1"][0] == 0.0 and first["pts_within_1"][0] == 1.0
    assert strided["occlusion_accuracy"][0] == pytest.approx(2 / 3)
    assert strided["jaccard_1"][0] == pytest.approx(2 / 3)
    np.testing.assert_array_equal(evaluation_mask(np.array([1, 2.4]), 4, "first"),
                                  [[False, False, True, True], [False, False, False, True]])
    np.testing.assert_array_equal(evaluation_mask(np.array([1]), 3, "strided"), [[True, False, True]])
    with pytest.raises(ValueError, match="query_mode 'last'"):
        evaluation_mask(np.array([0]), 3, "last")


def test_threshold_is_strict_and_occluded_truth_counts_as_false_positive():
    gt = np.zeros((1, 1, 3, 2))
    pred = gt.copy()
    pred[..., 0] = 1.0                                  # exactly 1 px off everywhere
    gt_occ = np.array([[[False, False, True]]])         # last frame occluded in the truth
    pred_occ = np.zeros((1, 1, 3), bool)                # predicted visible everywhere
    m = compute_tapvid_metrics(np.zeros((1, 1, 3)), gt_occ, gt, pred_occ, pred, "strided")
    # scored frames 1, 2: frame 1 visible, distance^2 = 1 is not < 1
    assert m["pts_within_1"][0] == 0.0 and m["pts_within_2"][0] == 1.0
    assert m["occlusion_accuracy"][0] == 0.5
    # d = 2: TP = frame 1, FP = frame 2 (truth occluded), positives = 1 -> 1 / 2
    assert m["jaccard_2"][0] == pytest.approx(0.5)
    assert m["jaccard_1"][0] == 0.0


def test_batches_per_track_and_empty_denominators():
    gt_occ, gt, pred_occ, pred = one_track_case()
    both_occ = np.concatenate([gt_occ, np.ones_like(gt_occ)], axis=1)     # track 2 never visible
    both_gt = np.concatenate([gt, gt], axis=1)
    both_pred_occ = np.concatenate([pred_occ, pred_occ], axis=1)
    both_pred = np.concatenate([pred, pred], axis=1)
    query = np.zeros((1, 2, 3))
    per_track = compute_tapvid_metrics(query, both_occ, both_gt, both_pred_occ, both_pred, "first", per_track=True)
    assert per_track["jaccard_1"].shape == (1, 2)
    assert per_track["jaccard_1"][0, 0] == pytest.approx(1 / 4)
    assert np.isnan(per_track["pts_within_1"][0, 1])      # no visible ground truth
    with pytest.raises(ValueError, match="pred_tracks must have shape"):
        compute_tapvid_metrics(query, both_occ, both_gt, both_pred_occ, both_pred[:, :1], "first")


def test_query_sampling_and_conversions():
    visibles = np.array([[False, True, True, False], [False, False, False, False], [True, False, True, True]])
    tracks = np.arange(24, dtype=float).reshape(3, 4, 2)
    q, idx = queries_first(visibles, tracks)
    np.testing.assert_array_equal(idx, [0, 2])
    np.testing.assert_array_equal(q, [[1, 3, 2], [0, 17, 16]])          # (t, y, x)
    q, idx = queries_strided(visibles, tracks, stride=2)
    np.testing.assert_array_equal(idx, [2, 0, 2])
    np.testing.assert_array_equal(q[:, 0], [0, 2, 2])
    np.testing.assert_array_equal(rescale_points(np.array([[1920.0, 1280.0]]), (1920, 1280), (256, 256)), [[256, 256]])
    out = to_tapvid(np.array([[[960.0, 640.0]]]), np.array([[True]]), 1920, 1280)
    np.testing.assert_allclose(out["points"], [[[0.5, 0.5]]])
    assert out["occluded"].tolist() == [[False]]
