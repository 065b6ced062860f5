"""The re-render loss's two estimators (`lighting.render_loss`): in expectation `squared` is the squared
bias plus the Monte Carlo variance of one render, `decorrelated` the squared bias alone, at equal samples.

A flat glossy patch under an analytic light with a sharp lobe (a small bright cap over a dim sky), the same
pixel re-rendered N times: each term's mean over the N copies is compared with the bias and variance
measured from an independent sample of renders, within 5 standard errors (from the
measured moments of one render)."""

import pytest
import torch

from pipeline.models.export import LIGHT_FORMAT, read_export
from pipeline.systems.lighting import LightingSystem

N = 80000  # copies of the pixel per loss evaluation
SPP = 8


def _system(micro_exports, render_loss):
    light = read_export(micro_exports / "light.pt", LIGHT_FORMAT)["light_net"]
    render = {"estimator": "importance", "spp": SPP, "eval_spp": SPP, "seed": 0}
    system = LightingSystem(
        light_net=light, material=None, render=render, gbuffers="ground_truth", render_loss=render_loss
    )
    cap = torch.nn.functional.normalize(torch.tensor([0.3, 0.2, 1.0], dtype=torch.float64), dim=0)

    def light_fn(ctx, gb, fov, generator):  # a bright cap of ~0.3 sr towards the camera's side, dim elsewhere
        def radiance(idx, origin, wi, image):
            inside = (wi.double() @ cap) > 0.95
            return torch.where(inside, 10.0, 0.2).to(wi.dtype).unsqueeze(-1).expand(-1, 3)

        return radiance

    system.light_fn = light_fn
    return system


def _gbuffer():
    """One 2x2 view of a wall facing the camera 2 m away: glossy grey dielectric."""
    return {
        "depth": torch.full((1, 2, 2), 2.0),
        "normal": torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1).expand(1, 3, 2, 2).contiguous(),
        "albedo": torch.full((1, 3, 2, 2), 0.5),
        "material": torch.stack([torch.full((1, 2, 2), 0.2), torch.zeros(1, 2, 2)], 1),
    }


@pytest.mark.parametrize("render_loss", ["squared", "decorrelated"])
def test_render_loss_expectation_is_bias_squared_plus_what_it_should_carry(micro_exports, render_loss):
    torch.manual_seed(0)
    system = _system(micro_exports, render_loss)
    gb, fov, scale = _gbuffer(), torch.tensor([60.0]), torch.ones(1)
    pix = torch.zeros(N, dtype=torch.long)
    # the one-render estimator at the training layer's samples, measured apart: its mean and variance
    layer = system.train_layer
    samples, _ = layer.render_pixels(gb, fov, pix, system.light_fn(None, gb, fov, None), system.generator)
    mean, var = samples.double().mean(0), samples.double().var(0)
    target = (mean * 0.5).float().expand(N, 3)  # a biased light: the render is twice too bright
    bias2 = (mean * 0.5) ** 2
    reps = 4
    got = sum(float(system.render_term(None, gb, fov, pix, target, scale)) for _ in range(reps)) / reps
    err2 = (samples.double() - target.double()) ** 2  # one estimate's squared error, per copy
    if render_loss == "squared":
        # one render of all the layer's samples: the loss carries that render's variance
        expected, term_var = float((bias2 + var).mean()), float(err2.mean(1).var())
    else:  # two independent renders: E[(r1 - t)(r2 - t)] = bias^2, Var = E[(r - t)^2]^2 - bias^4
        expected, term_var = float(bias2.mean()), float((err2.mean(0) ** 2 - bias2**2).mean())
    sigma = (term_var / (N * reps)) ** 0.5
    assert abs(got - expected) < 5 * sigma, (got, expected, sigma)
    # the variance this light puts into the squared loss dwarfs the bias: what the decorrelated term removes
    assert float(var.mean()) > 3 * float(bias2.mean())


@pytest.mark.parametrize(
    ("spp", "render_loss", "message"),
    [(1, "decorrelated", "render_loss=decorrelated needs at least 2"), (2, "l1", "lighting.render_loss='l1'")],
)
def test_bad_render_loss_settings_are_refused(micro_exports, spp, render_loss, message):
    light = read_export(micro_exports / "light.pt", LIGHT_FORMAT)["light_net"]
    render = {"estimator": "importance", "spp": spp, "eval_spp": spp, "seed": 0}
    with pytest.raises(ValueError, match=message):
        LightingSystem(light_net=light, material=None, render=render, gbuffers="ground_truth", render_loss=render_loss)
