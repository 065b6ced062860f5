"""MaterialNet (the paper's MGNet): one encoder, four decoders with skip links.

Input: an HDR image (B, 3, H, W), linear radiance in any units. Outputs at the input resolution:
albedo (B, 3, H, W) in [0, 1], normal (B, 3, H, W) unit view-space vectors (+z towards the camera),
material (B, 2, H, W) roughness and metallic in [0, 1], depth (B, 1, H, W) positive z-depth in arbitrary
scale (losses and metrics fit the scale by least squares, as a single image fixes depth only up to scale).

Layouts: `compact` (this project's U-Net: any backbone, decoders ending at 1/2 resolution, then upsampled)
and `mgnet` (the released MGNet layer for layer, DenseNet121 only; `pipeline.models.mgnet`).
Backbones: `densenet121` (the paper), `resnet34`, and `small` (a plain strided CNN sized for a CPU).
ImageNet weights cannot be downloaded here; `pretrained_path` loads a torchvision state dict from disk.
Input normalisation: `log_mean` (divide by the image mean, log1p: exposure invariant) or `clamp` (the
released code's clamp to [0, 1] of the linear HDR input).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from pipeline.models.mgnet import HEAD_CHANNELS, MGNetDecoder, MGNetEncoder, mgnet_outputs

HEADS = {"albedo": 3, "normal": 3, "material": 2, "depth": 1}


def normalize_input(im: torch.Tensor) -> torch.Tensor:
    """HDR (B, 3, H, W) -> network input: divided by the image's mean (exposure invariance) and
    log-compressed, so highlights hundreds of times the mean stay in a trainable range."""
    scale = im.clamp(min=0).mean(dim=(1, 2, 3), keepdim=True).clamp(min=1e-6)
    return torch.log1p(im.clamp(min=0) / scale)


INPUT_NORMS = ("log_mean", "clamp")
LAYOUTS = ("compact", "mgnet")


def _conv(cin: int, cout: int, stride: int = 1, norm: str = "batch") -> nn.Sequential:
    """3x3 convolution, normalisation (`batch`, or `group` for batches of one image), ReLU."""
    layer = nn.BatchNorm2d(cout) if norm == "batch" else nn.GroupNorm(min(8, cout), cout)
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), layer, nn.ReLU(inplace=True))


class SmallEncoder(nn.Module):
    """Five stride-2 stages (features at 1/2 .. 1/32) of two 3x3 convolutions each."""

    def __init__(self, widths=(16, 32, 64, 96, 128), norm: str = "batch"):
        super().__init__()
        stages, cin = [], 3
        for w in widths:
            stages.append(nn.Sequential(_conv(cin, w, 2, norm), _conv(w, w, 1, norm)))
            cin = w
        self.stages = nn.ModuleList(stages)
        self.channels = list(widths)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        feats = []
        for stage in self.stages:
            x = stage(x)
            feats.append(x)
        return feats


class ResNetEncoder(nn.Module):
    """torchvision ResNet34 up to layer4: features at 1/2, 1/4, 1/8, 1/16, 1/32."""

    def __init__(self):
        super().__init__()
        from torchvision.models import resnet34

        self.net = resnet34(weights=None)
        self.net.fc = nn.Identity()
        self.channels = [64, 64, 128, 256, 512]

    def forward(self, x):
        n = self.net
        f1 = n.relu(n.bn1(n.conv1(x)))
        f2 = n.layer1(n.maxpool(f1))
        f3 = n.layer2(f2)
        f4 = n.layer3(f3)
        return [f1, f2, f3, f4, n.layer4(f4)]


class DenseNetEncoder(nn.Module):
    """torchvision DenseNet121 features: 1/2 (conv0), 1/4 (block1), 1/8, 1/16, 1/32 (block4)."""

    def __init__(self):
        super().__init__()
        from torchvision.models import densenet121

        self.net = densenet121(weights=None)
        self.net.classifier = nn.Identity()
        self.channels = [64, 256, 512, 1024, 1024]

    def forward(self, x):
        f = self.net.features
        f1 = f.relu0(f.norm0(f.conv0(x)))
        f2 = f.denseblock1(f.pool0(f1))
        f3 = f.denseblock2(f.transition1(f2))
        f4 = f.denseblock3(f.transition2(f3))
        f5 = F.relu(f.norm5(f.denseblock4(f.transition3(f4))))
        return [f1, f2, f3, f4, f5]


ENCODERS = {"small": SmallEncoder, "resnet34": ResNetEncoder, "densenet121": DenseNetEncoder}


class Decoder(nn.Module):
    """U-Net decoder: from the deepest feature, upsample x2, concatenate the skip, two convolutions, up
    to 1/2 resolution; there a 3x3 head with `out` channels (no activation), bilinearly upsampled to
    the input resolution (full-resolution convolutions would cost most of the network's time)."""

    def __init__(self, enc_channels: list[int], widths: list[int], out: int):
        super().__init__()
        skips = enc_channels[:-1][::-1]  # 1/16, 1/8, 1/4, 1/2
        blocks, cin = [], enc_channels[-1]
        for skip, w in zip(skips, widths, strict=True):
            blocks.append(nn.Sequential(_conv(cin + skip, w), _conv(w, w)))
            cin = w
        self.blocks = nn.ModuleList(blocks)
        self.head = nn.Conv2d(cin, out, 3, 1, 1)

    def forward(self, feats: list[torch.Tensor], x: torch.Tensor) -> torch.Tensor:
        y = feats[-1]
        for block, skip in zip(self.blocks, feats[:-1][::-1], strict=True):
            y = F.interpolate(y, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            y = block(torch.cat([y, skip], 1))
        return F.interpolate(self.head(y), size=x.shape[-2:], mode="bilinear", align_corners=False)


class MaterialNet(nn.Module):
    """Shared encoder + albedo/normal/material/depth decoders. forward(im (B,3,H,W) HDR) -> dict of maps
    (see the module docstring)."""

    def __init__(
        self,
        backbone: str = "small",
        decoder_widths: tuple[int, ...] = (96, 64, 48, 32),
        pretrained_path: str | None = None,
        layout: str = "compact",
        decoder_groups: tuple[int, ...] | None = None,
        input_norm: str = "log_mean",
    ):
        super().__init__()
        if backbone not in ENCODERS:
            raise ValueError(f"model.backbone={backbone!r}: choose one of {sorted(ENCODERS)}")
        if layout not in LAYOUTS:
            raise ValueError(f"model.layout={layout!r}: choose one of {LAYOUTS}")
        if input_norm not in INPUT_NORMS:
            raise ValueError(f"model.input_norm={input_norm!r}: choose one of {INPUT_NORMS}")
        self.backbone, self.layout, self.input_norm = backbone, layout, input_norm
        if layout == "mgnet":
            if backbone != "densenet121":
                raise ValueError(f"model.layout=mgnet needs model.backbone=densenet121, got {backbone!r}")
            self.encoder = MGNetEncoder()
            heads = {
                k: MGNetDecoder(self.encoder.channels, list(decoder_widths), list(decoder_groups or ()), c)
                for k, c in HEAD_CHANNELS.items()
            }
        else:
            if len(decoder_widths) != 4:
                raise ValueError(f"model.decoder_widths={list(decoder_widths)}: need 4 widths (1/16 .. 1/2)")
            self.encoder = ENCODERS[backbone]()
            heads = {k: Decoder(self.encoder.channels, list(decoder_widths), c) for k, c in HEADS.items()}
        if pretrained_path:
            load_backbone_weights(self.encoder, pretrained_path)
        self.decoders = nn.ModuleDict(heads)

    def forward(self, im: torch.Tensor) -> dict[str, torch.Tensor]:
        if im.ndim != 4 or im.shape[1] != 3:
            raise ValueError(f"MaterialNet expects (B, 3, H, W) images, got {tuple(im.shape)}")
        x = normalize_input(im) if self.input_norm == "log_mean" else im.clamp(0, 1)
        feats = self.encoder(x)
        raw = {k: dec(feats, x) for k, dec in self.decoders.items()}
        if self.layout == "mgnet":
            return mgnet_outputs(raw)
        return {
            "albedo": torch.sigmoid(raw["albedo"]),
            "normal": F.normalize(raw["normal"], dim=1, eps=1e-6),
            "material": torch.sigmoid(raw["material"]),
            "depth": F.softplus(raw["depth"]) + 1e-3,
        }


def load_backbone_weights(encoder: nn.Module, path: str | Path) -> None:
    """Load a torchvision ImageNet state dict (e.g. resnet34-*.pth) from disk into the encoder's network,
    weights only; the classifier is ignored. A file that does not fit the backbone is an error."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"model.pretrained_path={path}: no such file")
    if not hasattr(encoder, "net"):
        raise ValueError(f"model.pretrained_path={path}: the `small` backbone has no ImageNet weights")
    state = torch.load(path, map_location="cpu", weights_only=True)
    state = {k: v for k, v in state.items() if not k.startswith(("fc.", "classifier."))}
    missing, unexpected = encoder.net.load_state_dict(state, strict=False)
    missing = [k for k in missing if not k.startswith(("fc.", "classifier."))]
    if missing or unexpected:
        raise ValueError(f"{path}: does not fit the backbone (missing {missing[:3]}, unexpected {unexpected[:3]})")


def parameter_count(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


@torch.no_grad()
def predict_maps(
    net: MaterialNet, meta: dict, im: np.ndarray, renormalize_normals: bool = True
) -> dict[str, np.ndarray]:
    """One (H, W, 3) linear image -> maps at (H, W) in the InteriorVerse conventions: albedo (H, W, 3) linear,
    normal (H, W, 3) unit view space (OpenGL), depth (H, W) z-depth in millimetres (the network's depth
    times the export's `depth_scale`), material (H, W, 3) R roughness, G metallic, B 0. The network runs
    at the export's training resolution `input_size` (the image is resized to it and the maps back).
    Upsampled normals are renormalised unless `renormalize_normals` is off (the NYUv2 protocol scores
    the bilinearly resized prediction as it is)."""
    H, W = im.shape[:2]
    x = torch.from_numpy(im).permute(2, 0, 1)[None]
    size = meta["input_size"]  # (h, w) the network was trained at
    x = F.interpolate(x, size=tuple(size), mode="area" if size[0] < H else "bilinear", align_corners=None)
    pred = net(x)
    back = {k: F.interpolate(v, size=(H, W), mode="bilinear", align_corners=False) for k, v in pred.items()}
    if renormalize_normals:
        back["normal"] = F.normalize(back["normal"], dim=1, eps=1e-6)
    depth_m = back["depth"][0, 0] * float(meta["depth_scale"])
    material = back["material"][0].permute(1, 2, 0).clamp(0, 1)
    return {
        "albedo": back["albedo"][0].permute(1, 2, 0).clamp(0, 1).numpy(),
        "normal": back["normal"][0].permute(1, 2, 0).numpy(),
        "depth": (depth_m * 1000.0).numpy(),
        "material": torch.cat([material, torch.zeros_like(material[..., :1])], -1).numpy(),
    }


def load_material_export(path) -> tuple[MaterialNet, dict]:
    """(MaterialNet in eval mode, export dict: model, input_size, depth_scale, ...) of a `models.export`
    MaterialNet export."""
    from pipeline.models.export import MATERIAL_FORMAT, build_from_export, read_export

    blob = read_export(path, MATERIAL_FORMAT)
    return build_from_export(path, MaterialNet, blob["model"], blob["state_dict"]), blob
