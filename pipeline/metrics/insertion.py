"""Scores of insertion and editing cases (docs/design.md, section 6.3); their intervals come from metrics.bootstrap.

Every score is on the case's pixels only (the object or edit mask), against the Mitsuba render, after
one tone map for all rows (`metrics.image.tonemap` with the photo's mean): PSNR and SSIM (the SSIM map of
the two composited photos averaged over the mask), and the HDR log-L1 on radiance in units of the
photo's mean.
"""

from __future__ import annotations

import numpy as np
import torch

from pipeline.metrics.image import psnr_tonemapped, ssim_tonemapped, tonemap
from pipeline.metrics.lighting import log_l1

SCORES = ("psnr", "ssim", "log_l1")
HIGHER_IS_BETTER = {"psnr": True, "ssim": True, "log_l1": False}


def case_scores(
    pred: torch.Tensor, target: torch.Tensor, photo: torch.Tensor, pixels: torch.Tensor, scale: float
) -> dict[str, float]:
    """pred, target (M, 3) HDR radiance at flat pixels (M,) of photo (H, W, 3); scale the photo's mean."""
    s = torch.full((len(pred),), float(scale), dtype=torch.float64)
    pred64, target64 = pred.double(), target.double()
    flat = photo.double().reshape(-1, 3)
    a, b = flat.clone(), flat.clone()
    a[pixels], b[pixels] = pred64, target64
    mask = np.zeros(len(flat), bool)
    mask[pixels.numpy()] = True
    H, W = photo.shape[:2]
    return {
        "psnr": float(psnr_tonemapped(pred64, target64, s)),
        "ssim": ssim_tonemapped(a.reshape(H, W, 3).numpy(), b.reshape(H, W, 3).numpy(), scale, mask.reshape(H, W)),
        "log_l1": float(log_l1(pred64, target64, s)),
    }


def psnr_decorrelated(half_a: torch.Tensor, half_b: torch.Tensor, target: torch.Tensor, scale: float) -> float:
    """PSNR (dB, peak 1, capped at 120) of the converged render, estimated from two independent renders
    half_a, half_b (M, 3) of the same pixels (HDR radiance; independent samples, same expectation) against
    target (M, 3), with `tonemap` at the photo's mean `scale`.

    The squared error of one noisy render is the converged render's plus the render's variance; the product
    of the two renders' errors, mean of (T(a) - T(g)) (T(b) - T(g)), has the converged render's squared
    error as its expectation, the variance gone (a and b independent). The tone map's curvature leaves a
    term of the variance times the error itself, small where the error is (`psnr_extrapolated` removes
    it). Averaged over a case's pixels the product is positive; where it is not (an exact match within
    noise), the cap applies."""
    s = torch.full((len(target),), float(scale), dtype=torch.float64)
    ref = tonemap(target.double(), s)
    return _psnr(_error_product(tonemap(half_a.double(), s), tonemap(half_b.double(), s), ref))


def psnr_extrapolated(quarters: list[torch.Tensor], target: torch.Tensor, scale: float) -> tuple[float, float]:
    """(extrapolated, decorrelated) PSNR (dB, capped at 120) of the converged render from four independent
    renders `quarters` (each (M, 3), a quarter of the samples) of the same pixels against target (M, 3).

    On a render of n samples the tone map's expectation is off by its curvature times the variance,
    E T(a_n) = T(mu) + c / n + O(1/n^2): the decorrelated product of two halves is biased by that term
    times the error (and its square). Each half is extrapolated to infinite samples from its two quarters
    q1, q2 (Richardson in 1/n): 2 T((q1 + q2) / 2) - (T(q1) + T(q2)) / 2 has expectation T(mu) + O(1/n^2).
    The product of the two halves' extrapolated errors against T(g) (independent: disjoint quarters),
    averaged over the three ways to split the quarters in two, estimates the converged render's squared
    error without the first-order term, at no cost in samples. The decorrelated PSNR is that of the
    products of the halves' plain means (`psnr_decorrelated`) over the same splits."""
    if len(quarters) != 4:
        raise ValueError(f"psnr_extrapolated takes 4 independent renders, got {len(quarters)}")
    s = torch.full((len(target),), float(scale), dtype=torch.float64)
    ref = tonemap(target.double(), s)
    q = [x.double() for x in quarters]
    tq = [tonemap(x, s) for x in q]
    extrapolated, decorrelated = [], []
    for (a, b), (c, e) in (((0, 1), (2, 3)), ((0, 2), (1, 3)), ((0, 3), (1, 2))):
        half_1, half_2 = tonemap((q[a] + q[b]) / 2, s), tonemap((q[c] + q[e]) / 2, s)
        ext_1, ext_2 = 2 * half_1 - (tq[a] + tq[b]) / 2, 2 * half_2 - (tq[c] + tq[e]) / 2
        extrapolated.append(_error_product(ext_1, ext_2, ref))
        decorrelated.append(_error_product(half_1, half_2, ref))
    return _psnr(float(np.mean(extrapolated))), _psnr(float(np.mean(decorrelated)))


def _error_product(a: torch.Tensor, b: torch.Tensor, ref: torch.Tensor) -> float:
    """Mean over pixels and channels of (a - ref) (b - ref): two independent estimates' errors, all (M, 3)
    tone-mapped."""
    return float(((a - ref) * (b - ref)).mean())


def _psnr(mse: float) -> float:
    return float(-10 * np.log10(max(mse, 1e-12)))


def noise_floor_psnr(target: torch.Tensor, stderr: torch.Tensor, scale: float) -> float:
    """The PSNR (dB) an exact render would be expected to score against a ground truth (M, 3) whose
    pixels carry standard errors stderr (M, 3): the truth's own noise through the tone map's slope,
    mean of (tonemap'(L) se)^2, with tonemap(L) = y / (1 + y), y = L / (2 scale)."""
    y = target.double().clamp(min=0) / (2 * scale)
    slope = 1 / (2 * scale * (1 + y) ** 2)
    mse = ((slope * stderr.double()) ** 2).mean().clamp(min=1e-12)
    return float(-10 * torch.log10(mse))
