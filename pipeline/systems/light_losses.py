"""LightNet training losses (docs/design.md, section 5) on HDR radiance (M, 3) of the step's probe texels, in
units of each sample's image mean (scale (M,)): the light loss `lighting.light_loss` picks from
`LIGHT_LOSSES`, and the normalised-MSE term weighted by `lighting.nmse_weight`.
"""

from __future__ import annotations

import torch

from pipeline.metrics.lighting import log_l1, normalised_mse


def hdr_relative_loss(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor, eps: float = 1e-3):
    """LightNet's HDR light loss: mean(((L^ - L) / (sg(L^) + eps))^2) of radiance in units of each
    sample's image mean, scale (M,) (RawNeRF's relative MSE, no clipping). In those units the networks
    predict, and an absolute eps would weigh a dim room's texels unlike a bright room's. Its fixed point
    is the conditional mean; it is a loss, not the reported `metrics.lighting.relmse`."""
    pred, target = pred / scale[:, None], target / scale[:, None]
    return (((pred - target) / (pred.detach() + eps)) ** 2).mean()


def hdr_log_l1_loss(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor):
    """mean |log(1 + L^/s) - log(1 + L/s)| of radiance (M, 3) in units of each sample's image mean s (M,):
    the reported light log-L1 as a loss. A lamp 100x the image mean and a wall at half of it both count
    (about 4.6 and 0.4 in this space), and one huge texel cannot dominate a step as it does the relative
    MSE. Its fixed point is the conditional median: the energy the median leaves out is asked for by the
    re-rendering loss, which integrates the light as the image does."""
    return log_l1(pred, target, scale)


LIGHT_LOSSES = {"relative_mse": hdr_relative_loss, "log_l1": hdr_log_l1_loss}  # lighting.light_loss


def light_nmse_loss(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """sum (L^ - L)^2 / sum L^2 over the step's texels, radiance (M, 3) in units of each sample's image
    mean s (M,): the reported normalised MSE as a loss term (`lighting.nmse_weight`). The brightest
    texels (lamps, sun) carry it, so it asks where each probe's energy is, which the log-L1 loss, whose
    fixed point is the median, does not; per texel its fixed point is the conditional mean."""
    s = scale[:, None]
    return normalised_mse(pred / s, target / s)
