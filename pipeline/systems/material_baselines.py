"""Trivial MaterialNet baselines: what a model that learned nothing would also reach.

Fitted on the training split (means over valid pixels), evaluated on the same views as the model with
the same metrics. Each baseline predicts only the maps it is named for.
"""

from __future__ import annotations

import torch

from pipeline.metrics.synthetic import albedo_mse, channel_mse, depth_log_mse, normal_angle

# baseline name -> the metrics (maps) it competes on
BASELINE_MAPS = {
    "mean_albedo": ("albedo_mse",),
    "image_as_albedo": ("albedo_mse",),
    "camera_facing_normal": ("normal_angle_deg",),
    "mean_material": ("roughness_mse", "metallic_mse"),
    "constant_depth": ("depth_log_mse",),
}


class MaterialBaselines:
    """Training-split statistics: mean albedo (3,), mean roughness and metallic (2,)."""

    def __init__(self, mean_albedo: torch.Tensor, mean_material: torch.Tensor):
        self.mean_albedo = mean_albedo.double().view(1, 3, 1, 1)
        self.mean_material = mean_material.double().view(1, 2, 1, 1)

    @classmethod
    def fit(cls, batches) -> MaterialBaselines:
        """batches: iterable of collated batches (albedo, material, mask). Raises on an empty split."""
        a_sum, m_sum, n = torch.zeros(3, dtype=torch.float64), torch.zeros(2, dtype=torch.float64), 0.0
        for b in batches:
            mask = b["mask"].double()
            a_sum += (b["albedo"].double() * mask).sum(dim=(0, 2, 3))
            m_sum += (b["material"].double() * mask).sum(dim=(0, 2, 3))
            n += float(mask.sum())
        if n == 0:
            raise ValueError("baselines: the training split has no valid pixels")
        return cls(a_sum / n, m_sum / n)

    def metrics(self, batch: dict) -> dict[str, torch.Tensor]:
        """Per-image (B,) metrics of every baseline, keyed `<baseline>/<metric>`."""
        mask, im = batch["mask"], batch["im"].double()
        B, _, H, W = im.shape
        ones = torch.ones(B, 1, H, W, dtype=torch.float64)
        facing = torch.cat([0 * ones, 0 * ones, ones], 1)  # view space: +z points towards the camera
        mat = self.mean_material.expand(B, 2, H, W)
        return {
            "mean_albedo/albedo_mse": albedo_mse(self.mean_albedo.expand(B, 3, H, W), batch["albedo"], mask),
            "image_as_albedo/albedo_mse": albedo_mse(im, batch["albedo"], mask),
            "camera_facing_normal/normal_angle_deg": normal_angle(facing, batch["normal"], mask),
            "mean_material/roughness_mse": channel_mse(mat[:, :1], batch["material"][:, :1], mask),
            "mean_material/metallic_mse": channel_mse(mat[:, 1:], batch["material"][:, 1:], mask),
            "constant_depth/depth_log_mse": depth_log_mse(ones, batch["depth"], mask),
        }


def accuracy_gate(model: dict[str, float], baselines: dict[str, float], margin: float = 0.2) -> dict[str, float]:
    """For every (baseline, map): the model's error relative to the baseline's (lower is better) and
    whether it is at least `margin` lower. model: {metric: value}; baselines: {"<name>/<metric>": value}.
    Returns flat entries `gate/<name>/<metric>` (ratio) and `gate/passed` (1.0 or 0.0)."""
    out, passed = {}, True
    for name, metrics in BASELINE_MAPS.items():
        for metric in metrics:
            ratio = model[metric] / max(baselines[f"{name}/{metric}"], 1e-20)
            out[f"gate/{name}/{metric}"] = ratio
            passed &= ratio <= 1.0 - margin
    out["gate/passed"] = float(passed)
    return out
