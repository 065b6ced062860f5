"""Lighting metrics: relMSE, normalised MSE and log-L1 on hand-computed cases; exposure invariance."""

import math

import torch

from pipeline.systems.lighting import log_l1, normalised_mse, psnr_tonemapped, ray_classes, relative_mse_metric


def test_relmse_by_hand_and_exposure_invariant():
    target = torch.tensor([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
    pred = torch.tensor([[2.0, 2.0, 2.0], [0.1, 0.1, 0.1]])
    scale = torch.tensor([1.0, 1.0])
    # texel 1: (2 - 1)^2 / (1 + 0.01); texel 2: 0.1^2 / 0.01 = 1
    expect = (1 / 1.01 + 1.0) / 2
    assert math.isclose(float(relative_mse_metric(pred, target, scale)), expect, rel_tol=1e-6)
    for k in (1e-3, 37.0):  # the same scene at another exposure scores the same
        assert math.isclose(float(relative_mse_metric(pred * k, target * k, scale * k)), expect, rel_tol=1e-5)
    assert float(relative_mse_metric(target, target, scale)) == 0.0


def test_nmse_is_error_energy_over_light_energy():
    target = torch.tensor([[3.0, 0.0, 4.0]])
    assert math.isclose(float(normalised_mse(torch.zeros_like(target), target)), 1.0)
    assert math.isclose(float(normalised_mse(target * 0.5, target)), 0.25, rel_tol=1e-6)


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
    from pipeline.systems.lighting import relative_mse

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


def test_mean_training_radiance_and_its_exposure_ratio():
    from pipeline.systems.lighting_stage import mean_training_radiance

    im = torch.ones(2, 3, 4, 4)
    im[1] *= 4.0  # image means 1 and 4
    light = [
        {"surf_radiance": torch.full((1, 2, 2, 3), 2.0), "free_radiance": torch.full((1, 1, 2, 3), 2.0)},
        {"surf_radiance": torch.full((1, 2, 2, 3), 8.0), "free_radiance": torch.full((1, 1, 2, 3), 8.0)},
    ]
    constant, ratio = mean_training_radiance([{"im": im, "light": light}])
    assert torch.allclose(constant, torch.full((3,), 5.0))  # (6 texels x 2 + 6 x 8) / 12
    assert torch.allclose(ratio, torch.full((3,), 2.0))  # every texel is twice its image's mean


def test_ray_classes_partition_every_ray_by_hit_and_confidence():
    hit = torch.tensor([True, True, True, False, False])
    u = torch.tensor([0.0, 0.49, 0.5, 1.0, 0.2])
    masks = ray_classes(hit, u)
    assert masks["hit"].tolist() == [True, True, False, False, False]
    assert masks["uncertain"].tolist() == [False, False, True, False, False]
    assert masks["miss"].tolist() == [False, False, False, True, True]
    assert (sum(m.long() for m in masks.values()) == 1).all()


def test_probe_oracles_predict_each_probes_own_mean_and_median():
    from pipeline.systems.lighting_stage import probe_oracle_light

    texels = torch.tensor([1.0, 2.0, 3.0, 10.0])  # one probe of 2 x 2 texels, grey
    lights = [
        {"surf_radiance": texels.view(1, 2, 2, 1).expand(1, 2, 2, 3).numpy()},
        {"surf_radiance": torch.zeros(0, 2, 2, 3).numpy()},  # a view without probes adds nothing
    ]
    out = probe_oracle_light(lights, "surf", torch.tensor([2.0, 5.0]))
    pred, target, scale = out["probe_mean_oracle"]
    torch.testing.assert_close(pred, torch.full((4, 3), 4.0))
    torch.testing.assert_close(target[:, 0], texels)
    torch.testing.assert_close(scale, torch.full((4,), 2.0))
    torch.testing.assert_close(out["probe_median_oracle"][0], torch.full((4, 3), 2.0))  # the lower median
    assert probe_oracle_light(lights[1:], "surf", torch.tensor([5.0])) is None
