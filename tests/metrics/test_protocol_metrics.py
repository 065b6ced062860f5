"""WHDR, NYUv2 depth and normal scores against hand-computed cases."""

import math

import numpy as np
import pytest

from pipeline.metrics.depth import median_scaled, si_error, si_rmse
from pipeline.metrics.normal import angles, mean_angular_error, pooled_stats
from pipeline.metrics.whdr import JudgementError, whdr


def _judgements(points, comparisons):
    return {
        "intrinsic_points": [{"id": i, "x": x, "y": y, "opaque": o} for i, (x, y, o) in enumerate(points)],
        "intrinsic_comparisons": [
            {"id": 100 + k, "point1": a, "point2": b, "darker": d, "darker_score": w}
            for k, (a, b, d, w) in enumerate(comparisons)
        ],
    }


def _image():
    """4 x 4 image: left half reflectance 0.2, right half 0.4 (grey), bottom-right pixel 0.21."""
    r = np.full((4, 4, 3), 0.2)
    r[:, 2:] = 0.4
    r[3, 3] = 0.21
    return r


# points: 0 left (0.2), 1 right (0.4), 2 left again (0.2), 3 bottom-right (0.21), 4 non-opaque
POINTS = [(0.1, 0.1, True), (0.9, 0.1, True), (0.3, 0.6, True), (0.99, 0.99, True), (0.6, 0.1, False)]


def test_whdr_counts_weighted_disagreements():
    j = _judgements(POINTS, [(0, 1, "1", 1.0), (1, 0, "1", 3.0)])  # first right, second wrong (weight 3)
    assert whdr(_image(), j) == pytest.approx(3.0 / 4.0)


def test_whdr_ties_and_equal_judgements():
    # equal reflectance -> the algorithm says E; within delta (0.2 vs 0.21) -> E as well
    j = _judgements(POINTS, [(0, 2, "E", 1.0), (0, 3, "E", 1.0), (0, 3, "1", 2.0)])
    assert whdr(_image(), j, convention="linear") == pytest.approx(2.0 / 4.0)
    # a judgement of darker on an exact tie is a disagreement
    assert whdr(_image(), _judgements(POINTS, [(0, 2, "2", 1.0)])) == 1.0


def test_whdr_skips_non_opaque_points_zero_weights_and_bad_labels():
    j = _judgements(
        POINTS, [(0, 4, "2", 5.0), (0, 1, "2", 0.0), (0, 1, "2", -1.0), (0, 1, None, 1.0), (0, 1, "1", 1.0)]
    )
    assert whdr(_image(), j) == 0.0
    assert math.isnan(whdr(_image(), _judgements(POINTS, [(0, 4, "2", 5.0)])))


def test_whdr_gamma_and_linear_conventions_differ_as_expected():
    # 0.2 vs 0.25: ratio 1.25 > 1.1 in linear; 1.25^(1/2.2) = 1.107 > 1.1 still; 0.2 vs 0.23: 1.15 linear,
    # 1.15^(1/2.2) = 1.0656 < 1.1 in gamma -> E
    r = np.full((1, 2, 3), 0.2)
    r[0, 1] = 0.23
    j = _judgements([(0.1, 0.5, True), (0.6, 0.5, True)], [(0, 1, "1", 1.0)])
    assert whdr(r, j, convention="linear") == 0.0
    assert whdr(r, j, convention="gamma") == 1.0
    # global scale never matters
    assert whdr(7.0 * r, j, convention="linear") == whdr(r, j, convention="linear")


def test_whdr_uses_the_channel_mean_and_truncated_lookup():
    r = np.zeros((2, 2, 3))
    r[0, 0] = (0.6, 0.0, 0.0)  # mean 0.2
    r[0, 1] = (0.2, 0.2, 0.2)  # mean 0.2 -> equal
    r[1, :] = 0.5
    j = _judgements([(0.49, 0.49, True), (0.5, 0.0, True), (0.0, 0.5, True)], [(0, 1, "E", 1.0), (0, 2, "1", 1.0)])
    assert whdr(r, j, convention="linear") == 0.0
    # gamma encodes each channel before the mean: (0.6^(1/2.2)) / 3 = 0.26 < 0.2^(1/2.2) = 0.48 -> "1", not E
    assert whdr(r, j, convention="gamma") == 0.5


def test_whdr_rejects_malformed_judgements():
    with pytest.raises(JudgementError, match="point 9"):
        whdr(_image(), _judgements(POINTS, [(0, 9, "1", 1.0)]))
    with pytest.raises(JudgementError, match="intrinsic_comparisons"):
        whdr(_image(), {"intrinsic_points": []})
    with pytest.raises(JudgementError, match="outside the image"):
        whdr(_image(), _judgements([(1.0, 0.5, True), (0.1, 0.1, True)], [(0, 1, "1", 1.0)]))
    with pytest.raises(ValueError, match="convention"):
        whdr(_image(), _judgements(POINTS, []), convention="srgb")
    with pytest.raises(ValueError, match="NaN"):
        whdr(np.full((2, 2, 3), np.nan), _judgements(POINTS, []))


def test_si_rmse_is_scale_invariant_and_masks_1_to_10_metres():
    rng = np.random.default_rng(0)
    gt = rng.uniform(0.5, 12.0, (20, 30))
    pred = gt * np.exp(rng.normal(0, 0.1, gt.shape))
    assert si_rmse(3.7 * pred, gt) == pytest.approx(si_rmse(pred, gt), rel=1e-12)
    assert si_rmse(gt * 42.0, gt) == pytest.approx(0.0, abs=1e-9)
    # errors outside 1-10 m do not count, but those pixels still enter the means (the reference's choice)
    bad = pred.copy()
    out = (gt <= 1.0) | (gt >= 10.0)
    bad[out] *= 5.0
    a, b = np.log(bad + 1e-20), np.log(gt + 1e-20)
    a, b = a - a.mean(), b - b.mean()
    assert si_error(bad, gt) == pytest.approx(((a - b) ** 2)[~out].mean(), rel=1e-12)
    assert math.isnan(si_rmse(pred, np.full_like(gt, 0.5)))


def test_si_rmse_hand_case():
    gt = np.array([[2.0, 4.0]])
    pred = np.array([[1.0, 1.0]])  # a = 0, b = log2 +-: (a-b)^2 = (log 2 / 2)^2 each
    assert si_rmse(pred, gt) == pytest.approx(math.log(2) / 2, rel=1e-12)


def test_median_scaled_scores():
    gt = np.array([[2.0, 4.0, 8.0]])
    m = median_scaled(gt * 0.1, gt)
    assert m["abs_rel"] == pytest.approx(0.0) and m["delta_1.25"] == 1.0
    with pytest.raises(ValueError, match="equal"):
        median_scaled(gt, gt.T)


def test_normal_angles_respect_the_mask_and_renormalisation():
    gt = np.zeros((2, 2, 3))
    gt[..., 2] = 2.0  # not unit: the ground truth is normalised
    pred = np.zeros((2, 2, 3))
    pred[..., 2] = 1.0
    pred[0, 0] = (1.0, 0.0, 0.0)  # 90 degrees off
    pred[1, 1] = (0.0, 0.0, 0.5)  # right direction, half length: cos 0.5 -> 60 deg unless renormalised
    mask = np.array([[True, True], [False, True]])
    assert mean_angular_error(pred, gt, mask) == pytest.approx((90 + 0 + 60) / 3)
    assert mean_angular_error(pred, gt, mask, renormalize=True) == pytest.approx(30.0)
    assert math.isnan(mean_angular_error(pred, gt, np.zeros((2, 2), bool)))
    stats = pooled_stats([angles(pred, gt, mask, True), np.array([10.0])])
    assert stats["pooled_median"] == pytest.approx(5.0) and stats["pct_under_11.25"] == pytest.approx(75.0)
