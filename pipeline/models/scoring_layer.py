"""`ScoringLayer`: the render layer's re-render of chosen pixels, estimated at converged noise for
scoring (`ops.scoring_mc`: Sobol samples, an optional light guide; no gradients). The `edit` stage and the
benches that score insertion render every row with it; training keeps `MCRenderLayer`."""

from __future__ import annotations

import torch

from pipeline.models.render_layer import PointRadianceFn
from pipeline.ops import scoring_mc
from pipeline.ops.camera import RAY_OFFSET_M, backproject_views


class ScoringLayer:
    """spp: samples per pixel; chunk: samples per radiance call (bounds memory). Samples the BRDF by
    importance, as `MCRenderLayer(estimator="importance")`."""

    def __init__(self, spp: int, chunk: int = 1 << 16):
        if spp < 1:
            raise ValueError(f"spp={spp}: must be >= 1")
        self.spp, self.chunk = int(spp), int(chunk)

    def render_pixels(
        self,
        gbuffer: dict[str, torch.Tensor],
        fov_x,
        pixels: torch.Tensor,
        radiance: PointRadianceFn,
        generator: torch.Generator,
        guide=None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Re-render flat pixel indices (M,) (into B*H*W) of G-buffers (depth (B, H, W) z-depth metres,
        normal/albedo (B, 3, H, W), material (B, 2, H, W) roughness+metallic; fov_x degrees) as
        `MCRenderLayer.render_pixels` does (shading points back-projected, secondary rays RAY_OFFSET_M
        above them), `generator` drawing the estimate's seed and `guide` (`ops.guide.SphereGuide`, view
        space) sampled beside the BRDF. Returns (rgb (M, 3), image index (M,))."""
        B, _, H, W = gbuffer["normal"].shape
        b = pixels // (H * W)
        rc = pixels % (H * W)
        row, col = rc // W, rc % W
        pts = backproject_views(gbuffer["depth"], fov_x)[b, row, col]
        normal = torch.nn.functional.normalize(gbuffer["normal"][b, :, row, col], dim=-1)
        origin = pts + RAY_OFFSET_M * normal
        mat = gbuffer["material"][b, :, row, col]
        wo = torch.nn.functional.normalize(-pts, dim=-1)
        seed = int(torch.randint(0, 1 << 30, (1,), generator=generator))
        rgb = scoring_mc.estimate(
            lambda k, wi: radiance(k, origin[k], wi, b[k]),
            normal,
            wo,
            gbuffer["albedo"][b, :, row, col],
            mat[:, 0],
            mat[:, 1],
            self.spp,
            seed,
            guide,
            self.chunk,
        )
        return rgb, b
