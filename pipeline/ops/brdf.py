"""The paper's GGX microfacet BRDF in the metallic workflow (docs/design.md, section 5).

    alpha = roughness^2 (clamped to ALPHA_MIN, the same clamp the sampler and its pdf use)
    diffuse  = (1 - m) * albedo / pi
    F0 = lerp(0.04, albedo, m), F90 = min(1, 25 lum(F0)), F = F0 + (F90 - F0)(1 - wo.h)^5
    specular = D(h) * V(wo, wi) * F, V the height-correlated Smith visibility G2 / (4 n.wo n.wi)
All directions are unit vectors pointing away from the surface; shapes (N, 3) unless stated.
"""

from __future__ import annotations

import math

import torch

from pipeline.ops.frames import unit

ALPHA_MIN = 1e-4  # roughness 0.01: below it float32 GGX lobes are numerically a delta
LUMA = (0.2126, 0.7152, 0.0722)  # Rec. 709


def luminance(rgb: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (...)"""
    w = torch.tensor(LUMA, dtype=rgb.dtype, device=rgb.device)
    return (rgb * w).sum(-1)


def alpha_from_roughness(roughness: torch.Tensor) -> torch.Tensor:
    """(N,) or (N, 1) roughness -> (N,) GGX alpha = roughness^2, at least ALPHA_MIN."""
    return (roughness.reshape(-1) ** 2).clamp(min=ALPHA_MIN)


def f0(albedo: torch.Tensor, metallic: torch.Tensor) -> torch.Tensor:
    """Specular reflectance at normal incidence (N, 3): 0.04 for dielectrics, albedo for metals."""
    m = metallic.reshape(-1, 1)
    return 0.04 * (1 - m) + albedo * m


def ggx_d(cos_h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """GGX normal distribution D(h) for cos(theta_h) (N,) > 0; 0 where cos_h <= 0."""
    a2 = alpha * alpha
    c2 = cos_h.clamp(0, 1) ** 2
    # sin^2 + a^2 cos^2 rather than c^2 (a^2 - 1) + 1: in float32 a^2 - 1 rounds to -1 for tiny alpha and
    # the latter cancels to 0 at the lobe's peak; this form stays >= a^2 c^2 > 0
    denom = (1 - c2) + a2 * c2
    return torch.where(cos_h > 0, a2 / (math.pi * denom * denom), torch.zeros_like(cos_h))


def smith_g1(cos_v: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Smith masking G1 for GGX at cos(theta_v) (N,) in (0, 1]."""
    c = cos_v.clamp(min=0)
    a2 = alpha * alpha
    return 2 * c / (c + torch.sqrt(a2 + (1 - a2) * c * c)).clamp(min=1e-12)


def smith_visibility(cos_o: torch.Tensor, cos_i: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Height-correlated Smith visibility V = G2 / (4 cos_o cos_i) for cosines in (0, 1]."""
    a2 = alpha * alpha
    co, ci = cos_o.clamp(min=0), cos_i.clamp(min=0)
    lo = ci * torch.sqrt(co * co * (1 - a2) + a2)
    li = co * torch.sqrt(ci * ci * (1 - a2) + a2)
    return 0.5 / (lo + li).clamp(min=1e-12)


def evaluate(normal, wo, wi, albedo, roughness, metallic) -> tuple[torch.Tensor, torch.Tensor]:
    """BRDF values (diffuse (N, 3), specular (N, 3)), cosine not included, zero below either horizon.

    normal, wo, wi: (N, 3) unit; albedo (N, 3) linear; roughness, metallic (N,) or (N, 1) in [0, 1]."""
    m = metallic.reshape(-1, 1)
    alpha = alpha_from_roughness(roughness)
    cos_o = (normal * wo).sum(-1)
    cos_i = (normal * wi).sum(-1)
    above = (cos_o > 0) & (cos_i > 0)
    diffuse = (1 - m) * albedo / math.pi
    h = unit(wo + wi)
    cos_h = (normal * h).sum(-1)
    cos_oh = (wo * h).sum(-1).clamp(0, 1)
    spec_f0 = f0(albedo, metallic)
    f90 = (25 * luminance(spec_f0)).clamp(max=1).unsqueeze(-1)
    fresnel = spec_f0 + (f90 - spec_f0) * (1 - cos_oh).unsqueeze(-1) ** 5
    spec = (ggx_d(cos_h, alpha) * smith_visibility(cos_o, cos_i, alpha)).unsqueeze(-1) * fresnel
    zero = torch.zeros_like(diffuse)
    keep = above.unsqueeze(-1)
    return torch.where(keep, diffuse, zero), torch.where(keep, spec, zero)
