"""Lighting metrics, the HDR light loss and the lighting baselines on hand-computed cases."""

import math

import numpy as np
import pytest
import torch

from pipeline.data.lighting import Probes, ViewLighting
from pipeline.metrics.image import psnr_tonemapped
from pipeline.metrics.lighting import log_l1, normalised_mse, ray_classes, relmse


def test_relmse_by_hand_and_exposure_invariant():
    target = torch.tensor([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
    pred = torch.tensor([[2.0, 2.0, 2.0], [0.1, 0.1, 0.1]])
    scale = torch.tensor([1.0, 1.0])
    # texel 1: (2 - 1)^2 / (1 + 0.01); texel 2: 0.1^2 / 0.01 = 1
    expect = (1 / 1.01 + 1.0) / 2
    assert math.isclose(float(relmse(pred, target, scale)), expect, rel_tol=1e-6)
    for k in (1e-3, 37.0):  # the same scene at another exposure scores the same
        assert math.isclose(float(relmse(pred * k, target * k, scale * k)), expect, rel_tol=1e-5)
    assert float(relmse(target, target, scale)) == 0.0
    # a zero prediction scores at most 1 per texel, an over-estimate without bound: relMSE favours dark
    assert float(relmse(torch.zeros_like(target), target, scale)) <= 1.0
    assert float(relmse(target * 10 + 1, target, scale)) > 50.0


def test_nmse_is_error_energy_over_light_energy():
    target = torch.tensor([[3.0, 0.0, 4.0]])
    assert math.isclose(float(normalised_mse(torch.zeros_like(target), target)), 1.0)
    assert math.isclose(float(normalised_mse(target * 0.5, target)), 0.25, rel_tol=1e-6)


def test_log_l1_and_psnr_by_hand():
    scale = torch.tensor([1.0])
    # |log(1 + 3) - log(1 + 1)| = log 2 in every channel
    assert math.isclose(float(log_l1(torch.full((1, 3), 3.0), torch.ones(1, 3), scale)), math.log(2), rel_tol=1e-6)
    # tone map x / 2 then x / (1 + x): 2 -> 0.5, 0 -> 0; MSE 0.25 -> PSNR 10 log10(4)
    psnr = float(psnr_tonemapped(torch.full((1, 3), 2.0), torch.zeros(1, 3), scale))
    assert math.isclose(psnr, 10 * math.log10(4), rel_tol=1e-6)


def test_log_l1_and_psnr_are_exposure_invariant():
    g = torch.Generator().manual_seed(0)
    target = torch.rand(50, 3, generator=g) * 4
    pred = target * (0.5 + torch.rand(50, 3, generator=g))
    scale = torch.full((50,), 0.7)
    for k in (0.01, 100.0):
        assert math.isclose(
            float(log_l1(pred * k, target * k, scale * k)), float(log_l1(pred, target, scale)), rel_tol=1e-5
        )
        a, b = float(psnr_tonemapped(pred * k, target * k, scale * k)), float(psnr_tonemapped(pred, target, scale))
        assert math.isclose(a, b, rel_tol=1e-5)


def test_relative_mse_loss_is_exposure_invariant_and_stationary_at_the_mean():
    from pipeline.systems.light_losses import hdr_relative_loss as relative_mse

    g = torch.Generator().manual_seed(0)
    target = torch.rand(64, 3, generator=g, dtype=torch.float64) ** 4 * 10
    pred = torch.rand(64, 3, generator=g, dtype=torch.float64)
    scale = torch.full((64,), 0.3, dtype=torch.float64)
    a = relative_mse(pred, target, scale=scale)
    assert torch.allclose(relative_mse(pred * 7, target * 7, scale=scale * 7), a)
    # stop-gradient denominator: one shared prediction settles at the targets' mean, not a smaller value
    c = torch.full((64, 3), float(target.mean()), dtype=torch.float64, requires_grad=True)
    relative_mse(c, target.expand(64, 3).contiguous(), scale=scale).backward()
    assert abs(float(c.grad.sum())) < 1e-9


def _assert_fixed_point(loss_fn, centre: torch.Tensor, target: torch.Tensor, scale: torch.Tensor) -> None:
    """One prediction per channel shared by every sample, (3,): the loss's (sub)gradient summed over the
    samples is zero at `centre` and pulls towards it from 1.5x and 0.5x of it."""
    n = target.shape[0]
    for value, sign in ((centre, 0.0), (centre * 1.5, 1.0), (centre * 0.5, -1.0)):
        c = value.expand(n, 3).clone().requires_grad_(True)
        loss_fn(c, target, scale).backward()
        total = c.grad.sum(0)
        if sign == 0.0:
            assert torch.allclose(total, torch.zeros(3, dtype=torch.float64), atol=1e-12)
        else:
            assert bool((torch.sign(total) == sign).all())


def test_log_l1_loss_is_the_metric_and_stationary_at_the_median():
    from pipeline.systems.light_losses import hdr_log_l1_loss

    g = torch.Generator().manual_seed(1)
    target = torch.rand(63, 3, generator=g, dtype=torch.float64) ** 4 * 10  # odd count: a unique median
    pred = torch.rand(63, 3, generator=g, dtype=torch.float64)
    scale = torch.full((63,), 0.3, dtype=torch.float64)
    a = hdr_log_l1_loss(pred, target, scale)
    # by hand: two images (means 1 and 0.5), a negative prediction counting as 0; in image-mean units
    # |log(1 + p) - log(1 + t)| is log 2, log 2, log 4.5 for image 1 and log 3, log 7/3, log 3 for image 2
    small = hdr_log_l1_loss(
        torch.tensor([[3.0, 0.0, 8.0], [1.0, 1.0, -1.0]], dtype=torch.float64),
        torch.tensor([[1.0, 1.0, 1.0], [0.0, 3.0, 1.0]], dtype=torch.float64),
        torch.tensor([1.0, 0.5], dtype=torch.float64),
    )
    expect = (2 * math.log(2) + math.log(4.5) + 2 * math.log(3) + math.log(7 / 3)) / 6
    assert math.isclose(float(small), expect, rel_tol=1e-12)
    p, t, s = (x.numpy() for x in (pred, target, scale[:, None]))
    assert math.isclose(float(a), float(np.abs(np.log1p(p / s) - np.log1p(t / s)).mean()), rel_tol=1e-12)
    assert torch.allclose(hdr_log_l1_loss(pred * 7, target * 7, scale * 7), a)
    # one shared prediction per channel: zero subgradient at the median, a net pull towards it elsewhere
    _assert_fixed_point(hdr_log_l1_loss, target.median(0).values, target, scale)


def test_nmse_loss_is_the_metric_per_image_exposure_and_stationary_at_the_mean():
    from pipeline.systems.light_losses import light_nmse_loss

    g = torch.Generator().manual_seed(2)
    target = torch.rand(64, 3, generator=g, dtype=torch.float64) ** 4 * 10
    pred = torch.rand(64, 3, generator=g, dtype=torch.float64)
    scale = torch.where(torch.arange(64) < 32, 0.3, 2.0).to(torch.float64)  # two images, two exposures
    a = light_nmse_loss(pred, target, scale)
    # by hand: images of means 1 and 2; in those units the targets are (1, 0, 0) and (0, 2, 0), the
    # predictions (0, 0, 0) and (0, 1, 1): error energy 1 + 1 + 1 over light energy 1 + 4 (absolute: 9 / 17)
    small = light_nmse_loss(
        torch.tensor([[0.0, 0.0, 0.0], [0.0, 2.0, 2.0]], dtype=torch.float64),
        torch.tensor([[1.0, 0.0, 0.0], [0.0, 4.0, 0.0]], dtype=torch.float64),
        torch.tensor([1.0, 2.0], dtype=torch.float64),
    )
    assert math.isclose(float(small), 3 / 5, rel_tol=1e-12)
    p, t, s = (x.numpy() for x in (pred, target, scale[:, None]))
    assert math.isclose(float(a), float(((p / s - t / s) ** 2).sum() / ((t / s) ** 2).sum()), rel_tol=1e-12)
    # in units of each image's mean: a brighter exposure of one image leaves the loss as it is
    brighter = torch.where(torch.arange(64)[:, None] < 32, 5.0, 1.0).to(torch.float64)
    assert torch.allclose(light_nmse_loss(pred * brighter, target * brighter, scale * brighter[:, 0]), a)
    # one shared prediction per channel (one exposure): the gradient vanishes at the mean only
    _assert_fixed_point(light_nmse_loss, target.mean(0), target, torch.full((64,), 0.3, dtype=torch.float64))


@pytest.mark.parametrize(
    "bad, message",
    [({"light_loss": "l2"}, "lighting.light_loss"), ({"nmse_weight": -1.0}, "lighting.nmse_weight")],
)
def test_light_loss_settings_are_checked(bad, message):
    from pipeline.systems.lighting import LightingSystem

    with pytest.raises(ValueError, match=message):
        LightingSystem(
            light_net={},
            material=None,
            render={"estimator": "importance", "spp": 1, "eval_spp": 1, "seed": 0},
            gbuffers="ground_truth",
            **bad,
        )


def test_mean_training_radiance_and_its_exposure_ratio():
    from pipeline.systems.lighting_baselines import mean_training_radiance

    im = torch.ones(2, 3, 4, 4)
    im[1] *= 4.0  # image means 1 and 4
    light = [_view(torch.full((1, 2, 2, 3), v), torch.full((1, 1, 2, 3), v)) for v in (2.0, 8.0)]
    c = mean_training_radiance([{"im": im, "light": light}])
    assert torch.allclose(c.constant, torch.full((3,), 5.0))  # (6 texels x 2 + 6 x 8) / 12
    assert torch.allclose(c.ratio, torch.full((3,), 2.0))  # every texel is twice its image's mean
    for kind in ("surf", "free"):  # uniform probes: every band that saw a texel is at its probe's mean
        assert torch.allclose(c.profile[kind], torch.ones_like(c.profile[kind])), kind


def _probes_looking(up: list[float], radiance: list[list[float]]) -> Probes:
    """P probes of 1 x T texels (radiance (P, T) grey) whose centre directions have the T view-space up
    components `up`."""
    y = torch.tensor(up)
    d = torch.stack([(1 - y**2).sqrt(), y, torch.zeros_like(y)], -1)
    r = torch.tensor(radiance, dtype=torch.float32).reshape(-1, len(up))[..., None].expand(-1, -1, 3)
    P = len(r)
    return Probes(torch.zeros(P, 3), d.expand(P, 1, -1, 3).contiguous(), r[:, None].contiguous(), torch.zeros(P, 3))


def test_angular_profile_is_learnt_by_elevation_per_probe_and_kind():
    from pipeline.systems.lighting_baselines import PROFILE_BINS, elevation_band, mean_training_radiance

    y = torch.tensor([-1.0, 1.0, 0.0, 0.5, -0.5])
    d = torch.stack([(1 - y**2).sqrt(), y, torch.zeros_like(y)], -1)
    assert PROFILE_BINS == 8
    assert elevation_band(d).tolist() == [0, 7, 4, 6, 2]  # equal solid angle: uniform in y, not in angle
    up, mid, down = 0.99, 0.1, -0.99
    # surface: probe A 3x brighter above than below, probe B (10x the energy) 3x brighter at the horizon
    # than above; each texel counts relative to its own probe's mean, so B's energy does not outweigh A
    surf = _probes_looking([up, down], [[3.0, 1.0]])
    surf_b = _probes_looking([up, mid], [[10.0, 30.0]])
    # free points: the other way round, plus a black probe, which has no shape and is left out
    free = _probes_looking([up, down], [[1.0, 3.0], [0.0, 0.0]])
    c = mean_training_radiance(
        [
            {
                "im": torch.ones(2, 3, 2, 2),
                "light": [ViewLighting(surf, free), ViewLighting(surf_b, _probes_looking([up], []))],
            }
        ]
    )
    expect_surf = torch.ones(PROFILE_BINS)
    expect_surf[[0, 4, 7]] = torch.tensor([0.5, 1.5, 1.0])  # top band: A's 1.5 and B's 0.5
    torch.testing.assert_close(c.profile["surf"], expect_surf)  # unseen bands: the probe's mean (1)
    expect_free = torch.ones(PROFILE_BINS)
    expect_free[[0, 7]] = torch.tensor([1.5, 0.5])
    torch.testing.assert_close(c.profile["free"], expect_free)


def test_profile_oracle_keeps_each_probes_true_mean():
    from pipeline.systems.lighting_baselines import PROFILE_BINS, probe_oracle_light

    profile = torch.ones(PROFILE_BINS)
    profile[[0, 4, 7]] = torch.tensor([0.5, 1.5, 1.0])
    up, mid, down = 0.99, 0.1, -0.99
    # a probe shaped as taught is predicted exactly; one that sees only the upper bands (as a floor's
    # hemisphere does) is renormalised so its mean is still the probe's own
    test = ViewLighting(
        _probes_looking([down, up, mid], [[1.0, 2.0, 3.0]]), _probes_looking([up, mid], [[4.0, 6.0], [1.0, 1.0]])
    )
    pred, target, _ = probe_oracle_light([test], "surf", torch.tensor([1.0]), profile)["probe_profile_oracle"]
    torch.testing.assert_close(pred[:, 0], torch.tensor([1.0, 2.0, 3.0]))
    pred, target, _ = probe_oracle_light([test], "free", torch.tensor([1.0]), profile)["probe_profile_oracle"]
    torch.testing.assert_close(pred[:, 0], torch.tensor([4.0, 6.0, 0.8, 1.2]))  # weights 1 : 1.5, mean kept
    assert "probe_profile_oracle" not in probe_oracle_light([test], "surf", torch.tensor([1.0]))


def test_ray_classes_partition_every_ray_by_hit_and_confidence():
    hit = torch.tensor([True, True, True, False, False])
    u = torch.tensor([0.0, 0.49, 0.5, 1.0, 0.2])
    masks = ray_classes(hit, u)
    assert masks["hit"].tolist() == [True, True, False, False, False]
    assert masks["uncertain"].tolist() == [False, False, True, False, False]
    assert masks["miss"].tolist() == [False, False, False, True, True]
    assert (sum(m.long() for m in masks.values()) == 1).all()


def test_probe_oracles_predict_each_probes_own_mean_and_median():
    from pipeline.systems.lighting_baselines import probe_oracle_light

    texels = torch.tensor([1.0, 2.0, 3.0, 10.0])  # one probe of 2 x 2 texels, grey
    empty = torch.zeros(0, 2, 2, 3)
    lights = [
        _view(texels.view(1, 2, 2, 1).expand(1, 2, 2, 3), empty),
        _view(empty, empty),  # a view without probes adds nothing
    ]
    out = probe_oracle_light(lights, "surf", torch.tensor([2.0, 5.0]))
    pred, target, scale = out["probe_mean_oracle"]
    torch.testing.assert_close(pred, torch.full((4, 3), 4.0))
    torch.testing.assert_close(target[:, 0], texels)
    torch.testing.assert_close(scale, torch.full((4,), 2.0))
    torch.testing.assert_close(out["probe_median_oracle"][0], torch.full((4, 3), 2.0))  # the lower median
    assert probe_oracle_light(lights[1:], "surf", torch.tensor([5.0])) is None


def _view(surf_radiance: torch.Tensor, free_radiance: torch.Tensor) -> ViewLighting:
    """A ViewLighting holding only radiance (directions and positions zero: unused by these tests)."""
    P, Q = len(surf_radiance), len(free_radiance)
    surf = Probes(
        torch.zeros(P, 3),
        torch.zeros_like(surf_radiance),
        surf_radiance,
        torch.zeros(P, 3),
        torch.zeros(P, 2, dtype=torch.long),
    )
    return ViewLighting(surf, Probes(torch.zeros(Q, 3), torch.zeros_like(free_radiance), free_radiance))


def test_probe_rays_take_every_texel_in_order_or_a_seeded_sample():
    from pipeline.data.lighting import probe_rays

    rad = torch.arange(2 * 2 * 2 * 3, dtype=torch.float32).view(2, 2, 2, 3)  # 2 probes of 2 x 2 texels
    surf = Probes(
        torch.tensor([[0.0, 0, -1], [1, 0, -1]]),
        torch.zeros(2, 2, 2, 3),
        rad,
        torch.tensor([[0.0, 0, 1], [0, 0, 1]]),
        torch.tensor([[3, 4], [5, 6]]),
    )
    light = ViewLighting(surf, Probes(torch.zeros(0, 3), torch.zeros(0, 2, 2, 3), torch.zeros(0, 2, 2, 3)))
    rays = probe_rays([light, light], "surf")
    assert len(rays) == 16 and rays.image.tolist() == [0] * 8 + [1] * 8
    torch.testing.assert_close(rays.radiance[:8], rad.reshape(8, 3))
    torch.testing.assert_close(rays.origin[0], torch.tensor([0.0, 0.0, -1.0 + 1e-3]))  # lifted off the surface
    assert rays.pixel[4].tolist() == [5, 6]
    assert probe_rays([light], "free") is None
    a = probe_rays([light], "surf", 1, 2, torch.Generator().manual_seed(3))
    b = probe_rays([light], "surf", 1, 2, torch.Generator().manual_seed(3))
    assert len(a) == 2 and torch.equal(a.radiance, b.radiance) and torch.equal(a.direction, b.direction)
    # a texel is predicted as the mean over directions inside it: 2 x 2 grid centres in evaluation, one
    # random direction per texel in training; all on the probe's hemisphere (normal +z here)
    assert rays.direction.shape == (16, 4, 3) and a.direction.shape == (2, 1, 3)
    for d in (rays.direction, a.direction):
        torch.testing.assert_close(d.norm(dim=-1), torch.ones(d.shape[:2]))
        assert bool((d[..., 2] >= 0).all())
    # texel (0, 0) of a 2 x 2 hemisphere map: theta in [0, pi/4], phi in [0, pi)
    first = rays.direction[0]
    assert bool((first[:, 2] >= torch.cos(torch.tensor(torch.pi / 4)) - 1e-6).all() and (first[:, 1] >= -1e-6).all())


def test_ssim_tonemapped_is_one_on_itself_exposure_invariant_and_masked():
    import numpy as np

    from pipeline.metrics.image import ssim_tonemapped

    rng = np.random.default_rng(0)
    a = rng.uniform(0, 4, (24, 32, 3))
    b = a * rng.uniform(0.5, 1.5, a.shape)
    assert ssim_tonemapped(a, a, 1.0) == pytest.approx(1.0)
    s = ssim_tonemapped(b, a, 1.0)
    assert 0 < s < 0.99
    assert ssim_tonemapped(b * 10, a * 10, 10.0) == pytest.approx(s, rel=1e-9)  # the tone map follows exposure
    mask = np.zeros((24, 32), bool)
    mask[:, :16] = True
    b[:, 16:] = a[:, 16:] * 3  # damage outside the mask lowers the whole-image score more
    assert ssim_tonemapped(b, a, 1.0, mask) > ssim_tonemapped(b, a, 1.0)
    with pytest.raises(ValueError, match="no pixel"):
        ssim_tonemapped(b, a, 1.0, np.zeros((24, 32), bool))
