"""MaterialNet training losses (docs/design.md, section 5), masked by the dataset's valid-pixel mask.

Every term is a mean over valid pixels of the batch (masked pixels contribute nothing, not even to the
denominator). Shapes: predictions and ground truth (B, C, H, W), mask (B, 1, H, W) bool.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn
from torch.nn import functional as F

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


DEPTH_UNITS = ("metres", "max")


def depth_loss(pred, gt, mask, units: str = "metres"):
    """L2 on log(d + 1) after the per-image least-squares scale of the prediction to the ground truth.
    units: `metres` (gt as it is) or `max` (gt divided by its per-image maximum over the mask, as the
    released MGNet trains). The scale is detached: it is the closed-form optimum, so its gradient adds
    nothing at the optimum and detaching keeps the loss from collapsing the prediction's magnitude."""
    if units not in DEPTH_UNITS:
        raise ValueError(f"loss.depth_units={units!r}: choose one of {DEPTH_UNITS}")
    m = depth_mask(gt, mask)
    gt = torch.where(m, gt, torch.zeros_like(gt))
    if units == "max":
        gt = gt / gt.flatten(1).amax(1).clamp(min=1e-6).view(-1, 1, 1, 1)
    s = ls_scale(pred.detach(), gt, m)
    return masked_mean((torch.log1p(s * pred) - torch.log1p(gt)) ** 2, m)


VGG_LAYERS = {"relu1_2": 3, "relu2_2": 8, "relu3_3": 15, "relu4_3": 22}
PERCEPTUAL_DISTANCES = ("l1", "l2_masked")


class VGGPerceptual(nn.Module):
    """Distance between VGG16 features of prediction and ground truth (B, 3, H, W), both multiplied by the
    mask first. Needs ImageNet weights from `weights_path` (a torchvision vgg16 state dict); frozen.

    distance `l1`: mean |fx - fy| per layer, summed over `layers`; `l2_masked` (the released MGNet):
    sum (fx - fy)^2 m / sum m per layer, with the mask m average-pooled to the layer's resolution.
    imagenet_norm: standardise inputs with the ImageNet mean and std (the released code does not)."""

    def __init__(
        self,
        weights_path: str | Path,
        layers: tuple[str, ...] = ("relu1_2", "relu2_2", "relu3_3"),
        distance: str = "l1",
        imagenet_norm: bool = True,
    ):
        super().__init__()
        from torchvision.models import vgg16

        unknown = [name for name in layers if name not in VGG_LAYERS]
        if unknown or not layers:
            raise ValueError(f"loss.perceptual_layers={list(layers)}: choose from {list(VGG_LAYERS)}")
        if distance not in PERCEPTUAL_DISTANCES:
            raise ValueError(f"loss.perceptual_distance={distance!r}: choose one of {PERCEPTUAL_DISTANCES}")
        path = Path(weights_path)
        if not path.is_file():
            raise FileNotFoundError(f"loss.perceptual_weights={path}: no such file")
        net = vgg16(weights=None)
        net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
        self.layers = sorted(VGG_LAYERS[name] for name in layers)
        self.distance, self.imagenet_norm = distance, bool(imagenet_norm)
        self.features = net.features[: self.layers[-1] + 1].eval().requires_grad_(False)
        self.register_buffer("mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1))

    def forward(self, pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        m = mask.to(pred.dtype)
        x, y = pred * m, gt * m
        if self.imagenet_norm:
            x, y = (x - self.mean) / self.std, (y - self.mean) / self.std
        loss = pred.new_zeros(())
        for i, layer in enumerate(self.features):
            x, y = layer(x), layer(y)
            if i not in self.layers:
                continue
            if self.distance == "l1":
                loss = loss + (x - y).abs().mean()
            else:
                pooled = F.adaptive_avg_pool2d(m, x.shape[-2:]).expand_as(x)
                loss = loss + ((x - y) ** 2 * pooled).sum() / pooled.sum().clamp(min=1e-12)
        return loss


PERCEPTUAL_MAPS = ("albedo", "normal", "roughness", "metallic")


class MaterialLoss(nn.Module):
    """Weighted sum of the four map losses, plus perceptual terms when VGG16 weights are given:
    `perceptual` times the relative weight of each map in `perceptual_maps` (albedo, normal, roughness,
    metallic; one-channel maps are repeated to three). Normals enter VGG as 0.5 n + 0.5 with
    `perceptual_imagenet_norm`, as they are (in [-1, 1]) without it (the released code).
    forward(pred, batch) -> (total, {term: value})."""

    def __init__(
        self,
        albedo: float = 1.0,
        normal: float = 1.0,
        material: float = 1.0,
        depth: float = 1.0,
        perceptual: float = 0.0,
        perceptual_weights: str | None = None,
        metallic: str = "l2",
        depth_units: str = "metres",
        perceptual_maps: dict | None = None,
        perceptual_layers: tuple[str, ...] = ("relu1_2", "relu2_2", "relu3_3"),
        perceptual_distance: str = "l1",
        perceptual_imagenet_norm: bool = True,
    ):
        super().__init__()
        if metallic not in METALLIC_LOSSES:
            raise ValueError(f"loss.metallic={metallic!r}: choose one of {METALLIC_LOSSES}")
        if depth_units not in DEPTH_UNITS:
            raise ValueError(f"loss.depth_units={depth_units!r}: choose one of {DEPTH_UNITS}")
        self.metallic, self.depth_units = metallic, depth_units
        self.weights = {"albedo": albedo, "normal": normal, "material": material, "depth": depth}
        for k, w in self.weights.items():
            if not (w >= 0):
                raise ValueError(f"loss.{k}={w}: weights must be >= 0")
        self.perceptual_maps = dict({"albedo": 1.0, "normal": 1.0} if perceptual_maps is None else perceptual_maps)
        for k, w in self.perceptual_maps.items():
            if k not in PERCEPTUAL_MAPS or not (w >= 0):
                raise ValueError(f"loss.perceptual_maps.{k}={w}: maps are {PERCEPTUAL_MAPS}, weights >= 0")
        self.perceptual_weight = float(perceptual)
        self.vgg = (
            VGGPerceptual(perceptual_weights, tuple(perceptual_layers), perceptual_distance, perceptual_imagenet_norm)
            if perceptual_weights and perceptual > 0
            else None
        )

    @property
    def perceptual_on(self) -> bool:
        return self.vgg is not None

    def forward(self, pred: dict, batch: dict) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        mask = batch["mask"]
        terms = {
            "albedo": albedo_loss(pred["albedo"], batch["albedo"], mask),
            "normal": normal_loss(pred["normal"], batch["normal"], mask),
            "material": material_loss(pred["material"], batch["material"], mask, self.metallic),
            "depth": depth_loss(pred["depth"], batch["depth"], mask, self.depth_units),
        }
        total = sum(self.weights[k] * v for k, v in terms.items())
        if self.vgg is not None:
            terms["perceptual"] = sum(
                w * self.vgg(*self._vgg_pair(name, pred, batch), mask) for name, w in self.perceptual_maps.items()
            )
            total = total + self.perceptual_weight * terms["perceptual"]
        return total, terms

    def _vgg_pair(self, name: str, pred: dict, batch: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """Prediction and ground truth of one map as (B, 3, H, W) VGG inputs."""
        if name in ("roughness", "metallic"):
            c = 0 if name == "roughness" else 1
            return tuple(x["material"][:, c : c + 1].expand(-1, 3, -1, -1) for x in (pred, batch))
        if name == "normal" and self.vgg.imagenet_norm:
            return pred["normal"] * 0.5 + 0.5, batch["normal"] * 0.5 + 0.5
        return pred[name], batch[name]


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
