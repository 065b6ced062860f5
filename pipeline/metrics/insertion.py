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
    term of the variance times the error itself, small where the error is. Averaged over a case's pixels
    the product is positive; where it is not (an exact match within noise), the cap applies."""
    s = torch.full((len(target),), float(scale), dtype=torch.float64)
    ref = tonemap(target.double(), s)
    product = (tonemap(half_a.double(), s) - ref) * (tonemap(half_b.double(), s) - ref)
    return float(-10 * torch.log10(product.mean().clamp(min=1e-12)))


def noise_floor_psnr(target: torch.Tensor, stderr: torch.Tensor, scale: float) -> float:
    """The PSNR (dB) an exact render would be expected to score against a ground truth (M, 3) whose
    pixels carry standard errors stderr (M, 3): the truth's own noise through the tone map's slope,
    mean of (tonemap'(L) se)^2, with tonemap(L) = y / (1 + y), y = L / (2 scale)."""
    y = target.double().clamp(min=0) / (2 * scale)
    slope = 1 / (2 * scale * (1 + y) ** 2)
    mse = ((slope * stderr.double()) ** 2).mean().clamp(min=1e-12)
    return float(-10 * torch.log10(mse))
