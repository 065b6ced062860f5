"""Scores of insertion and editing cases (DESIGN.md section 6) and paired bootstrap intervals.

Every score is on the case's pixels only (the object or edit mask), against the Mitsuba render, after
one tone map for all rows (`metrics.image.tonemap` with the photo's mean): PSNR and SSIM (the SSIM map of
the two composited photos averaged over the mask), and the HDR log-L1 on radiance in units of the
photo's mean.
"""

from __future__ import annotations

import numpy as np
import torch

from pipeline.metrics.image import psnr_tonemapped, ssim_tonemapped
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


def noise_floor_psnr(target: torch.Tensor, stderr: torch.Tensor, scale: float) -> float:
    """The PSNR (dB) an exact render would be expected to score against a ground truth (M, 3) whose
    pixels carry standard errors stderr (M, 3): the truth's own noise through the tone map's slope,
    mean of (tonemap'(L) se)^2, with tonemap(L) = y / (1 + y), y = L / (2 scale)."""
    y = target.double().clamp(min=0) / (2 * scale)
    slope = 1 / (2 * scale * (1 + y) ** 2)
    mse = ((slope * stderr.double()) ** 2).mean().clamp(min=1e-12)
    return float(-10 * torch.log10(mse))


def paired_bootstrap(diff, resamples: int = 2000, seed: int = 0, level: float = 0.95, groups=None) -> dict[str, float]:
    """Mean of paired per-case differences (n,) and its percentile bootstrap interval. With `groups` (n,)
    (the view each case comes from) whole groups are resampled with replacement, since cases of one view
    share its photo, its predictions and so their errors; else single cases. Returns {"diff", "lo", "hi",
    "n"}; with fewer than two groups there is no spread to resample and lo, hi are NaN."""
    d = np.asarray(diff, np.float64)
    if d.ndim != 1 or not len(d):
        raise ValueError(f"paired_bootstrap: need a non-empty 1-D array of differences, got shape {d.shape}")
    if not np.isfinite(d).all():
        raise ValueError("paired_bootstrap: differences hold NaN/inf")
    labels = np.arange(len(d)) if groups is None else np.unique(np.asarray(groups), return_inverse=True)[1]
    if len(labels) != len(d):
        raise ValueError(f"paired_bootstrap: {len(labels)} group labels for {len(d)} differences")
    k = int(labels.max()) + 1
    out = {"diff": float(d.mean()), "n": float(len(d))}
    if k < 2:
        return {**out, "lo": float("nan"), "hi": float("nan")}
    sums, counts = np.bincount(labels, d, k), np.bincount(labels, minlength=k).astype(np.float64)
    draws = np.random.default_rng(seed).integers(0, k, size=(resamples, k))
    means = sums[draws].sum(1) / counts[draws].sum(1)
    tail = (1 - level) / 2 * 100
    lo, hi = np.percentile(means, [tail, 100 - tail])
    return {**out, "lo": float(lo), "hi": float(hi)}
