"""LightNet's `roombox` out-of-view branch (docs/design.md, section 5; `out_of_view.kind: roombox`).

An indoor room is, to first order, a box: walls, floor and ceiling, lamps on the ceiling, windows in the
walls. The branch holds the light out of view as HDR textures on the six faces of that box, and answers a
query ray by where it leaves the box: about a hundred operations per ray, and as sharp as a texel.

Per image (`encode`):
- the box: its rotation from the normals (Manhattan alignment), its faces from the depth map's robust
  extents (`ops.roombox`); or the true box handed in (`layout: gt`, the tests' oracle);
- what the camera saw of each face, lamps and windows included, splatted onto the texels with a coverage
  weight c = 1 - exp(-pixels / coverage_pixels);
- a decoded texture per face from a global code that keeps coarse position (the encoder's last feature
  map pooled to a `grid`, not to one vector), refined by a few convolutions that also see the observed
  texels and their coverage; radiance = c * observed + (1 - c) * decoded;
- a transparency channel per texel (windows) with a direction-only distant map behind (`far_field`).

Radiance is in the image's units divided by `unit` (image-mean units when the encoders see the normalised
image), as the NeRF branch's.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from pipeline.models.light_net.branches import EXP_MAX, _encoder
from pipeline.models.light_net.hyper import mlp_stack
from pipeline.models.material_net import normalize_input
from pipeline.ops.camera import backproject_views
from pipeline.ops.encodings import fourier, fourier_dim
from pipeline.ops.roombox import exit_face, extents_from_points, observed_textures, rotation_from_normals, texel_lookup

LAYOUTS = ("predicted", "gt")
# where the faces the camera did not see go: at the prior's fraction of the opposite face (`prior`), or
# there times exp(a per-face scale the code predicts), learnt through the light losses (`learnt`)
UNSEEN = ("prior", "learnt")
SEED_SIZE = 4  # side of the per-face map the code is reshaped to before upsampling


def normals_from_depth(points: torch.Tensor) -> torch.Tensor:
    """View-space unit normals (B, 3, H, W) of points (B, H, W, 3), facing the camera. Along each image
    axis the one-sided difference with the smaller depth change is used, so a pixel beside a depth edge
    takes its tangent from its own surface, not across the edge."""

    def tangent(ahead, behind):
        keep = (ahead[..., 2].abs() <= behind[..., 2].abs()).unsqueeze(-1)
        return torch.where(keep, ahead, behind)

    fwd_x = torch.zeros_like(points)
    fwd_x[:, :, :-1] = points[:, :, 1:] - points[:, :, :-1]
    bwd_x = torch.zeros_like(points)
    bwd_x[:, :, 1:] = points[:, :, 1:] - points[:, :, :-1]
    fwd_y = torch.zeros_like(points)
    fwd_y[:, :-1] = points[:, :-1] - points[:, 1:]  # upwards in the image
    bwd_y = torch.zeros_like(points)
    bwd_y[:, 1:] = points[:, :-1] - points[:, 1:]
    dx = tangent(torch.where(fwd_x.abs().sum(-1, keepdim=True) > 0, fwd_x, bwd_x), bwd_x)
    dy = tangent(torch.where(fwd_y.abs().sum(-1, keepdim=True) > 0, fwd_y, bwd_y), bwd_y)
    n = torch.linalg.cross(dx, dy, dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp(min=1e-9)
    n = torch.where((n * points).sum(-1, keepdim=True) > 0, -n, n)
    return n.permute(0, 3, 1, 2)


def box_radiance(room: dict, batch_index: torch.Tensor, origin: torch.Tensor, wi: torch.Tensor, far=None):
    """Radiance (N, 3) where rays origin + t wi (N, 3), view space, of images batch_index (N,) leave the box
    of `room` (rotation (B, 3, 3), lo, hi (B, 3), textures (B, 6, 4, T, T): radiance and opacity):
    opacity * face radiance + (1 - opacity) * far, far (N, 3) the distant light behind (None: nothing)."""
    rot = room["rotation"][batch_index].to(wi.dtype)
    q = (origin.unsqueeze(1) @ rot)[:, 0]
    d = (wi.unsqueeze(1) @ rot)[:, 0]
    lo, hi = room["lo"][batch_index].to(wi.dtype), room["hi"][batch_index].to(wi.dtype)
    face, st, _ = exit_face(q, d, lo, hi)
    textures = room["textures"]
    tex = texel_lookup(textures.flatten(0, 1), batch_index * 6 + face, st.to(textures.dtype))
    rgb, opacity = tex[:, :3], tex[:, 3:]
    return rgb if far is None else opacity * rgb + (1 - opacity) * far


class RoomBoxBranch(nn.Module):
    """backbone: the encoder (`material_net.ENCODERS`); grid: (rows, cols) the last feature map is pooled
    to; code_dim: the global code's width; texture_size: texels per face side; channels: the decoder's
    width; layout: `predicted` (from normals and depth) or `gt` (`encode(box=...)`); unseen_fraction,
    plane_tolerance: `ops.roombox`; coverage_pixels: pixels per texel at which the observation counts
    1 - 1/e; far_field, dir_frequencies: the distant map behind transparent texels."""

    kind = "roombox"
    bounds = None

    def __init__(
        self,
        backbone: str = "small",
        grid: tuple[int, int] = (3, 4),
        code_dim: int = 128,
        texture_size: int = 32,
        channels: int = 32,
        layout: str = "predicted",
        unseen_fraction=(0.6, 1.0, 0.25),
        plane_tolerance: float = 0.15,
        coverage_pixels: float = 1.0,
        far_field: bool = True,
        dir_frequencies: int = 4,
        unseen: str = "prior",
    ):
        super().__init__()
        if unseen not in UNSEEN:
            raise ValueError(f"model.light_net.out_of_view.roombox.unseen={unseen!r}: choose one of {UNSEEN}")
        if layout not in LAYOUTS:
            raise ValueError(f"model.light_net.out_of_view.roombox.layout={layout!r}: choose one of {LAYOUTS}")
        if int(texture_size) < SEED_SIZE or int(texture_size) % SEED_SIZE:
            raise ValueError(
                f"model.light_net.out_of_view.roombox.texture_size={texture_size}: a positive multiple of {SEED_SIZE}"
            )
        if not coverage_pixels > 0:
            raise ValueError(f"model.light_net.out_of_view.roombox.coverage_pixels={coverage_pixels}: must be > 0")
        self.encoder = _encoder(backbone)
        self.grid = (int(grid[0]), int(grid[1]))
        width = self.encoder.channels[-1] * self.grid[0] * self.grid[1]
        self.to_code = nn.Sequential(nn.Linear(width, int(code_dim)), nn.ReLU())
        self.texture_size, self.channels, self.layout = int(texture_size), int(channels), layout
        self.unseen_fraction, self.plane_tolerance = tuple(float(f) for f in unseen_fraction), float(plane_tolerance)
        self.coverage_pixels, self.dir_frequencies = float(coverage_pixels), int(dir_frequencies)
        self.seed = nn.Linear(int(code_dim), 6 * self.channels * SEED_SIZE * SEED_SIZE)
        c = self.channels
        self.refine = nn.Sequential(
            nn.Conv2d(c + 4, c, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(c, c, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(c, 4, 3, padding=1),
        )
        with torch.no_grad():  # start opaque (sigmoid(3) = 0.95) at one image mean
            self.refine[-1].bias.copy_(torch.tensor([0.0, 0.0, 0.0, 3.0]))
        self.far = mlp_stack(int(code_dim) + fourier_dim(3, self.dir_frequencies), [64, 64], 3) if far_field else None
        self.unseen_scale = None
        if unseen == "learnt":  # log-scales of the six faces' distances, zero at the start (the prior)
            self.unseen_scale = nn.Linear(int(code_dim), 6)
            nn.init.zeros_(self.unseen_scale.weight)
            nn.init.zeros_(self.unseen_scale.bias)

    def encode(self, im, unit, depth, fov_x, normal=None, normalise: bool = True, box=None) -> dict:
        """Per-image room: im (B, 3, H, W) HDR; unit (B,) what radiance is divided by; depth (B, H, W)
        z-depth metres (0 / non-finite: none); fov_x degrees; normal (B, 3, H, W) view space (None: from
        the depth); box (rotation (B, 3, 3), lo, hi (B, 3)) the true layout (layout gt). Returns code
        (B, code_dim), rotation, lo, hi and textures (B, 6, 4, T, T) (radiance in units, opacity)."""
        x = normalize_input(im) if normalise else im.clamp(min=0)
        fmap = self.encoder(x)[-1]
        code = self.to_code(F.adaptive_avg_pool2d(fmap, self.grid).flatten(1))
        with torch.no_grad():  # the layout and the observation are geometry, not learnt
            depth = depth.detach()
            valid = torch.isfinite(depth) & (depth > 0)
            if self.layout == "gt" or box is not None:
                if box is None:
                    raise ValueError("out_of_view.roombox.layout=gt: encode needs box=(rotation, lo, hi)")
                rotation, lo, hi = (t.to(im.device, im.dtype) for t in box)
            else:
                points = backproject_views(torch.where(valid, depth, torch.zeros_like(depth)), fov_x)
                n = normals_from_depth(points) if normal is None else normal.detach()
                normal = n  # the observation's inward-facing test uses the same normals
                rotation = rotation_from_normals(n, valid)
                lo, hi, seen_lo, seen_hi = extents_from_points(
                    points, valid, rotation, n, unseen_fraction=self.unseen_fraction, return_seen=True
                )
            photo = im.detach().clamp(min=0) / unit.view(-1, 1, 1, 1)
            obs, count = observed_textures(
                photo, depth, fov_x, rotation, lo, hi, self.texture_size, normal, self.plane_tolerance
            )
            coverage = 1 - torch.exp(-count / self.coverage_pixels)
        if self.unseen_scale is not None and self.layout == "predicted" and box is None:
            # faces by index 2 * axis + side: the scale moves only the faces that were not seen
            scale = torch.exp(self.unseen_scale(code).clamp(-2.0, 2.0)).view(-1, 3, 2)
            lo = torch.where(seen_lo, lo, lo * scale[..., 0])
            hi = torch.where(seen_hi, hi, hi * scale[..., 1])
        B, T, c = im.shape[0], self.texture_size, self.channels
        seed = self.seed(code).view(B * 6, c, SEED_SIZE, SEED_SIZE)
        seed = F.interpolate(seed, size=(T, T), mode="bilinear", align_corners=False)
        seen_in = torch.cat([torch.log1p(obs), coverage], 2).flatten(0, 1)
        raw = self.refine(torch.cat([seed, seen_in], 1)).view(B, 6, 4, T, T)
        decoded = torch.exp(raw[:, :, :3].clamp(max=EXP_MAX))
        radiance = coverage * obs + (1 - coverage) * decoded
        textures = torch.cat([radiance, torch.sigmoid(raw[:, :, 3:])], 2)
        return {"code": code, "rotation": rotation, "lo": lo, "hi": hi, "textures": textures}

    def query(self, room: dict, scale, batch_index, origin, wi) -> torch.Tensor:
        """Radiance (N, 3) of rays origin, wi (N, 3) view space of images batch_index (N,), times scale (B,)."""
        far = None
        if self.far is not None:
            d = (wi.unsqueeze(1) @ room["rotation"][batch_index].to(wi.dtype))[:, 0]  # the room's frame
            raw = self.far(torch.cat([room["code"][batch_index], fourier(d, self.dir_frequencies)], -1))
            far = torch.exp(raw.clamp(max=EXP_MAX))
        return box_radiance(room, batch_index, origin, wi, far) * scale[batch_index].unsqueeze(-1)
