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
        normal, albedo, rough, metal, mask, 60.0, lambda k, wi: torch.ones(len(k), 3), torch.Generator().manual_seed(0)
    )
    counts = out["counts"][0, 0]
    assert counts[2, 2] == counts[1:].max() and counts[2, 2] > counts[1, 1]


def test_from_config_reads_the_render_group_at_the_chosen_spp():
    render = {"estimator": "uniform", "spp": 4, "eval_spp": 32, "adaptive": True, "li_size": [4, 8], "chunk": 99}
    train, ev = MCRenderLayer.from_config(render), MCRenderLayer.from_config(render, "eval_spp")
    assert (train.spp, ev.spp) == (4, 32)
    assert (ev.estimator, ev.adaptive, ev.li_size, ev.chunk) == ("uniform", True, (4, 8), 99)
    defaults = MCRenderLayer.from_config({"estimator": "importance", "spp": 2})
    assert (defaults.adaptive, defaults.li_size, defaults.chunk) == (False, (8, 16), 1 << 16)


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


def _pixel_gbuffer(dtype=torch.float64):
    """Two 3x4 views of a tilted plane at 2-3 m with random materials; every pixel valid."""
    g = torch.Generator().manual_seed(5)
    B, H, W = 2, 3, 4
    normal = torch.nn.functional.normalize(torch.tensor([0.2, 0.3, 1.0], dtype=dtype), dim=0)
    return {
        "depth": 2.0 + torch.rand(B, H, W, generator=g, dtype=dtype),
        "normal": normal.view(1, 3, 1, 1).expand(B, 3, H, W).clone(),
        "albedo": 0.1 + 0.8 * torch.rand(B, 3, H, W, generator=g, dtype=dtype),
        "material": torch.stack(
            [0.2 + 0.7 * torch.rand(B, H, W, generator=g, dtype=dtype), torch.rand(B, H, W, generator=g, dtype=dtype)],
            1,
        ),
    }


@pytest.mark.parametrize("estimator", ("importance", "li2020"))
def test_render_pixels_gradients_match_finite_differences(estimator):
    """The re-render path training uses (`render_pixels`): float64 gradcheck. With the li2020 grid the
    directions are fixed, so the G-buffers and the light parameter are all checked; importance sampling
    draws its directions from the material (detached by design: the estimator's gradient is that of the
    fixed-sample sum), so a finite difference in the material moves the samples, and only the light
    parameter (what LightNet trains through) is checked there."""
    gb = _pixel_gbuffer()
    pixels = torch.tensor([0, 5, 11, 13, 22])
    layer = MCRenderLayer(estimator, spp=6, li_size=(3, 6), chunk=7)
    sky = torch.tensor([0.3, 0.5, 0.9], dtype=torch.float64)

    def f(albedo, material, level):
        g = {**gb, "albedo": albedo, "material": material}

        def radiance(k, origin, wi, image):  # depends on direction, origin and the image index
            return level * (1.5 + wi[:, 1:2] + 0.1 * origin[:, :1] + 0.2 * image[:, None]) * sky

        rgb, _ = layer.render_pixels(g, 70.0, pixels, radiance, torch.Generator().manual_seed(9))
        return rgb

    level = torch.tensor(1.3, dtype=torch.float64, requires_grad=True)
    if estimator == "li2020":
        args = (gb["albedo"].requires_grad_(), gb["material"].requires_grad_(), level)
        assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6, rtol=1e-4)
    else:
        assert torch.autograd.gradcheck(lambda lv: f(gb["albedo"], gb["material"], lv), (level,), eps=1e-6)


def test_render_pixels_agrees_with_the_image_layer_and_reports_images():
    """Pixel re-rendering shades the same points as the full-image layer: under a constant light the
    result depends on no random number, so both paths must agree exactly where they meet."""
    gb = _pixel_gbuffer(torch.float32)
    layer = MCRenderLayer("li2020", li_size=(4, 8))
    pixels = torch.arange(24)
    rgb, image = layer.render_pixels(
        gb, 70.0, pixels, lambda k, o, wi, b: torch.ones(len(wi), 3), torch.Generator().manual_seed(0)
    )
    assert image.tolist() == [0] * 12 + [1] * 12
    full = layer(
        gb["normal"],
        gb["albedo"],
        gb["material"][:, :1],
        gb["material"][:, 1:],
        torch.ones(2, 1, 3, 4),
        70.0,
        lambda k, wi: torch.ones(len(wi), 3),
        torch.Generator().manual_seed(1),
    )["rgb"]
    torch.testing.assert_close(rgb, full.permute(0, 2, 3, 1).reshape(-1, 3), rtol=1e-5, atol=1e-6)
