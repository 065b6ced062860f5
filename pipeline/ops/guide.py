"""A direction distribution proportional to a full-sphere light map: the light-sampling half of the
guided estimator (`mc.estimate(..., guide=...)`), which converges where BRDF sampling alone meets a small
bright lamp (a diffuse surface under a ceiling panel needs thousands of BRDF samples, docs/experiments.md,
'Insertion scoring at converged noise').

The map is laid out as `envmap.sphere_directions` (view space). Texels are drawn with probability
proportional to their luminance times their solid angle, after a 3 x 3 maximum filter (periodic in the
azimuth) so that the bilinear lookup's spill of a bright texel into its neighbours is covered too; the
direction is uniform in solid angle inside the texel. The density is therefore piecewise constant over
texels. Any map gives an unbiased estimate once combined with BRDF sampling (multiple importance
sampling covers every direction the BRDF reaches); a map close to the light gives a low variance.
"""

from __future__ import annotations

import math

import torch

from pipeline.ops.brdf import luminance
from pipeline.ops.envmap import texel_directions, texel_solid_angles


class SphereGuide:
    """Sampling and density of directions from one sphere map.

    radiance: (rows, cols, 3) or (1, rows, cols, 3) non-negative, finite HDR radiance. A map without
    energy is refused (it cannot guide anything)."""

    def __init__(self, radiance: torch.Tensor):
        if radiance.ndim == 4 and radiance.shape[0] == 1:
            radiance = radiance[0]
        if radiance.ndim != 3 or radiance.shape[-1] != 3:
            raise ValueError(f"guide map of shape {tuple(radiance.shape)}: expected (rows, cols, 3)")
        if not torch.isfinite(radiance).all() or (radiance < 0).any():
            raise ValueError("guide map: radiance must be finite and non-negative")
        rows, cols, _ = radiance.shape
        lum = luminance(radiance.detach().double())  # (rows, cols)
        padded = torch.cat([lum[:, -1:], lum, lum[:, :1]], 1)  # periodic in phi
        padded = torch.nn.functional.pad(padded[None, None], (0, 0, 1, 1), mode="replicate")
        spread = torch.nn.functional.max_pool2d(padded, 3, stride=1)[0, 0]  # (rows, cols)
        omega = torch.as_tensor(texel_solid_angles(rows, cols, hemisphere=False), dtype=torch.float64)
        mass = (spread * omega[:, None]).reshape(-1)
        total = float(mass.sum())
        if not total > 0:
            raise ValueError("guide map: no energy to guide by")
        self.rows, self.cols = rows, cols
        self.texel_prob = mass / total  # (rows * cols,)
        self.cdf = torch.cumsum(self.texel_prob, 0)
        self.cdf[-1] = 1.0
        self.density = (self.texel_prob.reshape(rows, cols) / omega[:, None]).reshape(-1)  # per steradian

    def sample(self, u: torch.Tensor) -> torch.Tensor:
        """(M, 3) unit view-space directions from u (M, 3) uniform in [0, 1): u[:, 0] picks the texel,
        u[:, 1:] the point inside it."""
        k = torch.searchsorted(self.cdf.to(u.dtype), u[:, 0].contiguous(), right=True).clamp(max=self.cdf.numel() - 1)
        row, col = k // self.cols, k % self.cols
        return texel_directions(row, col, u[:, None, 1:], self.rows, self.cols)[:, 0]

    def pdf(self, wi: torch.Tensor) -> torch.Tensor:
        """(M,) density over solid angle of `sample` drawing the unit directions wi (M, 3)."""
        x, y, z = wi.unbind(-1)
        theta = torch.acos(y.clamp(-1, 1))
        phi = torch.atan2(x, -z) % (2 * math.pi)
        row = (theta / math.pi * self.rows).long().clamp(0, self.rows - 1)
        col = (phi / (2 * math.pi) * self.cols).long().clamp(0, self.cols - 1)
        return self.density.to(wi.dtype)[row * self.cols + col]
