"""Image comparisons of HDR renders (docs/design.md, section 6.3): one tone map, PSNR and SSIM on it.

The tone map is x / (2 s), then Reinhard x / (1 + x), with s the image mean: values lie in [0, 1)
whatever the exposure, and the same map serves every row of a comparison.
"""

from __future__ import annotations

import numpy as np
import torch


def tonemap(x: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """x (N, 3) HDR radiance, scale (N,) image means -> (N, 3) in [0, 1). Negative values count as 0."""
    x = x.clamp(min=0) / (2 * scale[:, None])
    return x / (1 + x)


def psnr_tonemapped(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """PSNR (dB, peak 1) of (N, 3) HDR radiances after `tonemap`; 0-dim tensor. An exact match is capped
    at 120 dB (MSE floored at 1e-12) rather than infinite."""
    mse = ((tonemap(pred, scale) - tonemap(target, scale)) ** 2).mean().clamp(min=1e-12)
    return -10 * torch.log10(mse)


def ssim_tonemapped(pred: np.ndarray, target: np.ndarray, scale: float, mask: np.ndarray | None = None) -> float:
    """SSIM (scikit-image, Gaussian window sigma 1.5, data range 1) of two (H, W, 3) HDR images after
    `tonemap` with the image mean `scale`; with a boolean mask (H, W), the mean of the SSIM map over it."""
    from skimage.metrics import structural_similarity

    def tm(x: np.ndarray) -> np.ndarray:  # `tonemap` on an image's pixels, in float64
        flat = torch.from_numpy(np.asarray(x, np.float64)).reshape(-1, 3)
        return tonemap(flat, torch.full((len(flat),), float(scale), dtype=torch.float64)).reshape(x.shape).numpy()

    _, full = structural_similarity(
        tm(pred), tm(target), channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5, full=True
    )
    full = full.mean(-1)
    if mask is None:
        return float(full.mean())
    if not mask.any():
        raise ValueError("ssim_tonemapped: the mask selects no pixel")
    return float(full[mask].mean())
