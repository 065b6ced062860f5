"""Synthetic-test metrics (docs/design.md, section 6.1), per image, over the valid mask.

All inputs are (B, C, H, W) tensors with a (B, 1, H, W) bool mask; every function returns (B,) float64
per-image values, NaN where an image has no valid pixel (callers average over finite values and count
the rest). Depth is z-depth in metres (0 = no surface) and only pixels with positive ground truth count.
"""

from __future__ import annotations

import torch


def _masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of x (B, C, H, W) over mask (B, 1, H, W) and channels -> (B,); NaN where the mask is empty."""
    m = mask.expand_as(x).to(x.dtype)
    n = m.sum(dim=(1, 2, 3))
    return torch.where(n > 0, (x * m).sum(dim=(1, 2, 3)) / n.clamp(min=1), torch.full_like(n, float("nan")))


def ls_scale(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-image least-squares scale s = argmin_s sum_mask (s pred - gt)^2 = <pred, gt> / <pred, pred>,
    (B,) -> shaped (B, 1, 1, 1) for broadcasting; 1 where the mask is empty or pred is 0."""
    m = mask.expand_as(pred).to(pred.dtype)
    num = (pred * gt * m).sum(dim=(1, 2, 3))
    den = (pred * pred * m).sum(dim=(1, 2, 3))
    return torch.where(den > 0, num / den.clamp(min=1e-20), torch.ones_like(den)).view(-1, 1, 1, 1)


def depth_mask(gt_depth: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return mask & torch.isfinite(gt_depth) & (gt_depth > 0)


def albedo_mse(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """MSE of albedo after one least-squares scale per image (albedo from one image is known up to scale)."""
    pred, gt = pred.double(), gt.double()
    return _masked_mean((ls_scale(pred, gt, mask) * pred - gt) ** 2, mask)


def normal_angle(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean angle in degrees between predicted and ground-truth normals (both renormalised)."""
    p = torch.nn.functional.normalize(pred.double(), dim=1, eps=1e-12)
    g = torch.nn.functional.normalize(gt.double(), dim=1, eps=1e-12)
    cos = (p * g).sum(1, keepdim=True).clamp(-1, 1)
    return _masked_mean(torch.rad2deg(torch.acos(cos)), mask)


def channel_mse(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return _masked_mean((pred.double() - gt.double()) ** 2, mask)


def depth_log_mse(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """MSE of log(d + 1) after a least-squares scale of the prediction to the ground truth (metres)."""
    m = depth_mask(gt, mask)
    pred, gt = pred.double().clamp(min=0), torch.where(m, gt.double(), torch.zeros_like(gt, dtype=torch.float64))
    return _masked_mean((torch.log1p(ls_scale(pred, gt, m) * pred) - torch.log1p(gt)) ** 2, m)


def material_metrics(pred: dict, batch: dict) -> dict[str, torch.Tensor]:
    """All synthetic-test map metrics for MaterialNet-style predictions (dict with albedo, normal,
    material, depth) against a collated batch; each (B,) per image."""
    mask = batch["mask"]
    return {
        "albedo_mse": albedo_mse(pred["albedo"], batch["albedo"], mask),
        "normal_angle_deg": normal_angle(pred["normal"], batch["normal"], mask),
        "roughness_mse": channel_mse(pred["material"][:, :1], batch["material"][:, :1], mask),
        "metallic_mse": channel_mse(pred["material"][:, 1:], batch["material"][:, 1:], mask),
        "depth_log_mse": depth_log_mse(pred["depth"], batch["depth"], mask),
    }
