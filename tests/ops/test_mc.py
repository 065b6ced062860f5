"""The MC estimator: furnace against quadrature, Lambertian, gradients, chunking, adaptive counts."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pipeline.ops import brdf, mc
from tests.ops.sphere_quadrature import integrate_sphere

F64 = torch.float64


def _points(m, rough, view_deg, metal, albedo=(0.7, 0.5, 0.3)):
    th = math.radians(view_deg)
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64).expand(m, 3)
    wo = torch.tensor([[math.sin(th), 0.0, math.cos(th)]], dtype=F64).expand(m, 3)
    a = torch.tensor([albedo], dtype=F64).expand(m, 3)
    return n, wo, a, torch.full((m,), rough, dtype=F64), torch.full((m,), metal, dtype=F64)


def _reference(rough, view_deg, metal, env=None):
    """Directional albedo (or reflected radiance under env) of both lobes by quadrature: (2, 3)."""
    n, wo, a, r, m = _points(1, rough, view_deg, metal)
    mirror = torch.tensor([-wo[0, 0], 0.0, wo[0, 2]], dtype=F64)
    alpha = max(rough**2, brdf.ALPHA_MIN)

    def integrand(d, lobe):
        k = d.shape[0]
        fd, fs = brdf.evaluate(n.expand(k, 3), wo.expand(k, 3), d, a.expand(k, 3), r.expand(k), m.expand(k))
        L = env(d) if env is not None else 1.0
        return (fd if lobe == 0 else fs) * d[:, 2:].clamp(min=0) * L

    return np.stack([integrate_sphere(lambda d, k=k: integrand(d, k), mirror, alpha / 10, sub=8) for k in (0, 1)])


def _sky(d):
    """A smooth HDR environment: bright towards +x+z, dim below."""
    return (1.0 + 3.0 * torch.relu(d[:, :1] + d[:, 2:3]) ** 2) * torch.tensor([1.0, 0.9, 0.7], dtype=d.dtype)


@pytest.mark.parametrize("metal", (0.0, 1.0))
@pytest.mark.parametrize("view", (0.0, 60.0, 85.0))
@pytest.mark.parametrize("rough", (0.01, 0.05, 0.3, 1.0))
def test_furnace_importance_is_unbiased(rough, view, metal):
    """Constant and smooth HDR radiance: the per-pixel estimates' mean is within 4 standard errors of the
    quadrature reference, for each lobe and channel, down to roughness 0.01 and at grazing views."""
    m, spp = 4000, 32
    gen = torch.Generator().manual_seed(11)
    n, wo, a, r, mt = _points(m, rough, view, metal)
    for env in (None, _sky):
        fn = (lambda k, wi: torch.ones(len(k), 3, dtype=F64)) if env is None else (lambda k, wi: _sky(wi))
        with torch.no_grad():
            d, s = mc.estimate(fn, n, wo, a, r, mt, spp, gen, "importance")
        ref = _reference(rough, view, metal, env)
        for k, est in enumerate((d, s)):
            mean, se = est.mean(0).numpy(), est.std(0).numpy() / math.sqrt(m)
            assert (np.abs(mean - ref[k]) <= 4 * se + 1e-6 * (1 + ref[k])).all(), (k, mean, ref[k], se)


@pytest.mark.parametrize("estimator", ("uniform", "li2020"))
def test_lambertian_surfaces_return_their_albedo(estimator):
    m = 2000
    gen = torch.Generator().manual_seed(3)
    n, wo, a, r, mt = _points(m, 1.0, 30.0, 0.0)
    d, _ = mc.estimate(lambda k, wi: torch.ones(len(k), 3, dtype=F64), n, wo, a, r, mt, 64, gen, estimator)
    if estimator == "li2020":
        # a deterministic midpoint rule over 8 theta cells: no noise, but a known discretisation error
        # (0.65 % here), which is part of why the paper replaces this layer
        rel = ((d[0] - a[0]) / a[0]).abs()
        assert (rel < 1e-2).all() and (d.std(0) == 0).all()
    else:
        se = d.std(0) / math.sqrt(m)
        assert ((d.mean(0) - a[0]).abs() <= 4 * se).all()


def test_importance_diffuse_lobe_of_a_lambertian_is_its_albedo():
    m = 4000
    gen = torch.Generator().manual_seed(4)
    n, wo, a, r, mt = _points(m, 0.6, 40.0, 0.0)
    d, _ = mc.estimate(lambda k, wi: torch.ones(len(k), 3, dtype=F64), n, wo, a, r, mt, 16, gen)
    assert ((d.mean(0) - a[0]).abs() <= 4 * d.std(0) / math.sqrt(m)).all()


def test_uniform_estimator_is_unbiased_for_glossy_too():
    m = 4000
    gen = torch.Generator().manual_seed(5)
    n, wo, a, r, mt = _points(m, 0.3, 45.0, 1.0)
    d, s = mc.estimate(lambda k, wi: _sky(wi), n, wo, a, r, mt, 32, gen, "uniform")
    ref = _reference(0.3, 45.0, 1.0, _sky)
    assert (np.abs(s.mean(0).numpy() - ref[1]) <= 4 * s.std(0).numpy() / math.sqrt(m)).all()


def test_chunking_does_not_change_the_result_and_zero_counts_give_zero():
    gen_a, gen_b = torch.Generator().manual_seed(6), torch.Generator().manual_seed(6)
    n, wo, a, r, mt = _points(50, 0.2, 30.0, 0.5)
    counts = torch.randint(0, 9, (50,), generator=torch.Generator().manual_seed(0))
    counts[3] = 0
    fn = lambda k, wi: _sky(wi)  # noqa: E731
    d1, s1 = mc.estimate(fn, n, wo, a, r, mt, counts, gen_a, chunk=7)
    d2, s2 = mc.estimate(fn, n, wo, a, r, mt, counts, gen_b, chunk=1 << 20)
    torch.testing.assert_close(d1, d2)
    torch.testing.assert_close(s1, s2)
    assert (d1[3] == 0).all() and (s1[3] == 0).all()


def test_the_generator_is_explicit_and_alone_decides_the_samples():
    """Randomness is an argument: no fallback to the global RNG, whose state does not move the result."""
    n, wo, a, r, mt = _points(20, 0.3, 30.0, 0.0)
    fn = lambda k, wi: _sky(wi)  # noqa: E731
    with pytest.raises(TypeError, match="generator=None"):
        mc.estimate(fn, n, wo, a, r, mt, 4, None)
    torch.manual_seed(1)
    d1, _ = mc.estimate(fn, n, wo, a, r, mt, 4, torch.Generator().manual_seed(2))
    torch.manual_seed(99)
    d2, _ = mc.estimate(fn, n, wo, a, r, mt, 4, torch.Generator().manual_seed(2))
    assert torch.equal(d1, d2)


def test_gradients_match_common_random_number_differences():
    """With uniform sampling the directions do not depend on albedo/roughness/metallic, so the estimator
    is a smooth function of them under common random numbers: autograd == central differences."""
    n, wo, a, r, mt = _points(5, 0.4, 30.0, 0.3)
    a, r, mt = a.clone().requires_grad_(), r.clone().requires_grad_(), mt.clone().requires_grad_()

    def f(a_, r_, m_):
        gen = torch.Generator().manual_seed(7)
        d, s = mc.estimate(lambda k, wi: _sky(wi), n, wo, a_, r_, m_, 64, gen, "uniform", chunk=100)
        return (d + s).sum()

    ga, gr, gm = torch.autograd.grad(f(a, r, mt), (a, r, mt))
    eps = 1e-6
    for idx, (param, grad) in enumerate(((a, ga), (r, gr), (mt, gm))):
        flat = param.detach().reshape(-1)
        for i in range(0, flat.numel(), max(1, flat.numel() // 5)):
            plus, minus = flat.clone(), flat.clone()
            plus[i] += eps
            minus[i] -= eps
            args = [x.detach() for x in (a, r, mt)]
            args[idx] = plus.reshape(param.shape)
            fp = f(*args)
            args[idx] = minus.reshape(param.shape)
            fm = f(*args)
            fd = (fp - fm) / (2 * eps)
            assert abs(fd.item() - grad.reshape(-1)[i].item()) <= 1e-6 * (1 + abs(fd.item())), (idx, i)


def test_importance_gradient_is_unbiased():
    """d/d roughness of the importance estimate (directions detached) averages to the derivative of the
    quadrature reference."""
    m = 4000
    gen = torch.Generator().manual_seed(8)
    n, wo, a, _, mt = _points(m, 0.3, 50.0, 1.0)
    r = torch.full((m,), 0.3, dtype=F64, requires_grad=True)
    _, s = mc.estimate(lambda k, wi: _sky(wi), n, wo, a, r, mt, 16, gen)
    (g,) = torch.autograd.grad(s[:, 1].sum(), r)
    eps = 1e-4
    ref = (_reference(0.3 + eps, 50.0, 1.0, _sky)[1, 1] - _reference(0.3 - eps, 50.0, 1.0, _sky)[1, 1]) / (2 * eps)
    assert abs(g.mean().item() - ref) <= 4 * g.std().item() / math.sqrt(m) + 1e-4 * abs(ref)


def test_gradcheck_estimator_float64():
    """Uniform sampling: its directions do not move with the parameters, so the estimator under fixed
    random numbers is a smooth function whose Jacobian gradcheck can compare. (For importance sampling
    finite differences would also move the samples, which the estimator deliberately does not
    differentiate; its gradient is checked for unbiasedness instead.)"""
    n, wo, a, r, mt = _points(3, 0.5, 20.0, 0.4)
    scale = torch.tensor([1.5], dtype=F64, requires_grad=True)
    a, r, mt = a.clone().requires_grad_(), r.clone().requires_grad_(), mt.clone().requires_grad_()

    def f(a_, r_, m_, s_):
        gen = torch.Generator().manual_seed(9)
        d, s = mc.estimate(lambda k, wi: _sky(wi) * s_, n, wo, a_, r_, m_, 8, gen, "uniform", chunk=5)
        return d + s

    assert torch.autograd.gradcheck(f, (a, r, mt, scale), eps=1e-6, atol=1e-6)


def test_adaptive_allocation_spends_the_budget_on_glossy_pixels():
    a = torch.full((4, 3), 0.5, dtype=F64)
    r = torch.tensor([0.05, 0.9, 0.3, 0.05], dtype=F64)
    m = torch.tensor([1.0, 0.0, 0.0, 1.0], dtype=F64)
    valid = torch.tensor([True, True, True, False])
    counts = mc.allocate_samples(a, r, m, valid, budget=90)
    assert counts.sum() == 90 and counts[3] == 0 and counts[0] > counts[2] > 0 and counts[1] >= 1
    with pytest.raises(ValueError, match="budget"):
        mc.allocate_samples(a, r, m, valid, budget=2)


def test_memory_for_gradients_does_not_grow_with_samples():
    """Autograd keeps only the shared G-buffer tensors whatever the sample count: chunks are checkpointed
    and summed per pixel inside, so no per-sample tensor outlives its chunk."""
    n, wo, a, r, mt = _points(300, 0.3, 30.0, 0.5)
    a, r = a.clone().requires_grad_(), r.clone().requires_grad_()
    saved = {}
    for spp in (4, 64):
        storages = set()

        def pack(t, storages=storages):
            storages.add((t.untyped_storage().data_ptr(), t.untyped_storage().nbytes()))
            return t

        with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
            mc.estimate(lambda k, wi: _sky(wi), n, wo, a, r, mt, spp, torch.Generator().manual_seed(0), chunk=256)
        saved[spp] = sum(nbytes for _, nbytes in storages)
    assert saved[64] == saved[4] and saved[4] < 300 * 3 * 8 * 8


def test_counter_uniform_is_uniform_and_independent():
    from scipy import stats

    u = mc.counter_uniform(12345, torch.arange(200_000)).numpy()
    for d in range(3):
        assert stats.kstest(u[:, d], "uniform").pvalue > 1e-3
    assert abs(np.corrcoef(u[:, 0], u[:, 1])[0, 1]) < 0.01 and abs(np.corrcoef(u[:-1, 0], u[1:, 0])[0, 1]) < 0.01
    assert (u >= 0).all() and (u < 1).all()
    assert not np.array_equal(u, mc.counter_uniform(12346, torch.arange(200_000)).numpy())


def test_one_chunk_runs_the_radiance_callback_once_and_chunked_gradients_agree():
    """A training step's few samples fit one chunk: not checkpointed, so forward and backward see one call
    of the callback (a random callback would otherwise draw again in backward). Chunked and unchunked
    estimates draw the same samples, so their gradients agree."""
    n, wo, a, r, mt = _points(50, 0.4, 30.0, 0.5)
    grads, calls = {}, {}
    for chunk in (1 << 16, 64):
        s = torch.ones(3, dtype=F64, requires_grad=True)
        count = [0]

        def fn(k, wi, s=s, count=count):
            count[0] += 1
            return _sky(wi) * s

        d, sp = mc.estimate(fn, n, wo, a, r, mt, 8, torch.Generator().manual_seed(3), chunk=chunk)
        (d + sp).sum().backward()
        grads[chunk], calls[chunk] = s.grad.clone(), count[0]
    assert calls[1 << 16] == 1
    assert calls[64] == 2 * math.ceil(50 * 8 / 64)  # checkpointed: each chunk again in backward
    torch.testing.assert_close(grads[64], grads[1 << 16], rtol=1e-12, atol=1e-12)
