"""LightNet pieces: hypernetwork, volume rendering, the SSRT/out-of-view blend, gradients, hard rays."""

import math

import pytest
import torch
from torch import nn

from pipeline.bench.scenes import BoxRoom, ssrt_rays
from pipeline.models.light_net import LightNet, blend, confidence
from pipeline.models.light_net.hyper import HyperMLP
from pipeline.ops.volume import composite, ray_box, scene_bounds, stratified_edges


def test_generated_mlp_equals_an_ordinary_mlp_with_the_same_weights():
    torch.manual_seed(0)
    hyper = HyperMLP(feature_dim=5, sizes=[4, 7, 3])
    params = hyper(torch.randn(2, 5))
    x = torch.randn(6, 4)
    scene = torch.tensor([0, 1, 1, 0, 1, 0])
    out = HyperMLP.run_generated(params, x, scene)
    for b in (0, 1):
        mlp = nn.Sequential(nn.Linear(4, 7), nn.ReLU(), nn.Linear(7, 3))
        with torch.no_grad():
            mlp[0].weight.copy_(params[0][0][b]), mlp[0].bias.copy_(params[0][1][b])
            mlp[2].weight.copy_(params[1][0][b]), mlp[2].bias.copy_(params[1][1][b])
        sel = scene == b
        assert torch.allclose(out[sel], mlp(x[sel]), atol=1e-6)


def test_generated_mlp_same_for_grouped_and_interleaved_points_and_for_none():
    # grouped points skip the sort: same rows as the interleaved order, permuted; zero points -> (0, out)
    torch.manual_seed(3)
    params = HyperMLP(feature_dim=5, sizes=[4, 7, 3])(torch.randn(3, 5))
    x = torch.randn(8, 4)
    scene = torch.tensor([2, 0, 2, 1, 0, 2, 1, 0])
    order = torch.argsort(scene, stable=True)
    interleaved = HyperMLP.run_generated(params, x, scene)
    grouped = HyperMLP.run_generated(params, x[order], scene[order])
    assert torch.equal(grouped, interleaved[order])
    empty = HyperMLP.run_generated(params, x[:0], scene[:0])
    assert empty.shape == (0, 3)


def test_generated_mlp_gradients_match_a_per_point_weight_gather():
    # the grouped evaluation must give the same values and weight gradients as gathering W[scene[i]] per
    # point, also with a scene that has no points
    torch.manual_seed(1)
    hyper = HyperMLP(feature_dim=5, sizes=[4, 6, 2]).double()
    feature = torch.randn(3, 5, dtype=torch.float64, requires_grad=True)
    x = torch.randn(9, 4, dtype=torch.float64)
    scene = torch.tensor([2, 0, 2, 0, 0, 2, 2, 0, 0])  # scene 1 is empty

    def gathered(params):
        h = x
        for k, (w, b) in enumerate(params):
            h = torch.einsum("noi,ni->no", w[scene], h) + b[scene]
            h = h.relu() if k < len(params) - 1 else h
        return h

    a = HyperMLP.run_generated(hyper(feature), x, scene)
    (ga,) = torch.autograd.grad(a.square().sum(), feature)
    b = gathered(hyper(feature))
    (gb,) = torch.autograd.grad(b.square().sum(), feature)
    assert torch.allclose(a, b, atol=1e-12) and torch.allclose(ga, gb, atol=1e-10)


def test_volume_rendering_matches_the_closed_form():
    # constant density s and radiance c on [t0, t1]: L = c (1 - exp(-s (t1 - t0))), for any stratification
    t0, t1, s, c = torch.tensor([0.5, 1.0]), torch.tensor([2.5, 1.2]), 0.8, torch.tensor([1.0, 2.0, 3.0])
    for samples in (1, 7, 64):
        edges, _ = stratified_edges(t0, t1, samples, torch.Generator().manual_seed(0))
        sigma = torch.full((2, samples), s)
        rad, w, left = composite(sigma, c.expand(2, samples, 3), edges)
        expect = 1 - torch.exp(-s * (t1 - t0))
        assert torch.allclose(rad, expect[:, None] * c, atol=1e-6)
        assert torch.allclose(left, 1 - expect, atol=1e-6) and torch.allclose(w.sum(1), expect, atol=1e-6)
    # two slabs: an opaque-ish front hides the back
    edges = torch.tensor([[0.0, 1.0, 2.0]])
    rad, _, _ = composite(torch.tensor([[2.0, 1.0]]), torch.tensor([[[1.0], [5.0]]]), edges)
    a1, a2 = 1 - math.exp(-2.0), 1 - math.exp(-1.0)
    assert rad.item() == pytest.approx(a1 * 1.0 + math.exp(-2.0) * a2 * 5.0, rel=1e-6)


def test_blend_honours_u_at_0_1_and_misses():
    l_ssrt, l_out = torch.tensor([[1.0, 2.0, 3.0]] * 3), torch.tensor([[10.0, 20.0, 30.0]] * 3)
    hit = torch.tensor([True, True, False])
    u = confidence(hit, torch.tensor([0.0, 100.0, 0.0]), k=10.0)
    assert u.tolist() == [0.0, 1.0, 1.0]
    out = blend(l_ssrt, l_out, u)
    assert torch.equal(out[0], l_ssrt[0]) and torch.equal(out[1], l_out[1]) and torch.equal(out[2], l_out[2])
    half = blend(l_ssrt[:1], l_out[:1], torch.tensor([0.5]))
    assert torch.allclose(half, (l_ssrt[:1] + l_out[:1]) / 2)


def test_ray_box_and_scene_bounds():
    lo, hi = torch.tensor([[-1.0, -1.0, -1.0]]), torch.tensor([[1.0, 1.0, 1.0]])
    t0, t1 = ray_box(torch.tensor([[0.0, 0.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]]), lo, hi)
    assert t0.item() == 0.0 and t1.item() == pytest.approx(1.0)
    t0, t1 = ray_box(torch.tensor([[5.0, 5.0, 5.0]]), torch.tensor([[1.0, 0.0, 0.0]]), lo, hi)
    assert t1.item() == t0.item()  # a miss is an empty interval
    # 2 x 4 view, fov_x 90: f = (W/2) / tan(45) = 2, p = z ((j + .5 - 2) / 2, -(i + .5 - 1) / 2, -1) (docs/data.md).
    # Depth 3 except an inf and a 0 (no surface: left out) and a far pixel (row 1, col 3) at 6.
    depth = torch.full((1, 2, 4), 3.0)
    depth[0, 0, 0], depth[0, 0, 1], depth[0, 1, 3] = float("inf"), 0.0, 6.0
    # valid points: x from -2.25 (row 1, col 0) to 4.5 (the far pixel), y from -1.5 (the far pixel) to 0.75
    # (row 0), z from -6 to the camera's 0; the box grows by 0.1 of its size + 0.01 on each side
    lo, hi = torch.tensor([-2.25, -1.5, -6.0]), torch.tensor([4.5, 0.75, 0.0])
    pad = 0.1 * (hi - lo) + 0.01
    b = scene_bounds(depth, 90.0)
    assert b.shape == (1, 2, 3)
    torch.testing.assert_close(b[0], torch.stack([lo - pad, hi + pad]))


def _scene(B=2, H=24, W=32, fov=85.0):
    room = BoxRoom.default(torch.float32)
    depth, normal = room.render(H, W, fov)
    depth, normal = depth.float().repeat(B, 1, 1), normal.float().repeat(B, 1, 1, 1)
    g = torch.Generator().manual_seed(0)
    gbuffer = {
        "depth": depth,
        "normal": normal,
        "albedo": torch.rand(B, 3, H, W, generator=g),
        "material": torch.rand(B, 2, H, W, generator=g),
    }
    im = torch.rand(B, 3, H, W, generator=g) * 4
    o, wi = ssrt_rays(depth[:1], normal[:1], fov, 2, g)
    n = len(o)
    origin, wi = torch.cat([o, o]).float(), torch.cat([wi, wi]).float()
    batch_index = torch.cat([torch.zeros(n), torch.ones(n)]).long()
    return im, gbuffer, fov, origin, wi, batch_index


@pytest.mark.parametrize("mode", ("mixed", "ssrt_only", "out_of_view_only"))
def test_every_mode_gives_finite_non_negative_light_and_gradients_reach_both_branches(mode):
    torch.manual_seed(0)
    im, gbuffer, fov, origin, wi, bidx = _scene()
    net = LightNet(mode=mode, out_of_view={"samples": 8})
    ctx = net.encode(im, gbuffer["depth"], fov)
    out = net(ctx, gbuffer, fov, origin, wi, bidx, torch.Generator().manual_seed(1))
    L = out["radiance"]
    assert L.shape == (len(wi), 3) and torch.isfinite(L).all() and (L >= 0).all()
    L.sum().backward()
    if net.local is not None:
        assert net.local.mlp[-1].weight.grad.abs().sum() > 0
        assert net.local.encoder.stages[0][0][0].weight.grad.abs().sum() > 0
    if net.out_of_view is not None:
        assert net.out_of_view.hyper.heads[0].weight.grad.abs().sum() > 0
        assert out["out_queries"] == (len(wi) if mode != "ssrt_only" else 0)


def test_out_threshold_saves_queries_and_keeps_ssrt_light_below_it():
    torch.manual_seed(0)
    im, gbuffer, fov, origin, wi, bidx = _scene()
    full = LightNet(mode="mixed", out_threshold=0.0, out_of_view={"samples": 4})
    lazy = LightNet(mode="mixed", out_threshold=0.5, out_of_view={"samples": 4})
    lazy.load_state_dict(full.state_dict())
    with torch.no_grad():
        a = full(full.encode(im, gbuffer["depth"], fov), gbuffer, fov, origin, wi, bidx)
        b = lazy(lazy.encode(im, gbuffer["depth"], fov), gbuffer, fov, origin, wi, bidx)
    assert b["out_queries"] == int((a["u"] >= 0.5).sum()) < a["out_queries"]
    same = a["u"] >= 0.5
    assert torch.allclose(a["radiance"][same], b["radiance"][same], atol=1e-5)


def test_hard_rays_stay_finite():
    """Rays leaving the screen, starting on depth edges, pointing into the surface, or from behind the camera."""
    torch.manual_seed(0)
    im, gbuffer, fov, origin, wi, bidx = _scene(B=1)
    n = 6
    origin = torch.cat([origin[:n], torch.tensor([[0.0, 0.0, 0.5]]), origin[:1]])
    wi = torch.cat([wi[:n], torch.tensor([[0.0, 0.0, -1.0]]), -wi[:1]])
    wi[0] = torch.tensor([1.0, 0.0, 0.0])  # straight sideways: leaves the screen
    bidx = torch.zeros(len(wi), dtype=torch.long)
    net = LightNet(mode="mixed", out_of_view={"samples": 4})
    out = net(net.encode(im, gbuffer["depth"], fov), gbuffer, fov, origin, wi, bidx)
    assert torch.isfinite(out["radiance"]).all()
    out["radiance"].sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)


def test_pixel_base_returns_the_hit_pixels_radiance_when_the_correction_is_zero():
    """With g = 0 and a -> -inf the local branch is the image's own HDR value at the SSRT hit."""
    torch.manual_seed(0)
    im, gbuffer, fov, origin, wi, bidx = _scene()
    net = LightNet(mode="ssrt_only", local={"pixel_base": True})
    with torch.no_grad():
        net.local.mlp[-1].weight.zero_()
        net.local.mlp[-1].bias[:3].zero_()
        net.local.mlp[-1].bias[3:].fill_(-60.0)
        out = net(net.encode(im, gbuffer["depth"], fov), gbuffer, fov, origin, wi, bidx)
    from pipeline.models.light_net import trace_views

    pixel, hit, _ = trace_views(gbuffer, fov, origin, wi, bidx)
    assert hit.sum() > 10
    expect = im[bidx[hit], :, pixel[hit, 0], pixel[hit, 1]]
    assert torch.allclose(out["radiance"][hit], expect, rtol=1e-5, atol=1e-6)
    assert (out["radiance"][~hit] == 0).all()  # ssrt_only: misses get no light


def test_pixel_base_gradients_reach_the_encoder_and_mlp():
    torch.manual_seed(0)
    im, gbuffer, fov, origin, wi, bidx = _scene()
    net = LightNet(mode="mixed", local={"pixel_base": True}, out_of_view={"samples": 4})
    out = net(net.encode(im, gbuffer["depth"], fov), gbuffer, fov, origin, wi, bidx)
    assert torch.isfinite(out["radiance"]).all() and (out["radiance"] >= 0).all()
    out["radiance"].sum().backward()
    assert net.local.mlp[-1].weight.grad.abs().sum() > 0
    assert net.local.encoder.stages[0][0][0].weight.grad.abs().sum() > 0


@pytest.mark.parametrize("interleave", (False, True))
def test_chunked_queries_equal_one_pass_over_all_rays(monkeypatch, interleave):
    """Both branches split their rays into cache-sized chunks; with chunks of a few rays (several per image,
    images interleaved or grouped) radiance and every gradient equal one pass over all rays, in float64."""
    from pipeline.models.light_net import branches

    torch.manual_seed(0)
    im, gbuffer, fov, origin, wi, bidx = _scene()
    if interleave:  # rays of the two images alternate, so every chunk regroups them by image
        perm = torch.randperm(len(wi), generator=torch.Generator().manual_seed(2))
        origin, wi, bidx = origin[perm], wi[perm], bidx[perm]
    gbuffer = {k: v.double() for k, v in gbuffer.items()}
    net = LightNet(mode="mixed", out_of_view={"samples": 4}).double()

    def run(ray_chunk, point_chunk):
        monkeypatch.setattr(branches, "RAY_CHUNK", ray_chunk)
        monkeypatch.setattr(branches, "POINT_CHUNK", point_chunk)
        net.zero_grad()
        ctx = net.encode(im.double(), gbuffer["depth"], fov)
        L = net(ctx, gbuffer, fov, origin.double(), wi.double(), bidx, torch.Generator().manual_seed(1))["radiance"]
        (L * torch.linspace(0.5, 1.5, 3, dtype=L.dtype)).sum().backward()
        return L.detach(), {n: p.grad.clone() for n, p in net.named_parameters() if p.grad is not None}

    one_pass, grads = run(1 << 40, 1 << 40)
    assert len(wi) > 7 * 4
    chunked, chunk_grads = run(7, 4 * 5)  # 7 rays per local chunk, 5 rays per volume-rendering chunk
    assert torch.allclose(chunked, one_pass, rtol=1e-12, atol=1e-12)
    assert grads.keys() == chunk_grads.keys() and len(grads) > 10
    for name, g in grads.items():
        assert torch.allclose(chunk_grads[name], g, rtol=1e-10, atol=1e-12), name


@pytest.mark.parametrize("mode", ("mixed", "ssrt_only", "out_of_view_only"))
def test_no_rays_give_no_radiance(mode):
    # a batch whose every pixel is masked out queries zero rays: an empty result, not an error
    torch.manual_seed(0)
    im, gbuffer, fov, origin, wi, bidx = _scene()
    net = LightNet(mode=mode, out_of_view={"samples": 4})
    with torch.no_grad():
        L = net(net.encode(im, gbuffer["depth"], fov), gbuffer, fov, origin[:0], wi[:0], bidx[:0])["radiance"]
    assert L.shape == (0, 3)


def test_exp_activation_reaches_lamp_radiance_and_keeps_densities_softplus():
    """`activation: exp` maps the radiance heads through exp (clamped at EXP_MAX), so a texel 100x the image
    mean is a pre-activation of log(100) = 4.6; the densities stay softplus, so the same raw output gives
    the same transmittance as with softplus; huge pre-activations stay finite."""
    from pipeline.models.light_net.branches import EXP_MAX, _activate

    x = torch.tensor([-50.0, 0.0, math.log(100.0), 1e4])
    torch.testing.assert_close(_activate(x, "exp"), torch.tensor([math.exp(-50.0), 1.0, 100.0, math.exp(EXP_MAX)]))
    torch.manual_seed(0)
    im, gbuffer, fov, origin, wi, bidx = _scene(B=1)
    n = min(len(wi), 64)
    origin, wi, bidx = origin[:n], wi[:n], torch.zeros(n, dtype=torch.long)
    nets = {
        a: LightNet(mode="out_of_view_only", out_of_view={"samples": 4, "activation": a}) for a in ("softplus", "exp")
    }
    nets["exp"].load_state_dict(nets["softplus"].state_dict())
    seen = {}
    for name, net in nets.items():
        branch = net.out_of_view
        real = branch._march
        branch._march = lambda params, pts, edges, b, scale, real=real, name=name: seen.setdefault(
            name, real(params, pts, edges, b, scale)
        )
        out = net(net.encode(im, gbuffer["depth"], fov), gbuffer, fov, origin, wi, bidx)
        assert torch.isfinite(out["radiance"]).all() and (out["radiance"] >= 0).all()
    torch.testing.assert_close(seen["exp"][1], seen["softplus"][1])  # transmittance left: the same densities
    assert not torch.allclose(seen["exp"][0], seen["softplus"][0])  # radiance: another activation


def test_absolute_units_read_the_raw_image_and_cap_the_local_branch():
    """units=absolute (the released convention, `import-released lightnet`): the encoders see the raw HDR
    image, radiance is in the image's own units (unit 1, so doubling the exposure is a new input, not the
    same light twice as bright), and local.cap bounds the local branch; image_mean units scale with
    exposure exactly."""
    torch.manual_seed(0)
    im, gbuffer, fov, origin, wi, bidx = _scene()
    rel = LightNet(mode="ssrt_only")
    ab = LightNet(mode="ssrt_only", units="absolute", local={"cap": 2.0})
    ab.load_state_dict(rel.state_dict())
    with torch.no_grad():
        ctx = ab.encode(im, gbuffer["depth"], fov)
        assert torch.equal(ctx["unit"], torch.ones(2)) and torch.allclose(ctx["scale"], im.mean(dim=(1, 2, 3)))
        raw = ab.local.encoder(im.clamp(min=0))[: ab.local.levels]
        assert all(torch.equal(a, b) for a, b in zip(ctx["local"], raw, strict=True))
        for b in ab.local.mlp[-1].bias, rel.local.mlp[-1].bias:
            b.fill_(50.0)  # far above the cap
        out = ab(ctx, gbuffer, fov, origin, wi, bidx)["radiance"]
        hit = out.abs().sum(-1) > 0
        assert hit.sum() > 10 and torch.allclose(out[hit], torch.full_like(out[hit], 2.0))
        one = rel(rel.encode(im, gbuffer["depth"], fov), gbuffer, fov, origin, wi, bidx)["radiance"]
        two = rel(rel.encode(2 * im, gbuffer["depth"], fov), gbuffer, fov, origin, wi, bidx)["radiance"]
        assert torch.allclose(two, 2 * one, rtol=1e-5) and one.max() > 2.0  # no cap by default
    with pytest.raises(ValueError, match="model.light_net.units='metres'"):
        LightNet(units="metres")
    with pytest.raises(ValueError, match="local.cap=0"):
        LightNet(local={"cap": 0})
