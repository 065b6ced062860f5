"""Lighting errors (docs/design.md, section 6.2), one definition each, on exposure-normalised radiance.

Every function takes radiances pred, target (M, 3) and, where it says so, scale (M,): the mean of the
image each sample belongs to. Dividing by it makes the errors exposure-invariant (a room lit 10x brighter
and photographed 10x darker scores the same).
"""

from __future__ import annotations

import torch

RELMSE_EPS = 1e-2  # in units of the image mean squared: 1 % of the image's mean radiance, squared


def relmse_terms(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor | None = None, eps: float = RELMSE_EPS):
    """Per-element relative squared error (L^ - L)^2 / (L^2 + eps) of L = radiance / scale (scale None:
    absolute units). Same shape as pred. The form rendering uses to compare images with a reference;
    per element, so a dark texel lit wrongly counts as much as a lamp, and a prediction of 0 scores at
    most 1 while an over-estimate is unbounded (relMSE favours dark predictions)."""
    if scale is not None:
        s = scale.reshape(-1, *([1] * (pred.dim() - 1)))
        pred, target = pred / s, target / s
    return (pred - target) ** 2 / (target**2 + eps)


def relmse(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor | None = None, eps: float = RELMSE_EPS):
    """Rendering's relMSE: the mean of `relmse_terms` (a 0-dim tensor)."""
    return relmse_terms(pred, target, scale, eps).mean()


def normalised_mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """sum((L^ - L)^2) / sum(L^2): the squared error relative to the light's energy. Dominated by the few
    brightest texels (a sun or lamp texel can hold most of a probe's energy), so it mostly asks whether
    the light sources were found. Scale-free, so it needs no exposure normalisation."""
    return ((pred - target) ** 2).sum() / (target**2).sum().clamp(min=1e-12)


def log_l1(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """mean |log(1 + L^/s) - log(1 + L/s)| with s (M,) each sample's image mean: a relative (log) error
    whatever the scene's brightness (on absolute radiance of about 0.05 log1p is nearly linear and this
    would be a plain L1). Negative radiance counts as 0."""
    s = scale[:, None]
    return (torch.log1p(pred.clamp(min=0) / s) - torch.log1p(target.clamp(min=0) / s)).abs().mean()


def ray_classes(hit: torch.Tensor, u: torch.Tensor) -> dict[str, torch.Tensor]:
    """Masks (N,) of the three kinds of LightNet ray: `hit` (SSRT hit, u < 0.5: mostly the local branch),
    `uncertain` (hit, u >= 0.5: mostly the out-of-view branch) and `miss` (left the screen: out-of-view
    only). Errors are reported per class to show which branch an error comes from."""
    return {"hit": hit & (u < 0.5), "uncertain": hit & (u >= 0.5), "miss": ~hit}


def light_errors(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor) -> dict[str, float]:
    """{"light_relmse", "light_nmse", "light_log_l1"} of one set of (M, 3) radiances."""
    return {
        "light_relmse": float(relmse(pred, target, scale)),
        "light_nmse": float(normalised_mse(pred, target)),
        "light_log_l1": float(log_l1(pred, target, scale)),
    }
