"""LightNet's two branches (DESIGN.md section 5).

Local branch: multi-scale CNN features of the input image sampled at the SSRT hit pixel; an MLP over the
Fourier-encoded direction, the feature and the G-buffers at the hit (Kd, Ks, normal, roughness) gives the
radiance leaving the hit towards the query point.

Out-of-view branch: a second CNN gives one global feature per image; a hypernetwork turns it into the
weights of a small NeRF MLP (encoded position -> density, radiance), volume-rendered along p + t wi
inside the scene's bounding box (from the depth map); light that leaves the box unabsorbed takes a
direction-only "far field" radiance (windows, sky).

Radiance is in units of the input image's mean (the networks see mean-normalised images), so outputs
scale with exposure; both are non-negative (softplus).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from pipeline.models.light_net.hyper import HyperMLP
from pipeline.models.material_net import ENCODERS, normalize_input
from pipeline.ops.encodings import fourier, fourier_dim
from pipeline.ops.volume import composite, ray_box, stratified_edges

GBUFFER_DIM = 10  # Kd (3), Ks (3), normal (3), roughness (1)


def image_scale(im: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) -> (B,) mean radiance: the unit both branches predict in."""
    return im.clamp(min=0).mean(dim=(1, 2, 3)).clamp(min=1e-6)


def _encoder(backbone: str) -> nn.Module:
    # group norm: LightNet often sees one image at a time (batch statistics would be degenerate)
    return ENCODERS[backbone](norm="group") if backbone == "small" else ENCODERS[backbone]()


def _mlp(cin: int, hidden: int, layers: int, cout: int) -> nn.Sequential:
    mods, c = [], cin
    for _ in range(layers):
        mods += [nn.Linear(c, hidden), nn.ReLU(inplace=True)]
        c = hidden
    return nn.Sequential(*mods, nn.Linear(c, cout))


class LocalBranch(nn.Module):
    """pixel_base: also read the image's own radiance at the hit pixel (in units of the image mean) and
    predict L = pixel * exp(g) + softplus(a) from the MLP's (g, a), instead of softplus(MLP). The camera
    saw that pixel's radiance leaving the hit towards it; for a diffuse hit it is exactly the radiance
    leaving towards any query point, so the network only learns the view-dependent correction, and a
    visible lamp or window keeps its full HDR value instead of being decoded from compressed features."""

    def __init__(
        self,
        backbone: str = "small",
        levels: int = 3,
        frequencies: int = 4,
        hidden: int = 128,
        layers: int = 3,
        pixel_base: bool = False,
    ):
        super().__init__()
        self.encoder = _encoder(backbone)
        self.levels, self.frequencies, self.pixel_base = int(levels), int(frequencies), bool(pixel_base)
        feat_dim = sum(self.encoder.channels[: self.levels])
        extra = 3 if self.pixel_base else 0
        self.mlp = _mlp(fourier_dim(3, frequencies) + feat_dim + GBUFFER_DIM + extra, hidden, layers, 6 if extra else 3)
        if self.pixel_base:
            with torch.no_grad():  # start near L = pixel: unit gain, a small additive term
                self.mlp[-1].weight[:3].mul_(0.1)
                self.mlp[-1].bias[:3].zero_()
                self.mlp[-1].bias[3:].fill_(-4.0)

    def encode(self, im: torch.Tensor) -> list[torch.Tensor]:
        return self.encoder(normalize_input(im))[: self.levels]

    def query(self, feats, scale, batch_index, pixel, size, wi, gbuf, image=None):
        """feats: encode() output; scale (B,); batch_index (N,); pixel (N, 2) (row, col) hit pixels;
        size (H, W); wi (N, 3); gbuf (N, 10) at the hit; image (B, 3, H, W) the input divided by scale
        (needed with pixel_base) -> radiance (N, 3)."""
        H, W = size
        # pixel centres in grid_sample's [-1, 1] coordinates (align_corners=False)
        gx = (pixel[:, 1].to(wi.dtype) + 0.5) / W * 2 - 1
        gy = (pixel[:, 0].to(wi.dtype) + 0.5) / H * 2 - 1
        grid = torch.stack([gx, gy], -1)
        sampled = []
        for f in feats:  # per image: sample that image's rays
            out = f.new_zeros(len(wi), f.shape[1])
            for b in torch.unique(batch_index).tolist():
                sel = batch_index == b
                g = grid[sel].view(1, -1, 1, 2)
                out[sel] = F.grid_sample(f[b : b + 1], g, mode="bilinear", align_corners=False)[0, :, :, 0].T
            sampled.append(out)
        x = torch.cat([fourier(wi, self.frequencies), *sampled, gbuf], -1)
        if not self.pixel_base:
            return F.softplus(self.mlp(x)) * scale[batch_index].unsqueeze(-1)
        if image is None:
            raise ValueError("LocalBranch(pixel_base=True).query needs the normalised image")
        pix = image[batch_index, :, pixel[:, 0], pixel[:, 1]].clamp(min=0)
        out = self.mlp(torch.cat([x, torch.log1p(pix)], -1))
        radiance = pix * torch.exp(out[:, :3].clamp(-10.0, 5.0)) + F.softplus(out[:, 3:])
        return radiance * scale[batch_index].unsqueeze(-1)


class OutOfViewBranch(nn.Module):
    def __init__(
        self,
        backbone: str = "small",
        feature_dim: int = 128,
        nerf_hidden: int = 64,
        nerf_layers: int = 2,
        frequencies: int = 6,
        dir_frequencies: int = 4,
        samples: int = 16,
    ):
        super().__init__()
        self.encoder = _encoder(backbone)
        self.to_feature = nn.Linear(self.encoder.channels[-1], feature_dim)
        self.frequencies, self.dir_frequencies, self.samples = int(frequencies), int(dir_frequencies), int(samples)
        sizes = [fourier_dim(3, frequencies)] + [nerf_hidden] * nerf_layers + [4]
        self.hyper = HyperMLP(feature_dim, sizes)
        self.far = _mlp(feature_dim + fourier_dim(3, dir_frequencies), 64, 2, 3)

    def encode(self, im: torch.Tensor) -> tuple[torch.Tensor, list]:
        feature = self.to_feature(self.encoder(normalize_input(im))[-1].mean(dim=(2, 3)))
        return feature, self.hyper(feature)

    def query(self, feature, params, scale, bounds, batch_index, origin, wi, generator=None):
        """Volume-render rays (N,) of images batch_index inside their bounds (B, 2, 3) (box min, max in
        view space, metres) -> radiance (N, 3). generator None: stratum midpoints (deterministic)."""
        lo, hi = bounds[batch_index, 0], bounds[batch_index, 1]
        t_near, t_far = ray_box(origin, wi, lo, hi)
        edges, mids = stratified_edges(t_near, t_far, self.samples, generator)
        pts = origin[:, None, :] + mids[..., None] * wi[:, None, :]  # (N, S, 3)
        centre, half = (lo + hi) / 2, ((hi - lo) / 2).clamp(min=1e-3)
        local = (pts - centre[:, None]) / half[:, None]  # the box maps to [-1, 1]^3
        S = self.samples
        out = HyperMLP.run_generated(
            params, fourier(local.reshape(-1, 3), self.frequencies), batch_index.repeat_interleave(S)
        )
        out = out.view(-1, S, 4)
        sigma = F.softplus(out[..., 0]) * (S / (t_far - t_near).clamp(min=1e-3))[:, None]  # O(1) optical depth
        rad, _, left = composite(sigma, F.softplus(out[..., 1:]), edges)
        far = F.softplus(self.far(torch.cat([feature[batch_index], fourier(wi, self.dir_frequencies)], -1)))
        return (rad + left[:, None] * far) * scale[batch_index].unsqueeze(-1)
