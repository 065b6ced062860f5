"""Insertion scores and the paired bootstrap."""

import numpy as np
import pytest
import torch

from pipeline.metrics.bootstrap import paired_bootstrap
from pipeline.metrics.insertion import case_scores, noise_floor_psnr, psnr_decorrelated, psnr_extrapolated


def test_paired_bootstrap_covers_the_true_mean_at_its_level():
    """Over 300 simulated studies (30 differences, mean 0.5, sd 1) the 95 % interval holds the true mean
    in 95 % of them; the binomial sd of the coverage is 1.3 %, and a percentile bootstrap on 30 cases
    runs a little narrow, so 0.89-0.99 is the band."""
    rng = np.random.default_rng(0)
    hits = 0
    for k in range(300):
        ci = paired_bootstrap(rng.normal(0.5, 1.0, 30), resamples=1000, seed=k)
        hits += ci["lo"] <= 0.5 <= ci["hi"]
    assert 0.89 <= hits / 300 <= 0.99


def test_groups_are_resampled_whole():
    """Cases of one view that share an error: resampling them singly would make the interval too narrow."""
    rng = np.random.default_rng(1)
    view_error = np.repeat(rng.normal(0, 1, 20), 5)  # 20 views, 5 cases each, a shared error per view
    diff = view_error + rng.normal(0, 0.05, 100)
    groups = np.repeat(np.arange(20), 5)
    by_case = paired_bootstrap(diff, 2000, 0)
    by_view = paired_bootstrap(diff, 2000, 0, groups=groups)
    assert by_view["diff"] == pytest.approx(by_case["diff"])
    assert (by_view["hi"] - by_view["lo"]) > 1.8 * (by_case["hi"] - by_case["lo"])  # sqrt(5) ideally
    one = paired_bootstrap([1.0, 2.0], groups=["a", "a"])
    assert one["diff"] == 1.5 and np.isnan(one["lo"]) and np.isnan(one["hi"])
    same = paired_bootstrap(np.full(10, 0.7), groups=np.arange(10))
    assert same["lo"] == pytest.approx(0.7) and same["hi"] == pytest.approx(0.7)
    with pytest.raises(ValueError, match="NaN"):
        paired_bootstrap([1.0, np.nan])


def test_case_scores_and_the_noise_floor():
    photo = torch.rand(16, 16, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) + 0.1
    pixels = torch.tensor([35, 36, 51, 52, 120, 121])
    target = photo.reshape(-1, 3)[pixels] * 2
    exact = case_scores(target, target, photo, pixels, 0.5)
    assert exact["psnr"] == pytest.approx(120.0) and exact["log_l1"] == 0 and exact["ssim"] == pytest.approx(1.0)
    worse = case_scores(target * 1.5, target, photo, pixels, 0.5)
    assert worse["psnr"] < 40 and worse["log_l1"] > 0 and worse["ssim"] < 1
    # noise floor: the expected tone-mapped MSE of truth + noise, against a Monte Carlo estimate of it
    se = target * 0.05
    rng = torch.Generator().manual_seed(2)
    mses = []
    for _ in range(400):
        noisy = target + se * torch.randn(target.shape, generator=rng, dtype=torch.float64)
        mses.append(10 ** (-case_scores(noisy, target, photo, pixels, 0.5)["psnr"] / 10))
    assert noise_floor_psnr(target, se, 0.5) == pytest.approx(-10 * np.log10(np.mean(mses)), abs=0.5)


def test_decorrelated_psnr_is_the_converged_renders_not_the_noisy_ones():
    """Two independent renders whose noise variance is a quarter of the converged render's squared error
    (about the oracle's at tiny's samples): the plain PSNR of their mean loses about 0.5 dB to the noise;
    the decorrelated estimate matches its exact expectation (Gauss-Hermite quadrature of the tone map over
    the noise) within 4 standard errors, and that expectation the converged render's PSNR within 0.05 dB
    (the tone map's curvature term, which grows with the noise: 0.11 dB where the variance equals the
    squared error)."""
    from pipeline.metrics.image import tonemap

    g = torch.Generator().manual_seed(3)
    target = torch.rand(20000, 3, generator=g, dtype=torch.float64) * 4 + 0.05
    converged = target * (1 + 0.1 * torch.randn(target.shape, generator=g, dtype=torch.float64))
    sigma = 0.05 * target
    half_a, half_b = (converged + sigma * torch.randn(target.shape, generator=g, dtype=torch.float64) for _ in "ab")
    scale = 1.0
    s = torch.full((len(target),), scale, dtype=torch.float64)
    ref = tonemap(target, s)
    truth_mse = float(((tonemap(converged, s) - ref) ** 2).mean())
    nodes, weights = np.polynomial.hermite_e.hermegauss(40)  # E over a standard normal
    weights = torch.as_tensor(weights / weights.sum())
    expected_t = sum(w * tonemap(converged + float(z) * sigma, s) for z, w in zip(nodes, weights, strict=True))
    expected_mse = float(((expected_t - ref) ** 2).mean())
    product = (tonemap(half_a, s) - ref) * (tonemap(half_b, s) - ref)
    se = float(product.std() / np.sqrt(product.numel()))
    estimate = psnr_decorrelated(half_a, half_b, target, scale)
    assert abs(10 ** (-estimate / 10) - expected_mse) < 4 * se
    assert -10 * np.log10(expected_mse) == pytest.approx(-10 * np.log10(truth_mse), abs=0.05)
    plain = case_scores(
        (half_a + half_b) / 2, target, torch.zeros(200, 100, 3, dtype=torch.float64), torch.arange(20000), scale
    )
    assert -10 * np.log10(truth_mse) - plain["psnr"] > 0.3
    assert psnr_decorrelated(target, target, target, scale) == pytest.approx(120.0)


def test_extrapolated_psnr_removes_the_tone_maps_bias_where_the_noise_is_large():
    """Four independent quarter renders whose halves' noise variance is 4x the converged render's squared
    error (noisier than the oracle's mean pixel at tiny's samples): the decorrelated product of the halves
    is biased by the tone map's curvature (its exact expectation, by Gauss-Hermite quadrature, more than
    0.4 dB below the converged render's PSNR); each half extrapolated from its quarters is not (within
    0.1 dB), and the estimate matches its own exact expectation within 4 standard errors."""
    from pipeline.metrics.image import tonemap

    g = torch.Generator().manual_seed(5)
    target = torch.rand(20000, 3, generator=g, dtype=torch.float64) * 4 + 0.05
    converged = target * (1 + 0.1 * torch.randn(target.shape, generator=g, dtype=torch.float64))
    sigma_quarter = 0.2 * np.sqrt(2) * target  # halves: 0.2 x target, twice the converged error's 0.1
    quarters = [converged + sigma_quarter * torch.randn(target.shape, generator=g, dtype=torch.float64) for _ in "abcd"]
    s = torch.full((len(target),), 1.0, dtype=torch.float64)
    ref = tonemap(target, s)
    truth = -10 * np.log10(float(((tonemap(converged, s) - ref) ** 2).mean()))
    nodes, weights = np.polynomial.hermite_e.hermegauss(40)
    weights = torch.as_tensor(weights / weights.sum())

    def expected_t(sigma):  # E T(converged + sigma z), z standard normal
        return sum(w * tonemap(converged + float(z) * sigma, s) for z, w in zip(nodes, weights, strict=True))

    half_t, quarter_t = expected_t(sigma_quarter / np.sqrt(2)), expected_t(sigma_quarter)
    expected_decorrelated = -10 * np.log10(float(((half_t - ref) ** 2).mean()))
    expected_extrapolated_mse = float(((2 * half_t - quarter_t - ref) ** 2).mean())
    assert truth - expected_decorrelated > 0.4
    assert -10 * np.log10(expected_extrapolated_mse) == pytest.approx(truth, abs=0.1)

    extrapolated, decorrelated = psnr_extrapolated(quarters, target, 1.0)
    assert decorrelated == pytest.approx(expected_decorrelated, abs=0.15)
    tq = [tonemap(q, s) for q in quarters]
    per_pixel = torch.stack(  # the estimate's terms per pixel (mean over the three splits), for its spread
        [
            (2 * tonemap((quarters[a] + quarters[b]) / 2, s) - (tq[a] + tq[b]) / 2 - ref)
            * (2 * tonemap((quarters[c] + quarters[d]) / 2, s) - (tq[c] + tq[d]) / 2 - ref)
            for (a, b), (c, d) in (((0, 1), (2, 3)), ((0, 2), (1, 3)), ((0, 3), (1, 2)))
        ]
    ).mean(0)
    se = float(per_pixel.std() / np.sqrt(per_pixel.numel()))
    assert abs(10 ** (-extrapolated / 10) - expected_extrapolated_mse) < 4 * se
    with pytest.raises(ValueError, match="4 independent renders"):
        psnr_extrapolated(quarters[:2], target, 1.0)
