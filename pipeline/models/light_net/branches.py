"""LightNet's two branches (docs/design.md, section 5).

Local branch: multi-scale CNN features of the input image sampled at the SSRT hit pixel; an MLP over the
Fourier-encoded direction, the feature and the G-buffers at the hit (Kd, Ks, normal, roughness) gives the
radiance leaving the hit towards the query point.

Out-of-view branch: a second CNN gives one global feature per image; a hypernetwork turns it into the
weights of a small NeRF MLP (encoded position -> density, radiance), volume-rendered along p + t wi
inside the scene's bounds: `box` (an option: the depth map's bounding box, positions mapped to
[-1, 1]^3, density scaled to O(1) optical depth; light that leaves the box unabsorbed takes a
direction-only "far field" radiance, windows and sky, when `far_field` is on; the room behind the camera
lies outside it) or `sphere` (both profiles, as in the released code: positions in units of the view's
maximum depth, a camera-centred sphere of radius `sphere_radius` from `near`, raw density; behind the
sphere the far field when `far_field` is on, else nothing).

Options reproduce the released layers for `model/light_net=paper` (docs/method.md): the local MLP's
`skips` and random Fourier features (`encoding=rff`), ReLU outputs, and the hypernetwork's structure.

Radiance is in units of the input image's mean (the networks see mean-normalised images), so outputs
scale with exposure; both are non-negative (softplus). `LightNet(units="absolute")` is the released
convention instead: the encoders see the raw HDR image and radiance is in the image's own units, the local
branch capped (`cap`, released: 100).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from pipeline.models.light_net.hyper import HyperMLP, mlp_stack
from pipeline.models.material_net import ENCODERS, normalize_input
from pipeline.ops.encodings import fourier, fourier_dim, random_fourier
from pipeline.ops.volume import composite, ray_box, ray_sphere, stratified_edges

GBUFFER_DIM = 10  # Kd (3), Ks (3), normal (3), roughness (1)
GBUFFER_GROUPS = (("kd", 3), ("ks", 3), ("normal", 3), ("roughness", 1))  # the split of those 10
ENCODINGS = ("nerf", "rff")
ACTIVATIONS = ("softplus", "relu", "exp")
# exp: radiance = exp(x), x clamped at EXP_MAX (e^12: 1.6e5 image means), so a lamp 30-300x the image mean
# is a pre-activation of 3.4-5.7 rather than 30-300 (HDR light spans decades); densities stay softplus
EXP_MAX = 12.0
BOUNDS = ("box", "sphere")
# rays per chunk of either branch's query: the (rays [x samples] x width) activations stay a few MB and are
# reused from cache instead of being freshly paged in for every operation (pipeline.bench.light_net)
RAY_CHUNK = 8192
POINT_CHUNK = 1 << 15  # volume samples per chunk of the out-of-view branch (its rays: POINT_CHUNK // samples)


def image_scale(im: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) -> (B,) mean radiance: the unit both branches predict in."""
    return im.clamp(min=0).mean(dim=(1, 2, 3)).clamp(min=1e-6)


def _encoder(backbone: str) -> nn.Module:
    # group norm: LightNet often sees one image at a time (batch statistics would be degenerate)
    return ENCODERS[backbone](norm="group") if backbone == "small" else ENCODERS[backbone]()


class SkipMLP(nn.Module):
    """`layers` hidden Linear + ReLU of width `hidden`, the input concatenated again after each hidden
    layer whose index is in `skips` (NeRF's skip), then a Linear to `cout`. mlp[-1] is the output layer."""

    def __init__(self, cin: int, hidden: int, layers: int, cout: int, skips=()):
        super().__init__()
        self.skips = {int(i) for i in skips}
        if any(not 0 <= i < layers - 1 for i in self.skips):
            raise ValueError(
                f"skips={sorted(self.skips)}: each must index a hidden layer before the last ({layers - 1})"
            )
        linears, c = [], cin
        for i in range(layers):
            linears.append(nn.Linear(c, hidden))
            c = hidden + (cin if i in self.skips else 0)
        linears.append(nn.Linear(c, cout))
        self.linears = nn.ModuleList(linears)

    def __getitem__(self, i: int) -> nn.Linear:
        return self.linears[i]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = x
        for i, layer in enumerate(self.linears[:-1]):
            h = F.relu(layer(h))
            if i in self.skips:
                h = torch.cat([h, x], -1)
        return self.linears[-1](h)


def _activate(x: torch.Tensor, activation: str) -> torch.Tensor:
    if activation == "exp":
        return torch.exp(x.clamp(max=EXP_MAX))
    return F.softplus(x) if activation == "softplus" else F.relu(x)


def _check(name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"model.light_net.{name}={value!r}: choose one of {choices}")


class LocalBranch(nn.Module):
    """pixel_base: also read the image's own radiance at the hit pixel (in units of the image mean) and
    predict L = pixel * exp(g) + softplus(a) from the MLP's (g, a), instead of softplus(MLP). The camera
    saw that pixel's radiance leaving the hit towards it; for a diffuse hit it is exactly the radiance
    leaving towards any query point, so the network only learns the view-dependent correction, and a
    visible lamp or window keeps its full HDR value instead of being decoded from compressed features.
    activation: of the radiance, softplus | relu | exp (see EXP_MAX).

    encoding: `nerf` (the direction NeRF-encoded with `frequencies`, G-buffers as they are) or `rff` (the
    released code: direction, normal, Kd, Ks and roughness each through its own random Fourier basis of
    `rff_features` columns drawn from N(0, rff_sigma^2), stored with the weights). skips: hidden layers
    after which the MLP input is concatenated again. activation: of the radiance (softplus | relu)."""

    def __init__(
        self,
        backbone: str = "small",
        levels: int = 3,
        frequencies: int = 4,
        hidden: int = 128,
        layers: int = 3,
        pixel_base: bool = False,
        encoding: str = "nerf",
        rff_features: int = 32,
        rff_sigma: float = 1.0,
        skips: tuple[int, ...] = (),
        activation: str = "softplus",
        cap: float | None = None,
    ):
        super().__init__()
        _check("local.encoding", encoding, ENCODINGS)
        if cap is not None and not float(cap) > 0:
            raise ValueError(f"model.light_net.local.cap={cap}: give a positive radiance or null")
        self.cap = None if cap is None else float(cap)
        _check("local.activation", activation, ACTIVATIONS)
        self.encoder = _encoder(backbone)
        self.levels, self.frequencies, self.pixel_base = int(levels), int(frequencies), bool(pixel_base)
        self.encoding, self.activation = encoding, activation
        feat_dim = sum(self.encoder.channels[: self.levels])
        extra = 3 if self.pixel_base else 0
        if encoding == "rff":
            for name, dim in (("direction", 3), *GBUFFER_GROUPS):
                self.register_buffer(f"rff_{name}", torch.randn(dim, int(rff_features)) * float(rff_sigma))
            enc_dim = 2 * int(rff_features) * (1 + len(GBUFFER_GROUPS))
        else:
            enc_dim = fourier_dim(3, frequencies) + GBUFFER_DIM
        cin, cout = enc_dim + feat_dim + extra, 6 if extra else 3
        self.mlp = SkipMLP(cin, hidden, layers, cout, skips) if skips else mlp_stack(cin, [hidden] * layers, cout)
        if self.pixel_base:
            with torch.no_grad():  # start near L = pixel: unit gain, a small additive term
                self.mlp[-1].weight[:3].mul_(0.1)
                self.mlp[-1].bias[:3].zero_()
                self.mlp[-1].bias[3:].fill_(-4.0)

    def encode(self, im: torch.Tensor, normalise: bool = True) -> list[torch.Tensor]:
        """Feature levels of im (B, 3, H, W): of its log-mean-normalised copy, or of the raw HDR values
        (normalise False: the released LightNet's input, `LightNet(units="absolute")`)."""
        return self.encoder(normalize_input(im) if normalise else im.clamp(min=0))[: self.levels]

    def query(self, feats, scale, batch_index, pixel, size, wi, gbuf, image=None):
        """feats: encode() output; scale (B,); batch_index (N,); pixel (N, 2) (row, col) hit pixels;
        size (H, W); wi (N, 3); gbuf (N, 10) at the hit; image (B, 3, H, W) the input divided by scale
        (needed with pixel_base) -> radiance (N, 3)."""
        if len(wi) > RAY_CHUNK:  # cache-sized chunks (see RAY_CHUNK)
            return torch.cat(
                [
                    self.query(
                        feats,
                        scale,
                        *(x[i : i + RAY_CHUNK] for x in (batch_index, pixel)),
                        size,
                        wi[i : i + RAY_CHUNK],
                        gbuf[i : i + RAY_CHUNK],
                        image,
                    )
                    for i in range(0, len(wi), RAY_CHUNK)
                ]
            )
        H, W = size
        # pixel centres in grid_sample's [-1, 1] coordinates (align_corners=False)
        gx = (pixel[:, 1].to(wi.dtype) + 0.5) / W * 2 - 1
        gy = (pixel[:, 0].to(wi.dtype) + 0.5) / H * 2 - 1
        grid = torch.stack([gx, gy], -1)
        images = torch.unique(batch_index).tolist()
        sampled = []
        for f in feats:  # per image: sample that image's rays
            if len(images) == 1:  # one image: no scatter
                b = images[0]
                g = grid.view(1, -1, 1, 2)
                sampled.append(F.grid_sample(f[b : b + 1], g, mode="bilinear", align_corners=False)[0, :, :, 0].T)
                continue
            out = f.new_zeros(len(wi), f.shape[1])
            for b in images:
                sel = batch_index == b
                g = grid[sel].view(1, -1, 1, 2)
                out[sel] = F.grid_sample(f[b : b + 1], g, mode="bilinear", align_corners=False)[0, :, :, 0].T
            sampled.append(out)
        x = torch.cat([*self._encode_inputs(wi, gbuf), *sampled], -1)
        if not self.pixel_base:
            radiance = _activate(self.mlp(x), self.activation)
        else:
            if image is None:
                raise ValueError("LocalBranch(pixel_base=True).query needs the normalised image")
            pix = image[batch_index, :, pixel[:, 0], pixel[:, 1]].clamp(min=0)
            out = self.mlp(torch.cat([x, torch.log1p(pix)], -1))
            radiance = pix * torch.exp(out[:, :3].clamp(-10.0, 5.0)) + F.softplus(out[:, 3:])
        if self.cap is not None:  # the released local MLP's output clamp (in the units it predicts in)
            radiance = radiance.clamp(max=self.cap)
        return radiance * scale[batch_index].unsqueeze(-1)

    def _encode_inputs(self, wi: torch.Tensor, gbuf: torch.Tensor) -> list[torch.Tensor]:
        if self.encoding == "nerf":
            return [fourier(wi, self.frequencies), gbuf]
        parts = [random_fourier(wi, self.rff_direction)]
        for part, (name, _) in zip(gbuf.split([d for _, d in GBUFFER_GROUPS], -1), GBUFFER_GROUPS, strict=True):
            parts.append(random_fourier(part, getattr(self, f"rff_{name}")))
        return parts


class OutOfViewBranch(nn.Module):
    """feature_dim: the global feature's width (null: the encoder's own pooled width, no projection, as
    released); hyper: HyperMLP structure (trunk, head_hidden, split_bias, param_activation); bounds, near,
    sphere_radius, far_field: see the module docstring; activation: of density and radiance (exp: of the
    radiance and the far field, densities stay softplus); pi_encoding: positions encoded with
    sin(2^k pi x) (off: sin(2^k x), as released)."""

    def __init__(
        self,
        backbone: str = "small",
        feature_dim: int | None = 128,
        nerf_hidden: int = 64,
        nerf_layers: int = 2,
        frequencies: int = 6,
        dir_frequencies: int = 4,
        samples: int = 16,
        hyper: dict | None = None,
        bounds: str = "box",
        sphere_radius: float = 3.0,
        near: float = 0.05,
        far_field: bool = True,
        activation: str = "softplus",
        pi_encoding: bool = True,
    ):
        super().__init__()
        _check("out_of_view.bounds", bounds, BOUNDS)
        _check("out_of_view.activation", activation, ACTIVATIONS)
        if bounds == "sphere" and not 0 <= near < sphere_radius:
            raise ValueError(f"model.light_net.out_of_view: need 0 <= near ({near}) < sphere_radius ({sphere_radius})")
        self.encoder = _encoder(backbone)
        width = self.encoder.channels[-1]
        self.to_feature = nn.Identity() if feature_dim is None else nn.Linear(width, int(feature_dim))
        feature_dim = width if feature_dim is None else int(feature_dim)
        self.frequencies, self.dir_frequencies, self.samples = int(frequencies), int(dir_frequencies), int(samples)
        self.bounds, self.sphere_radius, self.near = bounds, float(sphere_radius), float(near)
        self.activation, self.pi_encoding = activation, bool(pi_encoding)
        sizes = [fourier_dim(3, frequencies)] + [nerf_hidden] * nerf_layers + [4]
        self.hyper = HyperMLP(feature_dim, sizes, **(hyper or {}))
        self.far = mlp_stack(feature_dim + fourier_dim(3, dir_frequencies), [64, 64], 3) if far_field else None

    def encode(self, im: torch.Tensor, normalise: bool = True) -> tuple[torch.Tensor, list]:
        """The global feature of im (B, 3, H, W) and the NeRF weights it generates; normalise as
        `LocalBranch.encode`."""
        x = normalize_input(im) if normalise else im.clamp(min=0)
        feature = self.to_feature(self.encoder(x)[-1].mean(dim=(2, 3)))
        return feature, self.hyper(feature)

    def query(
        self, feature, params, scale, bounds, batch_index, origin, wi, generator=None, depth_max=None, details=False
    ):
        """Volume-render rays (N,) of images batch_index -> radiance (N, 3). bounds (B, 2, 3): box min, max
        in view space, metres (`box`); depth_max (B,): each view's largest z-depth, metres (`sphere`).
        generator None: stratum midpoints (deterministic). details: return a dict instead, radiance (N, 3)
        with each sample's compositing weight (N, S), its distance along the ray (N, S) in metres and the
        transmittance left (N,) (where the volume puts its surfaces: bench.overfit's wall agreement)."""
        if self.bounds == "sphere":
            if depth_max is None:
                raise ValueError("out_of_view.bounds=sphere: query needs depth_max")
            unit = depth_max[batch_index].clamp(min=1e-6)[:, None]
            origin = origin / unit  # positions in units of the view's maximum depth (released convention)
            t_far = ray_sphere(origin, wi, self.sphere_radius).clamp(min=self.near)
            t_near = torch.full_like(t_far, self.near)
        else:
            lo, hi = bounds[batch_index, 0], bounds[batch_index, 1]
            t_near, t_far = ray_box(origin, wi, lo, hi)
        edges, mids = stratified_edges(t_near, t_far, self.samples, generator)
        if self.bounds == "box":  # the box maps to [-1, 1]^3
            centre, half = (lo + hi) / 2, ((hi - lo) / 2).clamp(min=1e-3)
        else:
            centre, half = torch.zeros_like(origin), torch.ones_like(origin)
        # density in units of the samples' spacing: O(1) optical depth across the box
        spacing = self.samples / (t_far - t_near).clamp(min=1e-3) if self.bounds == "box" else None
        step = max(1, POINT_CHUNK // self.samples)
        parts = []
        for i in range(0, max(len(wi), 1), step):  # at least one (possibly empty) chunk
            c = slice(i, i + step)
            pts = origin[c, None, :] + mids[c, :, None] * wi[c, None, :]  # (n, S, 3)
            pts = (pts - centre[c, None]) / half[c, None]
            parts.append(self._march(params, pts, edges[c], batch_index[c], None if spacing is None else spacing[c]))
        rad, left, weights = parts[0] if len(parts) == 1 else (torch.cat(x) for x in zip(*parts, strict=True))
        if self.far is not None:
            raw = self.far(torch.cat([feature[batch_index], fourier(wi, self.dir_frequencies)], -1))
            far = _activate(raw, "exp") if self.activation == "exp" else F.softplus(raw)
            rad = rad + left[:, None] * far
        rad = rad * scale[batch_index].unsqueeze(-1)
        if details:
            metres = mids * (unit if self.bounds == "sphere" else 1.0)
            return {"radiance": rad, "weights": weights, "t": metres, "left": left}
        return rad

    def _march(self, params, pts, edges, batch_index, density_scale):
        """Volume-render one chunk of rays: sample points pts (n, S, 3) (encoded positions' space), segment
        edges (n, S+1), images batch_index (n,), density_scale (n,) or None -> (radiance (n, 3), transmittance
        left (n,), compositing weights (n, S))."""
        S = pts.shape[1]
        encoded = fourier(pts.reshape(-1, 3), self.frequencies, pi=self.pi_encoding)
        out = HyperMLP.run_generated(params, encoded, batch_index.repeat_interleave(S))
        out = out.view(-1, S, 4)
        # density and radiance share the activation, but for exp, which is for radiance only
        sigma = _activate(out[..., 0], "softplus" if self.activation == "exp" else self.activation)
        sigma = sigma if density_scale is None else sigma * density_scale[:, None]
        rad, weights, left = composite(sigma, _activate(out[..., 1:], self.activation), edges)
        return rad, left, weights
