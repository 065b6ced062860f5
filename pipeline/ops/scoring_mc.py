"""Low-noise Monte Carlo of reflected radiance for scoring (no gradients): the estimate the `edit` stage
scores every row with, so that each row's PSNR is converged rather than lowered by its noise (noise
lowers a sharp light's PSNR more than a blurred one's).

Two things make it converge at far fewer samples than `mc.estimate`'s independent BRDF samples:
- A pixel's samples are the points of one scrambled Sobol sequence, shifted mod 1 by a random offset of
  the pixel's own (a randomised quasi-Monte Carlo rule: unbiased, each pixel independent of the others).
- With a `guide` (`ops.guide.SphereGuide`, a map resembling the light), each sample takes the guide's
  direction with probability GUIDE_FRACTION and the BRDF mixture's (`sampling.sample`) otherwise, and is
  weighted by the mixture of both densities at the direction taken (one-sample multiple importance
  sampling, balance heuristic): unbiased for any guide, since the BRDF mixture reaches every direction
  the BRDF does.
The BRDF (`brdf.evaluate`) and its sampler are the render layer's, so an estimate converges to the same
value as `mc.estimate` of the same light.
"""

from __future__ import annotations

import torch

from pipeline.ops import brdf, sampling
from pipeline.ops.mc import RadianceFn, counter_uniform

GUIDE_FRACTION = 0.5  # share of a guided estimate's samples drawn from the guide
DIMS = 4  # numbers per sample: the lobe (or texel), two for the direction, the strategy


def sobol_points(count: int, seed: int) -> torch.Tensor:
    """(count, DIMS) float64 points of a scrambled Sobol sequence (`seed` scrambles it)."""
    return torch.quasirandom.SobolEngine(DIMS, scramble=True, seed=int(seed)).draw(int(count), dtype=torch.float64)


def _directions(u, normal, wo, albedo, roughness, metallic, guide) -> tuple[torch.Tensor, torch.Tensor]:
    """wi (M, 3) and its density (M,): the BRDF mixture's sample, or with a guide the one-sample MIS of
    the guide and the BRDF. Where the BRDF has nothing to sample (wo below the horizon) the density is 0."""
    wi, p = sampling.sample(u[:, :3], normal, wo, albedo, roughness, metallic)
    if guide is None:
        return wi, p
    nothing = p <= 0
    from_guide = (u[:, 3] < GUIDE_FRACTION) & ~nothing
    wi = torch.where(from_guide[:, None], guide.sample(u[:, :3]), torch.where(nothing[:, None], normal, wi))
    mix = GUIDE_FRACTION * guide.pdf(wi) + (1 - GUIDE_FRACTION) * sampling.pdf(
        normal, wo, wi, albedo, roughness, metallic
    )
    return wi, torch.where(nothing, torch.zeros_like(mix), mix)


@torch.no_grad()
def estimate(
    radiance_fn: RadianceFn,
    normal: torch.Tensor,
    wo: torch.Tensor,
    albedo: torch.Tensor,
    roughness: torch.Tensor,
    metallic: torch.Tensor,
    spp: int,
    seed: int,
    guide=None,
    chunk: int = 1 << 16,
) -> torch.Tensor:
    """Reflected radiance (N, 3) at N shading points, `spp` samples each.

    normal, wo (N, 3) unit (view space); albedo (N, 3); roughness, metallic (N,); radiance_fn(point index
    (M,), wi (M, 3)) -> L_i (M, 3); seed: scrambles the sequence and draws the pixels' offsets; guide: an
    `ops.guide.SphereGuide` of the light, or None (BRDF sampling alone); chunk: samples per call of
    radiance_fn (bounds memory; the result does not depend on it)."""
    if spp < 1:
        raise ValueError(f"spp={spp}: at least 1 sample per point")
    N = normal.shape[0]
    points = sobol_points(spp, seed).to(normal.device)
    offsets = counter_uniform(seed, torch.arange(N, device=normal.device), DIMS)
    total = torch.zeros(N, 3, dtype=normal.dtype, device=normal.device)
    for start in range(0, N * spp, chunk):
        sample = torch.arange(start, min(N * spp, start + chunk), device=normal.device)
        pix, k = sample // spp, sample % spp
        u = torch.remainder(points[k] + offsets[pix], 1.0).to(normal.dtype)
        n, o, a, r, m = normal[pix], wo[pix], albedo[pix], roughness[pix], metallic[pix]
        wi, p = _directions(u, n, o, a, r, m, guide)
        f_d, f_s = brdf.evaluate(n, o, wi, a, r, m)
        cos = (n * wi).sum(-1).clamp(min=0)
        w = torch.where(p > 0, cos / torch.where(p > 0, p, torch.ones_like(p)), torch.zeros_like(cos))
        total.index_add_(0, pix, (f_d + f_s) * radiance_fn(pix, wi) * w[:, None])
    return total / spp
