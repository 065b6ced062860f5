"""BRDF and samplers: chi-square goodness of fit, normalisation, reciprocity, energy, gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pipeline.ops import brdf, sampling
from tests.ops.sphere_quadrature import chi_square_pvalue, integrate_sphere

ROUGHNESS = (0.05, 0.3, 0.8, 1.0)
VIEW_DEG = (5.0, 45.0, 80.0)
METALLIC = (0.0, 1.0)
N_TESTS = len(ROUGHNESS) * len(VIEW_DEG) * len(METALLIC)
ALPHA_LEVEL = 1e-3 / N_TESTS  # Sidak-style: the whole family fails by chance with probability ~1e-3


def _setup(n, rough, view_deg, metal, albedo=0.6, dtype=torch.float64):
    th = math.radians(view_deg)
    normal = torch.tensor([[0.0, 0.0, 1.0]], dtype=dtype).expand(n, 3)
    wo = torch.tensor([[math.sin(th), 0.0, math.cos(th)]], dtype=dtype).expand(n, 3)
    alb = torch.tensor([[albedo, albedo * 0.8, albedo * 0.5]], dtype=dtype).expand(n, 3)
    return normal, wo, alb, torch.full((n,), rough, dtype=dtype), torch.full((n,), metal, dtype=dtype)


def _mirror(wo_row):
    n = torch.tensor([0.0, 0.0, 1.0], dtype=wo_row.dtype)
    return 2 * (wo_row @ n) * n - wo_row


@pytest.mark.parametrize("metal", METALLIC)
@pytest.mark.parametrize("view", VIEW_DEG)
@pytest.mark.parametrize("rough", ROUGHNESS)
def test_chi_square_mixture_sampler(rough, view, metal):
    n = 200_000
    gen = torch.Generator().manual_seed(hash((rough, view, metal)) % 2**31)
    normal, wo, alb, r, m = _setup(n, rough, view, metal)
    wi, p = sampling.sample(torch.rand(n, 3, generator=gen, dtype=torch.float64), normal, wo, alb, r, m)
    assert torch.isfinite(wi).all() and (p >= 0).all()

    def pdf_fn(d):
        k = d.shape[0]
        return sampling.pdf(
            normal[:1].expand(k, 3), wo[:1].expand(k, 3), d, alb[:1].expand(k, 3), r[:1].expand(k), m[:1].expand(k)
        )

    alpha = max(rough**2, brdf.ALPHA_MIN)
    pval, total = chi_square_pvalue(wi, pdf_fn, _mirror(wo[0]), inner=alpha / 10)
    assert abs(total - 1) < 2e-3, f"pdf integrates to {total}"
    assert pval > ALPHA_LEVEL, f"chi-square p = {pval:.2e}"
    np.testing.assert_allclose(p.numpy(), pdf_fn(wi).numpy(), rtol=1e-9)  # sample() reports pdf()


@pytest.mark.parametrize("name", ["cosine", "uniform"])
def test_chi_square_hemisphere_samplers(name):
    n = 100_000
    gen = torch.Generator().manual_seed(1)
    normal = torch.nn.functional.normalize(torch.tensor([[0.3, -0.5, 0.8]], dtype=torch.float64), dim=-1)
    u = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    fn = sampling.sample_cosine if name == "cosine" else sampling.sample_uniform
    wi, p = fn(u, normal.expand(n, 3))

    def pdf_fn(d):
        c = (d * normal).sum(-1)
        return torch.where(c > 0, c / math.pi if name == "cosine" else torch.full_like(c, 1 / (2 * math.pi)), 0 * c)

    pval, total = chi_square_pvalue(wi, pdf_fn, normal[0], inner=0.05, extra=(math.pi / 2,))
    assert abs(total - 1) < 1e-3 and pval > 1e-4


def test_reciprocity_and_horizons():
    gen = torch.Generator().manual_seed(2)
    n = 4096
    normal = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1)
    a = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1)
    b = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1)
    alb = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    r, m = torch.rand(n, generator=gen, dtype=torch.float64), torch.rand(n, generator=gen, dtype=torch.float64)
    d1, s1 = brdf.evaluate(normal, a, b, alb, r, m)
    d2, s2 = brdf.evaluate(normal, b, a, alb, r, m)
    torch.testing.assert_close(s1, s2, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(d1, d2)
    below = ((normal * a).sum(-1) <= 0) | ((normal * b).sum(-1) <= 0)
    assert below.any() and (d1[below] == 0).all() and (s1[below] == 0).all()


@pytest.mark.parametrize("rough", (0.01, 0.05, 0.3, 1.0))
@pytest.mark.parametrize("view", (0.0, 60.0, 89.0))
@pytest.mark.parametrize("metal", (0.0, 1.0))
def test_each_lobe_conserves_energy(rough, view, metal):
    """Directional albedo of each lobe <= 1 at the worst case (white albedo): diffuse = (1-m) albedo
    exactly, specular <= 1 (single-scatter microfacets lose energy). The paper's model adds the two lobes
    without a Fresnel weight on the diffuse one, so their sum may exceed 1 for white dielectrics."""
    normal, wo, alb, r, m = _setup(1, rough, view, metal, albedo=1.0)
    alb = torch.ones_like(alb)

    def f_cos(d, lobe):
        k = d.shape[0]
        fd, fs = brdf.evaluate(normal.expand(k, 3), wo.expand(k, 3), d, alb.expand(k, 3), r.expand(k), m.expand(k))
        return (fd if lobe == 0 else fs) * d[:, 2:].clamp(min=0)

    alpha = max(rough**2, brdf.ALPHA_MIN)
    diff = integrate_sphere(lambda d: f_cos(d, 0), _mirror(wo[0]), alpha / 10, sub=6)
    spec = integrate_sphere(lambda d: f_cos(d, 1), _mirror(wo[0]), alpha / 10, sub=6)
    np.testing.assert_allclose(diff, 1 - metal, atol=2e-3)
    assert (spec <= 1 + 2e-3).all(), spec


def test_gradcheck_brdf_float64():
    gen = torch.Generator().manual_seed(3)
    n = 6
    normal = torch.nn.functional.normalize(torch.tensor([[0.1, 0.2, 1.0]], dtype=torch.float64), dim=-1).expand(n, 3)
    wo = torch.nn.functional.normalize(
        torch.rand(n, 3, generator=gen, dtype=torch.float64) + torch.tensor([0, 0, 1.0]), dim=-1
    )
    wi = torch.nn.functional.normalize(
        torch.rand(n, 3, generator=gen, dtype=torch.float64) + torch.tensor([0, 0, 1.0]), dim=-1
    )
    alb = torch.rand(n, 3, generator=gen, dtype=torch.float64).requires_grad_()
    r = (0.2 + 0.7 * torch.rand(n, generator=gen, dtype=torch.float64)).requires_grad_()
    m = torch.rand(n, generator=gen, dtype=torch.float64).requires_grad_()
    nn_ = normal.clone().requires_grad_()

    def fn(nrm, a, rr, mm):
        d, s = brdf.evaluate(torch.nn.functional.normalize(nrm, dim=-1), wo, wi, a, rr, mm)
        return d + s

    assert torch.autograd.gradcheck(fn, (nn_, alb, r, m), eps=1e-6, atol=1e-6)
