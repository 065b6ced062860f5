import pytest
import torch

from pipeline.models.render_layer import MCRenderLayer


def _gbuffer(B=2, H=6, W=8):
    g = torch.Generator().manual_seed(0)
    normal = torch.zeros(B, 3, H, W)
    normal[:, 2] = 1.0
    normal[:, 1] = 0.3 * torch.rand(B, H, W, generator=g)
    albedo = torch.rand(B, 3, H, W, generator=g)
    rough = torch.rand(B, 1, H, W, generator=g)
    metal = (torch.rand(B, 1, H, W, generator=g) > 0.5).float()
    mask = torch.ones(B, 1, H, W)
    mask[:, :, 0] = 0
    return normal, albedo, rough, metal, mask


@pytest.mark.parametrize("estimator", ("importance", "uniform", "li2020"))
@pytest.mark.parametrize("adaptive", (False, True))
def test_shapes_mask_counts_and_gradients(estimator, adaptive):
    normal, albedo, rough, metal, mask = _gbuffer()
    albedo.requires_grad_()
    rough.requires_grad_()
    level = torch.nn.Parameter(torch.tensor(2.0))
    layer = MCRenderLayer(estimator, spp=4, adaptive=adaptive, li_size=(4, 8), chunk=37)
    out = layer(
        normal,
        albedo,
        rough,
        metal,
        mask,
        60.0,
        lambda k, wi: level * (1 + wi[:, 2:]).expand(-1, 3),
        torch.Generator().manual_seed(1),
    )
    for key in ("diffuse", "specular", "rgb"):
        assert out[key].shape == (2, 3, 6, 8) and torch.isfinite(out[key]).all()
        assert (out[key][:, :, 0] == 0).all()
    valid = int(mask.sum())
    expected = 32 * valid if estimator == "li2020" else 4 * valid
    assert int(out["counts"].sum()) == expected and (out["counts"][:, :, 0] == 0).all()
    out["rgb"].sum().backward()
    assert level.grad is not None and level.grad > 0
    assert albedo.grad.abs()[:, :, 1:].sum() > 0 and (albedo.grad[:, :, 0] == 0).all()
    assert rough.grad is not None and torch.isfinite(rough.grad).all()


def test_adaptive_gives_glossy_pixels_more_samples():
    normal, albedo, rough, metal, mask = _gbuffer(1, 4, 4)
    rough[:] = 0.9
    metal[:] = 0.0
    rough[0, 0, 2, 2], metal[0, 0, 2, 2] = 0.05, 1.0
    out = MCRenderLayer("importance", spp=8, adaptive=True)(
        normal, albedo, rough, metal, mask, 60.0, lambda k, wi: torch.ones(len(k), 3)
    )
    counts = out["counts"][0, 0]
    assert counts[2, 2] == counts[1:].max() and counts[2, 2] > counts[1, 1]


def test_bad_configuration_names_the_key():
    with pytest.raises(ValueError, match="render.estimator='stratified'"):
        MCRenderLayer("stratified")
    with pytest.raises(ValueError, match="render.spp=0"):
        MCRenderLayer(spp=0)


def test_white_furnace_on_an_image():
    """Constant unit radiance on Lambertian-ish white pixels: the diffuse image is the albedo within 4 sigma."""
    normal, albedo, rough, metal, mask = _gbuffer(1, 20, 20)
    albedo[:] = 0.8
    metal[:] = 0.0
    out = MCRenderLayer("importance", spp=16)(
        normal, albedo, rough, metal, mask, 60.0, lambda k, wi: torch.ones(len(k), 3), torch.Generator().manual_seed(3)
    )
    vals = out["diffuse"][0, 0][mask[0, 0] > 0]
    assert abs(vals.mean().item() - 0.8) <= 4 * vals.std().item() / vals.numel() ** 0.5
