"""The options that reproduce the released networks: the blend's window-depth gap against an explicit
OpenGL projection, the sphere bounds, random Fourier features, the skip MLP, the split hypernetwork and
the MGNet layout's shapes and output ranges."""

import math

import numpy as np
import pytest
import torch

from pipeline.models.light_net import LightNet, trace_views
from pipeline.models.light_net.branches import LocalBranch, OutOfViewBranch, SkipMLP
from pipeline.models.light_net.hyper import HyperMLP
from pipeline.models.material_net import MaterialNet
from pipeline.ops.camera import depth_range, window_depth_difference
from pipeline.ops.encodings import fourier, random_fourier
from pipeline.ops.volume import ray_sphere


def _opengl_perspective(fovy: float, aspect: float, near: float, far: float) -> np.ndarray:
    """The classic gluPerspective / glm::perspective matrix (right-handed, clip z in [-1, 1])."""
    f = 1.0 / math.tan(fovy / 2)
    return np.array(
        [
            [f / aspect, 0, 0, 0],
            [0, f, 0, 0],
            [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)],
            [0, 0, -1, 0],
        ]
    )


def _window_z(points: np.ndarray, proj: np.ndarray) -> np.ndarray:
    """OpenGL window depth (0.5 ndc_z + 0.5) of eye-space points (N, 3), camera looking down -z."""
    clip = np.c_[points, np.ones(len(points))] @ proj.T
    return 0.5 * clip[:, 2] / clip[:, 3] + 0.5


def test_window_gap_equals_the_released_projection_of_the_same_points():
    """The released code divides view depth by the image's largest depth, projects with near = min/max
    and far = 1, and measures the gap as a difference of window depths. The closed form must give the
    same number for the same pair of points (ray and surface on one pixel's line of sight)."""
    rng = np.random.default_rng(0)
    d_min, d_max = 0.8, 6.5
    z_s = rng.uniform(d_min, d_max, 200)
    z_r = z_s + rng.uniform(0, 2.0, 200)  # the ray already behind the surface
    xy = rng.uniform(-0.5, 0.5, (200, 2))  # a pixel's line of sight: x, y proportional to depth
    proj = _opengl_perspective(math.radians(60), 4 / 3, d_min / d_max, 1.0)
    surf = np.c_[xy * z_s[:, None], -z_s] / d_max
    ray = np.c_[xy * z_r[:, None], -z_r] / d_max
    expected = _window_z(ray, proj) - _window_z(surf, proj)
    got = window_depth_difference(
        torch.tensor(z_s), torch.tensor(z_r), torch.full((200,), d_min, dtype=torch.float64), torch.tensor(d_max)
    )
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-9, atol=1e-12)
    assert (got >= 0).all()


def test_depth_range_ignores_invalid_pixels():
    depth = torch.tensor([[[0.0, 2.0], [float("inf"), 5.0]], [[0.0, 0.0], [0.0, 0.0]]])
    lo, hi = depth_range(depth)
    assert lo.tolist() == [2.0, 1.0] and hi.tolist() == [5.0, 1.0]


def test_window_gap_changes_u_only_through_the_gap():
    """The same rays through `metres` and `window`: hits keep their pixels, misses keep u = 1, and a
    window-depth u equals tanh(k * the window gap of the metric gap)."""
    torch.manual_seed(0)
    H, W = 12, 16
    depth = torch.full((1, H, W), 3.0)
    depth[0, :, 8:] = 1.5  # a step: rays can slip behind its edge
    gb = {
        "depth": depth,
        "normal": torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1).expand(1, 3, H, W).contiguous(),
        "albedo": torch.full((1, 3, H, W), 0.5),
        "material": torch.full((1, 2, H, W), 0.5),
    }
    origin = torch.tensor([[0.3, 0.1, -1.4]]).expand(64, 3).contiguous()
    wi = torch.nn.functional.normalize(
        torch.randn(64, 3) * torch.tensor([1.0, 1.0, 0.3]) - torch.tensor([0, 0, 1.0]), dim=-1
    )
    bidx = torch.zeros(64, dtype=torch.long)
    pixel, hit, gap = trace_views(gb, 60.0, origin, wi, bidx)
    outs = {}
    for units in ("metres", "window"):
        net = LightNet(mode="ssrt_only", gap_units=units, local={"hidden": 8, "layers": 1})
        ctx = net.encode(torch.rand(1, 3, H, W), depth, 60.0)
        outs[units] = net(ctx, gb, 60.0, origin, wi, bidx)
    m, w = outs["metres"], outs["window"]
    assert torch.equal(m["hit"], hit) and torch.equal(w["hit"], hit) and hit.any() and (~hit).any()
    assert (w["u"][~hit] == 1).all() and (m["u"][~hit] == 1).all()
    z_s = depth[0, pixel[hit, 0], pixel[hit, 1]]
    torch.testing.assert_close(m["u"][hit], torch.tanh(10 * gap[hit]))
    expected = torch.tanh(10 * window_depth_difference(z_s, z_s + gap[hit], torch.tensor(1.5), torch.tensor(3.0)))
    torch.testing.assert_close(w["u"][hit], expected)
    assert (gap[hit] > 0).any() and not torch.equal(w["u"], m["u"])


def test_ray_sphere_exit_distance():
    o = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -2.0]])
    w = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    t = ray_sphere(o, w, 3.0)
    assert t.tolist() == pytest.approx([3.0, 2.0, 1.0])
    end = o + t[:, None] * w
    assert end.norm(dim=-1).tolist() == pytest.approx([3.0] * 3)


def test_sphere_bounds_render_positions_in_units_of_the_max_depth():
    """With an empty NeRF (zero density) the sphere branch returns 0 (nothing behind the sphere, no far
    field); the query scales positions by the view's max depth, so doubling both the scene and the max
    depth leaves the radiance unchanged."""
    torch.manual_seed(0)
    branch = OutOfViewBranch(
        feature_dim=None,
        nerf_hidden=8,
        nerf_layers=1,
        samples=8,
        bounds="sphere",
        far_field=False,
        activation="relu",
        pi_encoding=False,
    )
    feature, params = branch.encode(torch.rand(1, 3, 32, 32))
    o, w = torch.randn(5, 3) * 0.3, torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    b = torch.zeros(5, dtype=torch.long)
    scale = torch.ones(1)
    r1 = branch.query(feature, params, scale, None, b, o, w, depth_max=torch.tensor([2.0]))
    r2 = branch.query(feature, params, scale, None, b, 2 * o, w, depth_max=torch.tensor([4.0]))
    torch.testing.assert_close(r1, r2)
    zero = [(torch.zeros_like(wt), torch.zeros_like(bs)) for wt, bs in params]
    assert branch.query(feature, zero, scale, None, b, o, w, depth_max=torch.tensor([2.0])).abs().max() == 0
    with pytest.raises(ValueError, match="depth_max"):
        branch.query(feature, params, scale, None, b, o, w)


def test_fourier_without_pi_and_random_fourier_features():
    x = torch.tensor([[0.25, 0.5, 1.0]])
    enc = fourier(x, 2, pi=False)
    # sines per coordinate: x, 2x
    torch.testing.assert_close(enc[0, 3:9], torch.sin(torch.tensor([0.25, 0.5, 0.5, 1.0, 1.0, 2.0])))
    basis = torch.randn(3, 7)
    rff = random_fourier(x, basis)
    assert rff.shape == (1, 14)
    torch.testing.assert_close(rff[:, :7] ** 2 + rff[:, 7:] ** 2, torch.ones(1, 7))


def test_skip_mlp_feeds_the_input_again_and_validates_skips():
    mlp = SkipMLP(5, 16, 4, 3, skips=[1])
    assert mlp[2].in_features == 16 + 5 and mlp[-1].out_features == 3
    assert mlp(torch.randn(7, 5)).shape == (7, 3)
    with pytest.raises(ValueError, match="skips"):
        SkipMLP(5, 16, 4, 3, skips=[3])


def test_rff_local_branch_keeps_its_bases_in_the_state_dict():
    torch.manual_seed(0)
    branch = LocalBranch(encoding="rff", rff_features=4, hidden=16, layers=3, skips=[1], activation="relu")
    keys = [k for k in branch.state_dict() if k.startswith("rff_")]
    assert sorted(keys) == ["rff_direction", "rff_kd", "rff_ks", "rff_normal", "rff_roughness"]
    torch.manual_seed(1)
    other = LocalBranch(encoding="rff", rff_features=4, hidden=16, layers=3, skips=[1], activation="relu")
    other.load_state_dict(branch.state_dict())
    feats = branch.encode(torch.rand(1, 3, 16, 16))
    px = torch.tensor([[3, 4], [10, 2]])
    args = (torch.ones(1), torch.zeros(2, dtype=torch.long), px, (16, 16), torch.randn(2, 3), torch.rand(2, 10))
    torch.testing.assert_close(branch.query(feats, *args), other.query(feats, *args))
    assert (branch.query(feats, *args) >= 0).all()


def test_split_hypernetwork_emits_leaky_parameters_of_the_right_shapes():
    hyper = HyperMLP(6, [5, 4, 2], trunk=(8, 8), head_hidden=(12,), split_bias=True, param_activation="leaky_relu")
    params = hyper(torch.randn(3, 6))
    assert [(tuple(w.shape), tuple(b.shape)) for w, b in params] == [((3, 4, 5), (3, 4)), ((3, 2, 4), (3, 2))]
    neg = torch.cat([w.flatten() for w, _ in params])
    assert (neg < 0).any()  # leaky: negative parameters survive, scaled by 0.1
    with pytest.raises(ValueError, match="param_activation"):
        HyperMLP(6, [5, 2], param_activation="tanh")


def test_mgnet_layout_shapes_ranges_and_refusals():
    torch.manual_seed(0)
    net = MaterialNet(
        "densenet121", [32, 16, 16, 8, 8], layout="mgnet", decoder_groups=[4, 4, 4, 2, 2], input_norm="clamp"
    ).eval()
    out = net(torch.rand(1, 3, 50, 70) * 3)  # odd sizes: skips and the full resolution still line up
    assert out["albedo"].shape == (1, 3, 50, 70) and out["depth"].shape == (1, 1, 50, 70)
    assert 0 <= out["albedo"].min() and out["albedo"].max() <= 1 and out["depth"].min() >= 1e-3
    torch.testing.assert_close(out["normal"].norm(dim=1), torch.ones(1, 50, 70))
    with pytest.raises(ValueError, match="densenet121"):
        MaterialNet("resnet34", [32, 16, 16, 8, 8], layout="mgnet", decoder_groups=[4, 4, 4, 2, 2])
    with pytest.raises(ValueError, match="input_norm"):
        MaterialNet("small", input_norm="gamma")
