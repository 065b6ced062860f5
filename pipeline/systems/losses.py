"""MaterialNet training losses (DESIGN.md section 5), masked by the dataset's valid-pixel mask.

Every term is a mean over valid pixels of the batch (masked pixels contribute nothing, not even to the
denominator). Shapes: predictions and ground truth (B, C, H, W), mask (B, 1, H, W) bool.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from pipeline.metrics.synthetic import depth_mask, ls_scale


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of x over the pixels (and channels) where mask is set; 0 (with a graph) if none is."""
    m = mask.expand_as(x).to(x.dtype)
    return (x * m).sum() / m.sum().clamp(min=1.0)


def albedo_loss(pred, gt, mask):
    """L2 between log1p albedos: relative errors on dark albedo count as much as on bright."""
    return masked_mean((torch.log1p(pred) - torch.log1p(gt)) ** 2, mask)


def normal_loss(pred, gt, mask):
    """1 - cos of the angle between predicted and ground-truth unit normals."""
    return masked_mean(1.0 - (pred * gt).sum(1, keepdim=True), mask)


METALLIC_LOSSES = ("l2", "bce")


def material_loss(pred, gt, mask, metallic: str = "l2"):
    """Roughness and metallic, pred/gt (B, 2, H, W) in [0, 1]: L2 on both (`metallic="l2"`), or L2 on
    roughness and binary cross-entropy on metallic (`"bce"`), averaged over the two channels.

    Metallic is nearly binary and mostly 0. Through the sigmoid output, L2's gradient on a pixel predicted
    near 0 carries a factor p(1 - p), so a confident "not metal" is almost never corrected; BCE's gradient
    on the logit is p - y. Both are proper scores: their minimiser is the same conditional mean."""
    if metallic not in METALLIC_LOSSES:
        raise ValueError(f"loss.metallic={metallic!r}: choose one of {METALLIC_LOSSES}")
    if metallic == "l2":
        return masked_mean((pred - gt) ** 2, mask)
    rough = masked_mean((pred[:, :1] - gt[:, :1]) ** 2, mask)
    p, y = pred[:, 1:].clamp(1e-6, 1 - 1e-6), gt[:, 1:]
    bce = masked_mean(-(y * torch.log(p) + (1 - y) * torch.log1p(-p)), mask)
    return 0.5 * (rough + bce)


def depth_loss(pred, gt, mask):
    """L2 on log(d + 1) after the per-image least-squares scale of the prediction to the ground truth
    (metres). The scale is detached: it is the closed-form optimum, so its gradient adds nothing at
    the optimum and detaching keeps the loss from collapsing the prediction's magnitude."""
    m = depth_mask(gt, mask)
    gt = torch.where(m, gt, torch.zeros_like(gt))
    s = ls_scale(pred.detach(), gt, m)
    return masked_mean((torch.log1p(s * pred) - torch.log1p(gt)) ** 2, m)


class VGGPerceptual(nn.Module):
    """L1 between VGG16 features (relu1_2, relu2_2, relu3_3) of prediction and ground truth, both masked.
    Needs ImageNet weights from `weights_path` (a torchvision vgg16 state dict); frozen."""

    LAYERS = (3, 8, 15)

    def __init__(self, weights_path: str | Path):
        super().__init__()
        from torchvision.models import vgg16

        path = Path(weights_path)
        if not path.is_file():
            raise FileNotFoundError(f"loss.perceptual_weights={path}: no such file")
        net = vgg16(weights=None)
        net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
        self.features = net.features[: self.LAYERS[-1] + 1].eval().requires_grad_(False)
        self.register_buffer("mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1))

    def forward(self, pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        m = mask.to(pred.dtype)
        x, y = (pred * m - self.mean) / self.std, (gt * m - self.mean) / self.std
        loss = pred.new_zeros(())
        for i, layer in enumerate(self.features):
            x, y = layer(x), layer(y)
            if i in self.LAYERS:
                loss = loss + (x - y).abs().mean()
        return loss


class MaterialLoss(nn.Module):
    """Weighted sum of the four map losses (+ perceptual terms on albedo and normal when VGG16 weights are
    given). forward(pred, batch) -> (total, {term: value})."""

    def __init__(
        self,
        albedo: float = 1.0,
        normal: float = 1.0,
        material: float = 1.0,
        depth: float = 1.0,
        perceptual: float = 0.0,
        perceptual_weights: str | None = None,
        metallic: str = "l2",
    ):
        super().__init__()
        if metallic not in METALLIC_LOSSES:
            raise ValueError(f"loss.metallic={metallic!r}: choose one of {METALLIC_LOSSES}")
        self.metallic = metallic
        self.weights = {"albedo": albedo, "normal": normal, "material": material, "depth": depth}
        for k, w in self.weights.items():
            if not (w >= 0):
                raise ValueError(f"loss.{k}={w}: weights must be >= 0")
        self.perceptual_weight = float(perceptual)
        self.vgg = VGGPerceptual(perceptual_weights) if perceptual_weights and perceptual > 0 else None

    @property
    def perceptual_on(self) -> bool:
        return self.vgg is not None

    def forward(self, pred: dict, batch: dict) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        mask = batch["mask"]
        terms = {
            "albedo": albedo_loss(pred["albedo"], batch["albedo"], mask),
            "normal": normal_loss(pred["normal"], batch["normal"], mask),
            "material": material_loss(pred["material"], batch["material"], mask, self.metallic),
            "depth": depth_loss(pred["depth"], batch["depth"], mask),
        }
        total = sum(self.weights[k] * v for k, v in terms.items())
        if self.vgg is not None:
            terms["perceptual"] = self.vgg(pred["albedo"], batch["albedo"], mask) + self.vgg(
                pred["normal"] * 0.5 + 0.5, batch["normal"] * 0.5 + 0.5, mask
            )
            total = total + self.perceptual_weight * terms["perceptual"]
        return total, terms


def ranking_loss(albedo: torch.Tensor, comparisons: list[dict], margin: float = 0.5) -> torch.Tensor:
    """Li et al. 2020's ordinal loss on IIW judgements, on r = log(mean_c albedo + 0.001) at each point:
    equal pairs w (r1 - r2)^2; "point k darker" pairs w max(0, r_darker - r_lighter + margin)^2; the
    weighted mean over all comparisons of the batch. albedo (B, 3, H, W); comparisons per image (see
    pipeline.data.benchmarks.comparisons_tensor)."""
    grey = torch.log(albedo.mean(1) + 1e-3)  # (B, H, W)
    total, weight = albedo.new_zeros(()), albedo.new_zeros(())
    for b, c in enumerate(comparisons):
        if not len(c["label"]):
            continue
        r1 = grey[b, c["p1"][:, 0], c["p1"][:, 1]]
        r2 = grey[b, c["p2"][:, 0], c["p2"][:, 1]]
        w = c["weight"].to(albedo)
        label = c["label"].to(albedo.device)
        darker_first = torch.relu(r1 - r2 + margin) ** 2
        darker_second = torch.relu(r2 - r1 + margin) ** 2
        equal = (r1 - r2) ** 2
        per = torch.where(label == 0, darker_first, torch.where(label == 1, darker_second, equal))
        total = total + (w * per).sum()
        weight = weight + w.sum()
    return total / weight.clamp(min=1e-12)


def hdr_relative_loss(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor, eps: float = 1e-3):
    """LightNet's HDR light loss: mean(((L^ - L) / (sg(L^) + eps))^2) of radiance in units of each
    sample's image mean, scale (M,) (RawNeRF's relative MSE, no clipping). In those units the networks
    predict, and an absolute eps would weigh a dim room's texels unlike a bright room's. Its fixed point
    is the conditional mean; it is a loss, not the reported `metrics.lighting.relmse`."""
    pred, target = pred / scale[:, None], target / scale[:, None]
    return (((pred - target) / (pred.detach() + eps)) ** 2).mean()
