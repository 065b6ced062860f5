"""Stability exactly where methods fail: roughness 0 and 1, grazing and below-horizon views, normals
facing away, black metal, zero and huge HDR radiance. Values and gradients must stay finite."""

from __future__ import annotations

import math

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.ops import brdf, mc, sampling

F32 = torch.float32
unit = st.floats(0.0, 1.0)
edge_unit = st.one_of(st.sampled_from([0.0, 1.0, 1e-7, 1 - 1e-7]), unit)


@st.composite
def shading_point(draw):
    """One shading point; view elevation from straight on down to exactly grazing and below."""
    elev = draw(st.one_of(st.sampled_from([0.0, 1e-7, -1e-3, math.pi / 2]), st.floats(-0.3, math.pi / 2)))
    az = draw(st.floats(0, 2 * math.pi))
    wo = torch.tensor([[math.cos(elev) * math.cos(az), math.cos(elev) * math.sin(az), math.sin(elev)]], dtype=F32)
    flip = draw(st.booleans())  # a normal facing away from the viewer
    normal = torch.tensor([[0.0, 0.0, -1.0 if flip else 1.0]], dtype=F32)
    black_metal = draw(st.booleans())
    albedo = torch.zeros(1, 3) if black_metal else torch.tensor([[draw(unit), draw(unit), draw(unit)]], dtype=F32)
    metallic = torch.tensor([1.0 if black_metal else draw(edge_unit)], dtype=F32)
    rough = torch.tensor([draw(edge_unit)], dtype=F32)
    radiance = draw(st.sampled_from([0.0, 1.0, 1e4, 1e6]))
    return normal, wo, albedo, rough, metallic, radiance


@settings(max_examples=150, deadline=None)
@given(shading_point(), st.integers(0, 2**31 - 1))
def test_sampler_pdf_and_brdf_are_finite(point, seed):
    normal, wo, albedo, rough, metal, _ = point
    n = 64
    gen = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 3, generator=gen)
    args = (normal.expand(n, 3), wo.expand(n, 3), albedo.expand(n, 3), rough.expand(n), metal.expand(n))
    wi, p = sampling.sample(u, *args)
    assert torch.isfinite(wi).all() and torch.isfinite(p).all() and (p >= 0).all()
    assert torch.isfinite(sampling.pdf(args[0], args[1], wi, *args[2:])).all()
    d, s = brdf.evaluate(args[0], args[1], wi, *args[2:])
    assert torch.isfinite(d).all() and torch.isfinite(s).all() and (d >= 0).all() and (s >= 0).all()


@settings(max_examples=100, deadline=None)
@given(shading_point(), st.sampled_from(mc.ESTIMATORS), st.integers(0, 2**31 - 1))
def test_estimates_and_gradients_are_finite(point, estimator, seed):
    normal, wo, albedo, rough, metal, radiance = point
    m = 8
    nrm = normal.expand(m, 3).clone().requires_grad_()
    alb = albedo.expand(m, 3).clone().requires_grad_()
    r = rough.expand(m).clone().requires_grad_()
    mt = metal.expand(m).clone().requires_grad_()
    level = torch.tensor(radiance, requires_grad=True)
    gen = torch.Generator().manual_seed(seed)
    n_unit = torch.nn.functional.normalize(nrm, dim=-1)
    d, s = mc.estimate(
        lambda k, wi: level * torch.ones(len(k), 3),
        n_unit,
        wo.expand(m, 3),
        alb,
        r,
        mt,
        4,
        gen,
        estimator,
        li_size=(4, 8),
    )
    assert torch.isfinite(d).all() and torch.isfinite(s).all()
    (d + s).sum().backward()
    for t in (nrm, alb, r, mt, level):
        assert t.grad is not None and torch.isfinite(t.grad).all()
