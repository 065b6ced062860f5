"""The content-blind baseline lights as render-layer callbacks."""

import torch

from pipeline.systems.lighting_baselines import Constants, constant_light, scaled_constant_light


def _constants():
    return Constants(torch.tensor([1.0, 2.0, 3.0]), torch.tensor([0.5, 0.25, 1.0]), {})


def test_constant_light_is_the_mean_training_radiance_everywhere():
    wi = torch.nn.functional.normalize(torch.randn(4, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    out = constant_light(_constants())(torch.arange(4), torch.zeros(4, 3), wi, torch.tensor([0, 1, 1, 0]))
    assert torch.equal(out, _constants().constant.expand(4, 3))


def test_scaled_constant_light_is_the_ratio_at_each_query_images_exposure():
    c = _constants()
    image = torch.tensor([0, 1, 1])
    out = scaled_constant_light(c, torch.tensor([2.0, 4.0]))(None, None, torch.zeros(3, 3), image)
    assert torch.equal(out, c.ratio * torch.tensor([[2.0], [4.0], [4.0]]))
    one_view = scaled_constant_light(c, torch.tensor(3.0))(
        None, None, torch.zeros(2, 3), torch.zeros(2, dtype=torch.long)
    )
    assert torch.equal(one_view, (c.ratio * 3.0).expand(2, 3))
