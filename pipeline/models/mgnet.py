"""The released MGNet layout (`model.material_net.layout=mgnet`, the `paper` profile; docs/method.md).

Encoder: torchvision DenseNet121 with its first max-pool skipped, so dense block 1 runs at 1/2 resolution;
skips are the stem (64 ch, 1/2) and the outputs of transitions 1-3 (128 ch 1/4, 256 ch 1/8, 512 ch 1/16);
the bottleneck is dense block 4 + norm5 (1024 ch, 1/16, no ReLU).
Decoder (one per map): a 3x3 convolution on the bottleneck, then four times: concatenate the skip,
upsample x2 (bilinear, align_corners=True), 3x3 convolution; every convolution has a bias, GroupNorm and
ReLU; the last block and a replication-padded 3x3 output convolution run at the full input resolution.
Output activations: clamp(1.01 sigmoid, 0, 1) for albedo and material, clamp(1.01 tanh, -1, 1) then unit
length for normals, and the mean of three channels through clamp(1.01 sigmoid) for depth (relative depth;
kept >= DEPTH_MIN here because SSRT and back-projection treat depth 0 as no surface).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

HEAD_CHANNELS = {"albedo": 3, "normal": 3, "material": 2, "depth": 3}
DEPTH_MIN = 1e-3


class MGNetEncoder(nn.Module):
    """DenseNet121 without pool0 -> [x1 (64, 1/2), x2 (128, 1/4), x3 (256, 1/8), x4 (512, 1/16),
    x5 (1024, 1/16)] for an input (B, 3, H, W)."""

    def __init__(self):
        super().__init__()
        from torchvision.models import densenet121

        self.net = densenet121(weights=None)
        self.net.classifier = nn.Identity()
        self.channels = [64, 128, 256, 512, 1024]

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        f = self.net.features
        x1 = f.relu0(f.norm0(f.conv0(x)))
        x2 = f.transition1(f.denseblock1(x1))
        x3 = f.transition2(f.denseblock2(x2))
        x4 = f.transition3(f.denseblock3(x3))
        x5 = f.norm5(f.denseblock4(x4))
        return [x1, x2, x3, x4, x5]


def _block(cin: int, cout: int, groups: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, 1, 1), nn.GroupNorm(groups, cout), nn.ReLU(inplace=True))


class MGNetDecoder(nn.Module):
    """widths (5,) and GroupNorm groups (5,) of the bottleneck block and the four upsampling blocks."""

    def __init__(self, enc_channels: list[int], widths: list[int], groups: list[int], out: int):
        super().__init__()
        if len(widths) != 5 or len(groups) != 5:
            raise ValueError(f"mgnet layout: need 5 decoder_widths and 5 decoder_groups, got {widths}, {groups}")
        skips = enc_channels[:-1][::-1]  # x4, x3, x2, x1
        blocks = [_block(enc_channels[-1], widths[0], groups[0])]
        for skip, cin, w, g in zip(skips, widths[:-1], widths[1:], groups[1:], strict=True):
            blocks.append(_block(cin + skip, w, g))
        self.blocks = nn.ModuleList(blocks)
        self.head = nn.Sequential(nn.ReplicationPad2d(1), nn.Conv2d(widths[-1], out, 3))

    def forward(self, feats: list[torch.Tensor], x: torch.Tensor) -> torch.Tensor:
        y = self.blocks[0](feats[-1])
        targets = [f.shape[-2:] for f in feats[:-2][::-1]] + [x.shape[-2:]]  # 1/8, 1/4, 1/2, full
        for block, skip, size in zip(self.blocks[1:], feats[:-1][::-1], targets, strict=True):
            y = torch.cat([_fit(y, skip.shape[-2:]), skip], 1)
            y = block(_fit(F.interpolate(y, scale_factor=2, mode="bilinear", align_corners=True), size))
        return self.head(y)


def _fit(y: torch.Tensor, size) -> torch.Tensor:
    """Bilinear resize to `size` where odd input sizes leave a one-pixel mismatch."""
    if tuple(y.shape[-2:]) == tuple(size):
        return y
    return F.interpolate(y, size=tuple(size), mode="bilinear", align_corners=True)


def mgnet_outputs(raw: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Raw decoder outputs -> albedo (B, 3, H, W), normal (B, 3, H, W), material (B, 2, H, W), depth
    (B, 1, H, W), with the released output activations."""

    def unit(x):
        return (1.01 * torch.sigmoid(x)).clamp(0, 1)

    normal = (1.01 * torch.tanh(raw["normal"])).clamp(-1, 1)
    depth = unit(raw["depth"].mean(1, keepdim=True))
    return {
        "albedo": unit(raw["albedo"]),
        "normal": F.normalize(normal, dim=1, eps=1e-6),
        "material": unit(raw["material"]),
        "depth": depth.clamp(min=DEPTH_MIN),
    }
