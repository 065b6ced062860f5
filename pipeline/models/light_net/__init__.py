"""LightNet: spatially-varying incident radiance L_i(p, wi) from one image (docs/design.md, section 5).

For a ray from surface point p along wi, screen-space ray tracing finds where it lands in the image; the
local branch predicts the radiance leaving that pixel, the out-of-view branch volume-renders a
per-image NeRF. They are blended with the SSRT confidence: L = (1 - u) L_ssrt + u L_out, u = tanh(k gap),
u = 1 for misses.

Modes: `mixed` (the paper), `ssrt_only` (misses get no light), `out_of_view_only`. Compute follows need:
in `mixed` the out-of-view branch is queried only for rays with u >= `out_threshold`; below it a ray
keeps L_ssrt alone (its u < threshold share of L_out is dropped). `out_threshold=0` queries every ray.

Out-of-view kinds (`out_of_view.kind`): `nerf` (the paper: a hypernetwork NeRF, `branches.OutOfViewBranch`)
or `roombox` (textures on the room's box, `roombox.RoomBoxBranch`); the nerf keys of `out_of_view` are read
by `nerf` only, the `roombox` block by `roombox` only (with the shared `backbone`, `far_field`,
`dir_frequencies`).

gap_units: the depth gap in u = tanh(k gap) is in `metres` (this project) or `window` (the released
code: OpenGL window depth of the view divided by its largest depth, so k = 10 means what it meant there;
`pipeline.ops.camera.window_depth_difference`).
"""

from __future__ import annotations

import torch
from torch import nn

from pipeline.models.light_net.branches import LocalBranch, OutOfViewBranch, image_scale
from pipeline.models.light_net.roombox import RoomBoxBranch
from pipeline.ops import ssrt
from pipeline.ops.brdf import f0
from pipeline.ops.camera import depth_range, window_depth_difference
from pipeline.ops.volume import scene_bounds

MODES = ("mixed", "ssrt_only", "out_of_view_only")
GAP_UNITS = ("metres", "window")
# image_mean: the encoders see the log-mean-normalised image and radiance is predicted in units of the image
# mean (exposure-invariant); absolute: the released LightNet's convention, the raw HDR image in and radiance
# in the image's own units out (what `invrender import-released lightnet` exports)
UNITS = ("image_mean", "absolute")
OUT_OF_VIEW_KINDS = ("nerf", "roombox")
SHARED_OUT_OF_VIEW_KEYS = ("backbone", "far_field", "dir_frequencies")  # what roombox reads beside its block


def blend(l_ssrt: torch.Tensor, l_out: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """(1 - u) L_ssrt + u L_out for (N, 3) radiances and (N,) weights in [0, 1]."""
    u = u.unsqueeze(-1)
    return (1 - u) * l_ssrt + u * l_out


def confidence(hit: torch.Tensor, gap: torch.Tensor, k: float) -> torch.Tensor:
    """u = tanh(k gap) for SSRT hits, 1 for misses; (N,)."""
    return torch.where(hit, torch.tanh(k * gap), torch.ones_like(gap))


class LightNet(nn.Module):
    def __init__(
        self,
        mode: str = "mixed",
        k: float = 10.0,
        out_threshold: float = 0.0,
        local: dict | None = None,
        out_of_view: dict | None = None,
        ssrt_compiled: bool = False,
        gap_units: str = "metres",
        units: str = "image_mean",
    ):
        super().__init__()
        if mode not in MODES:
            raise ValueError(f"model.light_net.mode={mode!r}: choose one of {MODES}")
        if units not in UNITS:
            raise ValueError(f"model.light_net.units={units!r}: choose one of {UNITS}")
        self.units = units
        if gap_units not in GAP_UNITS:
            raise ValueError(f"model.light_net.gap_units={gap_units!r}: choose one of {GAP_UNITS}")
        self.gap_units = gap_units
        if not 0.0 <= out_threshold <= 1.0:
            raise ValueError(f"model.light_net.out_threshold={out_threshold}: must be in [0, 1]")
        self.mode, self.k, self.out_threshold, self.ssrt_compiled = mode, float(k), float(out_threshold), ssrt_compiled
        self.local = LocalBranch(**(local or {})) if mode != "out_of_view_only" else None
        self.out_of_view = out_of_view_branch(out_of_view) if mode != "ssrt_only" else None

    def encode(self, im: torch.Tensor, depth: torch.Tensor, fov_x, normal=None, box=None) -> dict:
        """Per-image context: im (B, 3, H, W) HDR, depth (B, H, W) z-depth metres, fov_x float or (B,);
        normal (B, 3, H, W) view space, read by the roombox branch (None: it derives them from the depth);
        box (rotation (B, 3, 3), lo, hi (B, 3)): the true room box for the roombox branch's `layout: gt`."""
        # scale: the image's exposure (what losses and metrics normalise by); unit: what the branches'
        # outputs are multiplied by, the same in image_mean units and 1 in absolute ones
        normalise = self.units == "image_mean"
        scale = image_scale(im)
        ctx = {"scale": scale, "unit": scale if normalise else torch.ones_like(scale), "size": im.shape[-2:]}
        bounds = self.out_of_view.bounds if self.out_of_view is not None else None
        if bounds == "box":  # the context holds only what the configured branches read
            ctx["bounds"] = scene_bounds(depth, fov_x)
        if self.gap_units == "window" or bounds == "sphere":
            ctx["depth_min"], ctx["depth_max"] = depth_range(depth)
        if self.local is not None:
            ctx["local"] = self.local.encode(im, normalise)
            ctx["image"] = im.clamp(min=0) / ctx["unit"].view(-1, 1, 1, 1)
        if isinstance(self.out_of_view, RoomBoxBranch):
            ctx["room"] = self.out_of_view.encode(im, ctx["unit"], depth, fov_x, normal, normalise, box)
            ctx["feature"], ctx["params"] = ctx["room"]["code"], None
        elif self.out_of_view is not None:
            ctx["feature"], ctx["params"] = self.out_of_view.encode(im, normalise)
        return ctx

    def forward(self, ctx: dict, gbuffer: dict, fov_x, origin, wi, batch_index, generator=None) -> dict:
        """Incident radiance for N rays. fov_x: degrees, one float or (B,) per view; gbuffer: depth (B, H, W)
        z-depth metres, normal (B, 3, H, W),
        albedo (B, 3, H, W), material (B, 2, H, W); origin, wi (N, 3) view space; batch_index (N,) long.
        Returns radiance (N, 3), u (N,), hit (N,) and out_queries (number of out-of-view evaluations)."""
        N = len(wi)
        pixel, hit, gap = trace_views(gbuffer, fov_x, origin.detach(), wi.detach(), batch_index, self.ssrt_compiled)
        if self.gap_units == "window":
            gap = self._window_gap(ctx, gbuffer["depth"], pixel, hit, gap, batch_index)
        u = confidence(hit, gap.to(wi.dtype), self.k)
        l_ssrt = wi.new_zeros(N, 3)
        if self.local is not None and hit.any():
            h = torch.nonzero(hit).squeeze(-1)
            b, px = batch_index[h], pixel[h]
            gb = _gbuffer_at(gbuffer, b, px)
            l_ssrt = l_ssrt.index_put(
                (h,), self.local.query(ctx["local"], ctx["unit"], b, px, ctx["size"], wi[h], gb, ctx["image"])
            )
        if self.mode == "ssrt_only":
            return {"radiance": l_ssrt, "u": u, "hit": hit, "out_queries": 0}
        need = torch.ones_like(hit) if self.mode == "out_of_view_only" else u >= self.out_threshold
        q = torch.nonzero(need).squeeze(-1)
        l_out = wi.new_zeros(N, 3)
        if q.numel():
            l_out = l_out.index_put((q,), self.out_of_view_radiance(ctx, batch_index[q], origin[q], wi[q], generator))
        if self.mode == "out_of_view_only":
            radiance = l_out
        else:
            radiance = torch.where(need.unsqueeze(-1), blend(l_ssrt, l_out, u), l_ssrt)
        return {"radiance": radiance, "u": u, "hit": hit, "out_queries": int(q.numel())}

    def out_of_view_radiance(self, ctx: dict, batch_index, origin, wi, generator=None) -> torch.Tensor:
        """The out-of-view branch's radiance (N, 3) for rays origin, wi (N, 3) of images batch_index (N,)."""
        if isinstance(self.out_of_view, RoomBoxBranch):
            return self.out_of_view.query(ctx["room"], ctx["unit"], batch_index, origin, wi)
        return self.out_of_view.query(
            ctx["feature"],
            ctx["params"],
            ctx["unit"],
            ctx.get("bounds"),
            batch_index,
            origin,
            wi,
            generator,
            depth_max=ctx.get("depth_max"),
        )

    @staticmethod
    def _window_gap(ctx, depth, pixel, hit, gap, batch_index) -> torch.Tensor:
        """Metric gaps (N,) of hits -> window-depth gaps (misses keep theirs; u = 1 for them anyway)."""
        h = torch.nonzero(hit).squeeze(-1)
        if not h.numel():
            return gap
        b = batch_index[h]
        z_s = depth[b, pixel[h, 0], pixel[h, 1]].to(gap.dtype)
        win = window_depth_difference(z_s, z_s + gap[h], ctx["depth_min"][b], ctx["depth_max"][b])
        return gap.index_put((h,), win.to(gap.dtype))


def out_of_view_branch(config: dict | None):
    """The out-of-view branch `config["kind"]` names (default nerf), built from the keys that kind reads."""
    config = dict(config or {})
    kind = config.pop("kind", "nerf")
    roombox = dict(config.pop("roombox", None) or {})
    if kind not in OUT_OF_VIEW_KINDS:
        raise ValueError(f"model.light_net.out_of_view.kind={kind!r}: choose one of {OUT_OF_VIEW_KINDS}")
    if kind == "nerf":
        return OutOfViewBranch(**config)
    shared = {k: config[k] for k in SHARED_OUT_OF_VIEW_KEYS if k in config}
    return RoomBoxBranch(**shared, **roombox)


def trace_views(gbuffer: dict, fov_x, origin, wi, batch_index, compiled: bool = False):
    """ssrt.trace for a batch whose views may differ in FOV (one trace per distinct FOV)."""
    if not torch.is_tensor(fov_x) or fov_x.ndim == 0:
        return ssrt.trace(gbuffer["depth"], gbuffer["normal"], float(fov_x), origin, wi, batch_index, compiled=compiled)
    N = len(wi)
    pixel = torch.full((N, 2), -1, dtype=torch.long, device=wi.device)
    hit = torch.zeros(N, dtype=torch.bool, device=wi.device)
    gap = torch.zeros(N, dtype=gbuffer["depth"].dtype, device=wi.device)
    per_ray = fov_x.to(wi.device)[batch_index]
    for f in torch.unique(fov_x).tolist():
        sel = torch.nonzero(per_ray == f).squeeze(-1)
        if sel.numel():
            p, h, g = ssrt.trace(
                gbuffer["depth"], gbuffer["normal"], f, origin[sel], wi[sel], batch_index[sel], compiled=compiled
            )
            pixel[sel], hit[sel], gap[sel] = p, h, g
    return pixel, hit, gap


def _gbuffer_at(gbuffer: dict, b: torch.Tensor, px: torch.Tensor) -> torch.Tensor:
    """(N, 10) Kd, Ks, normal, roughness at pixels px (N, 2) (row, col) of images b (N,)."""

    def at(x):
        return x[b, :, px[:, 0], px[:, 1]]

    albedo, mat = at(gbuffer["albedo"]), at(gbuffer["material"])
    rough, metal = mat[:, :1], mat[:, 1:2]
    kd = (1 - metal) * albedo
    ks = f0(albedo, metal)
    return torch.cat([kd, ks, at(gbuffer["normal"]), rough], -1)


def load_light_export(path) -> tuple[LightNet, dict]:
    """(LightNet in eval mode, export dict: light_net, ...) of a `models.export` LightNet export."""
    from pipeline.models.export import LIGHT_FORMAT, build_from_export, read_export

    blob = read_export(path, LIGHT_FORMAT)
    return build_from_export(path, LightNet, blob["light_net"], blob["state_dict"]), blob
