"""The scoring estimator (`ops.scoring_mc`) and its light guide (`ops.guide`): the guide samples its own
density (chi-square), the estimate converges to the render layer's (`mc.estimate`) with and without a
guide (k sigma), does not depend on its chunking, and is far less noisy under a lamp."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from pipeline.ops import mc, scoring_mc
from pipeline.ops.envmap import sphere_lookup, texel_solid_angles
from pipeline.ops.guide import SphereGuide

F64 = torch.float64


def _lamp_map(rows: int = 16, cols: int = 32, lamp: float = 400.0) -> torch.Tensor:
    """(1, rows, cols, 3) a dim room with one bright texel overhead-forward, as a ceiling panel."""
    g = torch.Generator().manual_seed(3)
    m = 0.2 + 0.3 * torch.rand(1, rows, cols, 3, generator=g, dtype=F64)
    m[0, 3, 1] = lamp
    return m


def _points(m: int, rough: float, metal: float, view_deg: float = 40.0):
    th = math.radians(view_deg)
    n = torch.tensor([[0.0, 1.0, 0.0]], dtype=F64).expand(m, 3)  # facing up, towards the lamp
    wo = torch.tensor([[math.sin(th), math.cos(th), 0.0]], dtype=F64).expand(m, 3)
    a = torch.tensor([[0.7, 0.5, 0.3]], dtype=F64).expand(m, 3)
    return n, wo, a, torch.full((m,), rough, dtype=F64), torch.full((m,), metal, dtype=F64)


def test_guide_draws_texels_by_their_probability_and_its_density_integrates_to_one():
    lamp = _lamp_map()
    guide = SphereGuide(lamp)
    u = torch.rand(200_000, 3, generator=torch.Generator().manual_seed(0), dtype=F64)
    wi = guide.sample(u)
    assert torch.allclose(wi.norm(dim=-1), torch.ones(len(wi), dtype=F64))
    theta, phi = torch.acos(wi[:, 1].clamp(-1, 1)), torch.atan2(wi[:, 0], -wi[:, 2]) % (2 * math.pi)
    texel = (theta / math.pi * 16).long().clamp(max=15) * 32 + (phi / (2 * math.pi) * 32).long().clamp(max=31)
    counts = np.bincount(texel.numpy(), minlength=16 * 32)
    expected = guide.texel_prob.numpy() * len(wi)
    keep = expected >= 5
    merged_obs = np.append(counts[keep], counts[~keep].sum())
    merged_exp = np.append(expected[keep], expected[~keep].sum())
    assert stats.chisquare(merged_obs, merged_exp).pvalue > 1e-3
    omega = np.repeat(texel_solid_angles(16, 32, hemisphere=False), 32)
    assert float((guide.density.numpy() * omega).sum()) == pytest.approx(1.0, abs=1e-9)
    assert torch.allclose(guide.pdf(wi), guide.density[texel])
    block = counts.reshape(16, 32)[2:5, 0:3].sum()  # the lamp's texel and the 3 x 3 around it (bilinear spill)
    assert block > 0.9 * len(wi)


def test_guide_refuses_maps_it_cannot_sample():
    with pytest.raises(ValueError, match="expected \\(rows, cols, 3\\)"):
        SphereGuide(torch.ones(4, 8))
    with pytest.raises(ValueError, match="finite and non-negative"):
        SphereGuide(torch.full((4, 8, 3), float("nan")))
    with pytest.raises(ValueError, match="no energy"):
        SphereGuide(torch.zeros(4, 8, 3))


@pytest.mark.parametrize(("rough", "metal"), [(1.0, 0.0), (0.3, 0.0), (0.05, 1.0)])
@pytest.mark.parametrize("guided", [False, True])
def test_estimate_converges_to_the_render_layers_value(rough, metal, guided):
    """Both estimators are unbiased for the same integral: their means over many independent pixels agree
    within 4 combined standard errors, with the guide and without, diffuse to mirror-like metal."""
    lamp = _lamp_map()

    def light(k, wi):
        return sphere_lookup(lamp, torch.zeros(len(k), dtype=torch.long), wi)

    M = 3000
    n, wo, a, r, m = _points(M, rough, metal)
    ours = scoring_mc.estimate(light, n, wo, a, r, m, 32, seed=5, guide=SphereGuide(lamp) if guided else None)
    with torch.no_grad():
        d, s = mc.estimate(light, n, wo, a, r, m, 256, torch.Generator().manual_seed(9), "importance")
    ref = d + s
    se = torch.sqrt(ours.var(0) / M + ref.var(0) / M)
    assert torch.all((ours.mean(0) - ref.mean(0)).abs() <= 4 * se), (ours.mean(0), ref.mean(0), se)


def test_guide_and_sobol_points_lower_the_noise_under_a_lamp():
    """A diffuse surface under a small bright lamp: BRDF samples alone rarely find it. At equal samples the
    Sobol points lower the per-pixel spread, and the guide lowers it far more."""
    lamp = _lamp_map()

    def light(k, wi):
        return sphere_lookup(lamp, torch.zeros(len(k), dtype=torch.long), wi)

    n, wo, a, r, m = _points(2000, 1.0, 0.0)
    with torch.no_grad():
        d, s = mc.estimate(light, n, wo, a, r, m, 64, torch.Generator().manual_seed(1), "importance")
    spread = {
        "random": (d + s).std(0).mean(),
        "sobol": scoring_mc.estimate(light, n, wo, a, r, m, 64, seed=2).std(0).mean(),
        "sobol+guide": scoring_mc.estimate(light, n, wo, a, r, m, 64, seed=2, guide=SphereGuide(lamp)).std(0).mean(),
    }
    assert spread["sobol"] < 0.9 * spread["random"], spread
    assert spread["sobol+guide"] < 0.3 * spread["random"], spread


def test_estimate_does_not_depend_on_its_chunks_and_refuses_zero_samples():
    lamp = _lamp_map()

    def light(k, wi):
        return sphere_lookup(lamp, torch.zeros(len(k), dtype=torch.long), wi)

    n, wo, a, r, m = _points(50, 0.3, 0.0)
    guide = SphereGuide(lamp)
    whole = scoring_mc.estimate(light, n, wo, a, r, m, 16, seed=4, guide=guide)
    pieces = scoring_mc.estimate(light, n, wo, a, r, m, 16, seed=4, guide=guide, chunk=37)
    assert torch.allclose(whole, pieces, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="spp=0"):
        scoring_mc.estimate(light, n, wo, a, r, m, 0, seed=4)
