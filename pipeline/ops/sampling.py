"""Direction samplers for the BRDF of `brdf.py`, each with the pdf of exactly what it draws.

Random numbers come in as tensors u in [0, 1); every pdf is a density over solid angle on the whole
sphere (directions below the horizon included: a specular sample can land there, and its BRDF value,
hence its contribution, is then zero).

GGX visible normals are drawn with the spherical-cap construction: stretch wo by alpha into the
configuration where the microsurface is a hemisphere, draw a point uniformly on the spherical cap of
the unit sphere cut off by the plane z = -wo_std.z (uniform z in that range, uniform azimuth), add
wo_std to get a visible normal of the hemisphere, then unstretch. Its density over half-vectors is
D_wo(h) = G1(wo) max(0, wo.h) D(h) / cos_o, so the reflected direction has pdf G1(wo) D(h) / (4 cos_o).
"""

from __future__ import annotations

import math

import torch

from pipeline.ops.brdf import alpha_from_roughness, f0, ggx_d, luminance, smith_g1
from pipeline.ops.frames import from_local, orthonormal_basis, to_local, unit

LOBE_MIN = 0.01  # each lobe is picked with probability at least this


def specular_probability(albedo: torch.Tensor, metallic: torch.Tensor) -> torch.Tensor:
    """k_s = lum(F0) / (lum((1-m) albedo) + lum(F0)), clamped to [LOBE_MIN, 1 - LOBE_MIN]; (N,)."""
    m = metallic.reshape(-1, 1)
    spec = luminance(f0(albedo, metallic))
    diff = luminance((1 - m) * albedo)
    ks = spec / (diff + spec).clamp(min=1e-12)
    return ks.clamp(LOBE_MIN, 1 - LOBE_MIN)


# ---- local-frame samplers (z = normal) -------------------------------------------------------------


def cosine_local(u1: torch.Tensor, u2: torch.Tensor) -> torch.Tensor:
    """Cosine-weighted hemisphere directions (N, 3); pdf = z / pi."""
    r = torch.sqrt(u1)
    phi = 2 * math.pi * u2
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), torch.sqrt((1 - u1).clamp(min=0))], -1)


def uniform_local(u1: torch.Tensor, u2: torch.Tensor) -> torch.Tensor:
    """Uniform hemisphere directions (N, 3); pdf = 1 / (2 pi)."""
    z = u1
    r = torch.sqrt((1 - z * z).clamp(min=0))
    phi = 2 * math.pi * u2
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


def vndf_local(wo: torch.Tensor, alpha: torch.Tensor, u1: torch.Tensor, u2: torch.Tensor) -> torch.Tensor:
    """GGX visible-normal half-vectors (N, 3) for local wo (N, 3) with wo.z > 0, isotropic alpha (N,)."""
    a = alpha.unsqueeze(-1)
    v = unit(torch.cat([wo[:, :2] * a, wo[:, 2:]], -1))
    phi = 2 * math.pi * u1
    z = (1 - u2) * (1 + v[:, 2]) - v[:, 2]
    s = torch.sqrt((1 - z * z).clamp(min=0))
    h = torch.stack([s * torch.cos(phi), s * torch.sin(phi), z], -1) + v
    return unit(torch.cat([h[:, :2] * a, h[:, 2:].clamp(min=0)], -1))


def specular_pdf_local(wo: torch.Tensor, wi: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Density (N,) over wi of reflecting wo about a visible normal: G1(wo) D(h) / (4 cos_o)."""
    h = unit(wo + wi)
    cos_o = wo[:, 2]
    ok = (cos_o > 0) & (h[:, 2] > 0) & ((wo * h).sum(-1) > 0)
    pdf = smith_g1(cos_o, alpha) * ggx_d(h[:, 2], alpha) / (4 * cos_o.clamp(min=1e-12))
    return torch.where(ok, pdf, torch.zeros_like(pdf))


def diffuse_pdf_local(wi: torch.Tensor) -> torch.Tensor:
    return wi[:, 2].clamp(min=0) / math.pi


def _mixture_pdf_local(wo, wi, alpha, p_spec) -> torch.Tensor:
    """Density (N,) of the k_s mixture at local wi; 0 where wo is below the horizon (nothing is sampled)."""
    p = p_spec * specular_pdf_local(wo, wi, alpha) + (1 - p_spec) * diffuse_pdf_local(wi)
    return torch.where(wo[:, 2] > 0, p, torch.zeros_like(p))


# ---- the BRDF sampler (stable entry points) --------------------------------------------------------


def sample(u, normal, wo, albedo, roughness, metallic) -> tuple[torch.Tensor, torch.Tensor]:
    """Draw wi (N, 3) from the mixture of the GGX visible-normal lobe (probability k_s) and the cosine
    lobe, with its mixture pdf (N,). u (N, 3) uniform in [0, 1): u[:, 0] picks the lobe, u[:, 1:]
    the direction. Where wo is below the horizon there is nothing to sample: pdf = 0."""
    t, b = orthonormal_basis(normal)
    wo_l = to_local(wo, t, b, normal)
    alpha = alpha_from_roughness(roughness)
    p_spec = specular_probability(albedo, metallic)
    h = vndf_local(wo_l, alpha, u[:, 1], u[:, 2])
    wi_spec = 2 * (wo_l * h).sum(-1, keepdim=True) * h - wo_l
    wi_diff = cosine_local(u[:, 1], u[:, 2])
    wi_l = torch.where((u[:, 0] < p_spec).unsqueeze(-1), wi_spec, wi_diff)
    wi_l = unit(wi_l)
    return from_local(wi_l, t, b, normal), _mixture_pdf_local(wo_l, wi_l, alpha, p_spec)


def pdf(normal, wo, wi, albedo, roughness, metallic) -> torch.Tensor:
    """Mixture density (N,) over solid angle of `sample` drawing wi."""
    t, b = orthonormal_basis(normal)
    wo_l, wi_l = to_local(wo, t, b, normal), to_local(wi, t, b, normal)
    return _mixture_pdf_local(wo_l, wi_l, alpha_from_roughness(roughness), specular_probability(albedo, metallic))


def sample_uniform(u, normal) -> tuple[torch.Tensor, torch.Tensor]:
    """Uniform hemisphere around the normal: wi (N, 3) and pdf (N,) = 1 / (2 pi)."""
    t, b = orthonormal_basis(normal)
    wi = from_local(uniform_local(u[:, 1], u[:, 2]), t, b, normal)
    return wi, torch.full_like(u[:, 0], 1 / (2 * math.pi))


def sample_cosine(u, normal) -> tuple[torch.Tensor, torch.Tensor]:
    """Cosine-weighted hemisphere: wi (N, 3) and pdf (N,) = cos / pi."""
    t, b = orthonormal_basis(normal)
    wi_l = cosine_local(u[:, 1], u[:, 2])
    return from_local(wi_l, t, b, normal), diffuse_pdf_local(wi_l)
