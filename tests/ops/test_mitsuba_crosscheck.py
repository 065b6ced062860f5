"""D, G1 and the visible-normal density agree with Mitsuba 3's MicrofacetDistribution (GGX)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pipeline.ops import brdf, sampling

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("alpha", (0.01, 0.09, 0.36, 1.0))
def test_ggx_terms_match_mitsuba(alpha, mitsuba_variant):
    import mitsuba as mi

    distr = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, alpha, True)
    rng = np.random.default_rng(0)
    for _ in range(25):
        th_o, th_h = rng.uniform(0.01, 1.5), rng.uniform(0.0, 1.4)
        ph_o, ph_h = rng.uniform(0, 2 * math.pi), rng.uniform(0, 2 * math.pi)
        wo = np.array([math.sin(th_o) * math.cos(ph_o), math.sin(th_o) * math.sin(ph_o), math.cos(th_o)])
        h = np.array([math.sin(th_h) * math.cos(ph_h), math.sin(th_h) * math.sin(ph_h), math.cos(th_h)])
        a = torch.tensor([alpha], dtype=torch.float64)
        ours_d = brdf.ggx_d(torch.tensor([h[2]], dtype=torch.float64), a).item()
        ours_g1 = brdf.smith_g1(torch.tensor([wo[2]], dtype=torch.float64), a).item()
        theirs_d = float(np.array(distr.eval(mi.Vector3f(*map(float, h)))).ravel()[0])
        theirs_g1 = float(
            np.array(distr.smith_g1(mi.Vector3f(*map(float, wo)), mi.Vector3f(*map(float, h)))).ravel()[0]
        )
        theirs_vndf = float(np.array(distr.pdf(mi.Vector3f(*map(float, wo)), mi.Vector3f(*map(float, h)))).ravel()[0])
        assert ours_d == pytest.approx(theirs_d, rel=1e-4)
        if wo @ h > 0:
            assert ours_g1 == pytest.approx(theirs_g1, rel=1e-4)
        # our reflected-direction pdf times the reflection Jacobian 4 (wo.h) is the visible-normal density
        wi = 2 * (wo @ h) * h - wo
        ours_pdf = sampling.specular_pdf_local(torch.from_numpy(wo[None]), torch.from_numpy(wi[None]), a).item()
        ours_vndf = ours_pdf * 4 * max(wo @ h, 0)
        assert ours_vndf == pytest.approx(theirs_vndf, rel=1e-4, abs=1e-6)
