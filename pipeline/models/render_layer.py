"""`MCRenderLayer`: the differentiable Monte Carlo render layer over image G-buffers."""

from __future__ import annotations

from collections.abc import Callable, Mapping

import torch
from torch import nn

from pipeline.ops import mc
from pipeline.ops.camera import RAY_OFFSET_M, backproject_views, pixel_directions

# radiance(pixel index into the flattened (B, H, W) grid (M,), wi (M, 3) view space) -> L_i (M, 3)
ImageRadianceFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
# radiance(point index (K,), origin (K, 3), wi (K, 3), image index (K,)) -> L_i (K, 3), all view space
PointRadianceFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


class MCRenderLayer(nn.Module):
    """Re-renders G-buffers under an incident-radiance callback: the one render path of the project
    (training, baselines, evaluation and figures), configured by `conf/render/`.

    estimator: importance | uniform | li2020; spp: samples per valid pixel; adaptive: distribute
    spp x #valid samples by BRDF lobe (`mc.allocate_samples`) instead of evenly; li_size: (n_theta,
    n_phi) of the li2020 grid; chunk: samples per chunk (bounds memory); checkpoint_chunks: recompute
    chunks in backward (None: only when a render has more than one, `mc.estimate`)."""

    def __init__(
        self,
        estimator: str = "importance",
        spp: int = 16,
        adaptive: bool = False,
        li_size: tuple[int, int] = (8, 16),
        chunk: int = 1 << 16,
        checkpoint_chunks: bool | None = None,
    ):
        super().__init__()
        if estimator not in mc.ESTIMATORS:
            raise ValueError(f"render.estimator={estimator!r}: choose one of {mc.ESTIMATORS}")
        if spp < 1:
            raise ValueError(f"render.spp={spp}: must be >= 1")
        self.estimator, self.spp, self.adaptive = estimator, int(spp), bool(adaptive)
        self.li_size, self.chunk = tuple(li_size), int(chunk)
        self.checkpoint_chunks = checkpoint_chunks

    @classmethod
    def from_config(cls, render: Mapping, spp_key: str = "spp") -> MCRenderLayer:
        """The layer the `conf/render/` group describes (estimator, adaptive, li_size, chunk), at
        render[spp_key] samples per pixel (`spp` for training, `eval_spp` for evaluation)."""
        return cls(
            estimator=str(render["estimator"]),
            spp=int(render[spp_key]),
            adaptive=bool(render.get("adaptive", False)),
            li_size=tuple(render.get("li_size", (8, 16))),
            chunk=int(render.get("chunk", 1 << 16)),
        )

    def forward(
        self,
        normal: torch.Tensor,
        albedo: torch.Tensor,
        roughness: torch.Tensor,
        metallic: torch.Tensor,
        mask: torch.Tensor,
        fov_x: float,
        radiance: ImageRadianceFn,
        generator: torch.Generator,
    ) -> dict[str, torch.Tensor]:
        """normal/albedo (B, 3, H, W), roughness/metallic/mask (B, 1, H, W), fov_x degrees; `generator`
        draws the sample directions (`mc.estimate`). Returns diffuse, specular, rgb (B, 3, H, W) (0 outside
        the mask) and counts (B, 1, H, W)."""
        B, _, H, W = normal.shape
        flat = lambda x: x.permute(0, 2, 3, 1).reshape(B * H * W, -1)  # noqa: E731
        valid = flat(mask).reshape(-1) > 0.5
        idx = torch.nonzero(valid).squeeze(-1)
        view = pixel_directions(H, W, fov_x, normal.device, normal.dtype).reshape(1, H * W, 3).expand(B, -1, -1)
        wo = -torch.nn.functional.normalize(view.reshape(-1, 3), dim=-1)[idx]
        n = torch.nn.functional.normalize(flat(normal)[idx], dim=-1)
        a, r, m = flat(albedo)[idx], flat(roughness)[idx, 0], flat(metallic)[idx, 0]
        counts = self.sample_counts(a, r, m)

        def local_radiance(k: torch.Tensor, wi: torch.Tensor) -> torch.Tensor:
            return radiance(idx[k], wi)

        d, s = mc.estimate(
            local_radiance,
            n,
            wo,
            a,
            r,
            m,
            counts,
            generator,
            self.estimator,
            self.chunk,
            self.li_size,
            self.checkpoint_chunks,
        )
        out = {}
        for name, val in (("diffuse", d), ("specular", s)):
            img = torch.zeros(B * H * W, 3, dtype=val.dtype, device=val.device).index_copy(0, idx, val)
            out[name] = img.reshape(B, H, W, 3).permute(0, 3, 1, 2)
        out["rgb"] = out["diffuse"] + out["specular"]
        cnt = torch.zeros(B * H * W, dtype=torch.long, device=normal.device)
        cnt[idx] = counts
        out["counts"] = cnt.reshape(B, 1, H, W)
        return out

    def sample_counts(self, albedo: torch.Tensor, roughness: torch.Tensor, metallic: torch.Tensor) -> torch.Tensor:
        """Samples per shading point (N,) long: the li2020 grid's cell count, the BRDF-lobe allocation of
        spp x N samples (adaptive), or spp each."""
        N = albedo.shape[0]
        if self.estimator == "li2020":  # a fixed grid: one sample per cell
            return torch.full((N,), self.li_size[0] * self.li_size[1], dtype=torch.long, device=albedo.device)
        if self.adaptive:
            valid = torch.ones_like(roughness, dtype=torch.bool)
            return mc.allocate_samples(albedo, roughness, metallic, valid, self.spp * N)
        return torch.full((N,), self.spp, dtype=torch.long, device=albedo.device)

    def render_pixels(
        self,
        gbuffer: dict[str, torch.Tensor],
        fov_x,
        pixels: torch.Tensor,
        radiance: PointRadianceFn,
        generator: torch.Generator,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Re-render flat pixel indices (M,) (into B*H*W) of G-buffers: depth (B, H, W) z-depth metres,
        normal/albedo (B, 3, H, W), material (B, 2, H, W) roughness+metallic; fov_x degrees, one float or
        (B,). Shading points are the back-projected pixels; secondary rays start RAY_OFFSET_M above them
        along the normal; `generator` draws the sample directions. Returns (rgb (M, 3), image index (M,))."""
        B, _, H, W = gbuffer["normal"].shape
        b = pixels // (H * W)
        rc = pixels % (H * W)
        row, col = rc // W, rc % W
        pts = backproject_views(gbuffer["depth"], fov_x)[b, row, col]
        normal = torch.nn.functional.normalize(gbuffer["normal"][b, :, row, col], dim=-1)
        origin = pts + RAY_OFFSET_M * normal
        mat = gbuffer["material"][b, :, row, col]
        albedo, rough, metal = gbuffer["albedo"][b, :, row, col], mat[:, 0], mat[:, 1]
        wo = torch.nn.functional.normalize(-pts, dim=-1)
        diffuse, specular = mc.estimate(
            lambda k, wi: radiance(k, origin[k], wi, b[k]),
            normal,
            wo,
            albedo,
            rough,
            metal,
            self.sample_counts(albedo, rough, metal),
            generator,
            self.estimator,
            self.chunk,
            self.li_size,
            self.checkpoint_chunks,
        )
        return diffuse + specular, b
