"""bench.probe_rerender: the texel quadrature integrates the BRDF exactly as a fine reference grid does, the
training estimator's mean agrees with it within its noise, and the bench runs on the micro dataset."""

import math

import pytest
import torch

from pipeline.bench import probe_rerender
from pipeline.data.lighting import Probes
from pipeline.ops import brdf, mc
from pipeline.ops.envmap import hemisphere_directions
from pipeline.ops.frames import from_local, orthonormal_basis


def _probes(radiance: float, P: int = 3, R: int = 8, C: int = 16) -> dict:
    g = torch.Generator().manual_seed(1)
    normal = torch.nn.functional.normalize(
        torch.randn(P, 3, generator=g, dtype=torch.float64) + torch.tensor([0, 0, 2.0]), dim=-1
    )
    directions = torch.as_tensor(hemisphere_directions(normal.numpy(), R, C))
    probes = Probes(
        torch.tensor([[0.1, -0.2, -2.0]] * P), directions.float(), torch.full((P, R, C, 3), radiance), normal.float()
    )
    position = probes.position.double()
    return {
        "probes": probes,
        "normal": normal,
        "albedo": torch.tensor([[0.6, 0.4, 0.2]] * P, dtype=torch.float64),
        "roughness": torch.tensor([0.9, 0.5, 0.6], dtype=torch.float64)[:P],  # lobes an 8x16 map resolves
        "metallic": torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)[:P],
        "wo": -position / position.norm(dim=-1, keepdim=True),
        "pixel": torch.ones(P, 3, dtype=torch.float64),
    }


def test_quadrature_of_a_constant_sky_matches_a_fine_grid():
    g = _probes(2.0)
    lambert, _ = probe_rerender.quadrature(g, strata=8)
    dirs, weights = mc.li2020_directions(256, 512, dtype=torch.float64)
    for p in range(3):
        t, b = orthonormal_basis(g["normal"][p : p + 1])
        wi = from_local(dirs, t.expand(len(dirs), 3), b.expand(len(dirs), 3), g["normal"][p].expand(len(dirs), 3))
        n, wo = g["normal"][p].expand_as(wi), g["wo"][p].expand_as(wi)
        f_d, f_s = brdf.evaluate(
            n, wo, wi, g["albedo"][p].expand_as(wi), g["roughness"][p].expand(len(wi)), g["metallic"][p].expand(len(wi))
        )
        ref = ((f_d + f_s) * ((n * wi).sum(-1) * weights).unsqueeze(-1)).sum(0) * 2.0
        torch.testing.assert_close(lambert[p], ref, rtol=2e-2, atol=1e-4)


def test_estimator_mean_agrees_with_the_quadrature_within_its_noise():
    g = _probes(2.0)
    lambert, _ = probe_rerender.quadrature(g, strata=4)
    renders = 4000
    mean, var = probe_rerender.estimator_moments(g, spp=8, renders=renders, seed=3)
    sigma = (var / renders).sqrt()
    assert ((mean - lambert).abs() < 5 * sigma + 1e-6).all(), (mean, lambert, sigma)
    assert (var > 0).all()


def test_bench_runs_on_micro(micro_shards, tmp_path):
    report = probe_rerender.run(str(micro_shards), views=2, strata=2, spp=4, renders=8, seed=0, min_pixel=1e-4)
    m = report["measured"]
    assert m["probes"] == len(report["rows"]) > 0
    assert 0 <= m["estimator"]["variance_share_of_squared_loss"] <= 1
    for name in ("lambert", "burley"):
        assert math.isfinite(m[name]["ratio_median"]) and m[name]["ratio_median"] > 0
    probe_rerender.plot(report, tmp_path / "p.png")
    assert (tmp_path / "p.png").stat().st_size > 0
    with pytest.raises(ValueError, match="no surface probes"):
        probe_rerender.run(str(micro_shards), views=0, strata=2, spp=4, renders=2, seed=0, min_pixel=1e-4)
