"""Differential rendering of inserted objects' shadows (`models.shadows`): the one-render difference against
a quadrature of the BRDF over the cone a sphere blocks, and against two explicit renders."""

import math

import numpy as np
import torch

from pipeline.models.insertion import cast_shape, render_case
from pipeline.models.render_layer import RAY_OFFSET_M, MCRenderLayer
from pipeline.models.shadows import object_radiance, occlusion_light, proxy_pixels, shape_bounds
from pipeline.ops import brdf

SIZE, FOV, DEPTH = 5, 60.0, 2.0  # a wall facing the camera, 2 m away; its centre pixel looks along -z


def wall(albedo=0.6, roughness=0.7, metallic=0.0) -> dict:
    ones = torch.ones(1, 1, SIZE, SIZE)
    return {
        "depth": torch.full((1, SIZE, SIZE), DEPTH),
        "normal": torch.cat([0 * ones, 0 * ones, ones], 1),
        "albedo": albedo * torch.ones(1, 3, SIZE, SIZE),
        "material": torch.cat([roughness * ones, metallic * ones], 1),
    }


def uniform(value: float):
    return lambda idx, origin, wi, image: torch.full((len(wi), 3), value, dtype=wi.dtype)


def test_the_difference_is_the_blocked_cone_of_the_brdf():
    """Under a uniform light L = 1, a sphere of radius r centred at distance d above a wall point along its
    normal blocks the cone of half-angle asin(r / d) around the normal; with the object at radiance 0.2 the
    difference at that point is (0.2 - 1) times the cone's integral of the BRDF times the cosine (midpoint
    quadrature of `ops.brdf.evaluate`, viewed along the normal). Within 4 standard errors of 16 seeds."""
    gb, centre = wall(), SIZE * SIZE // 2
    point = torch.tensor([0.0, 0.0, -DEPTH], dtype=torch.float64)
    d, r = 0.5, 0.25
    sphere = torch.cat([point + torch.tensor([0.0, 0.0, d], dtype=torch.float64), torch.tensor([r])])[None]
    light = occlusion_light(uniform(1.0), [sphere], torch.full((1, 3), 0.2), cast_shape)
    estimates = [
        float(render_case(MCRenderLayer(spp=4096), gb, FOV, torch.tensor([centre]), light, seed)[0, 0])
        for seed in range(16)
    ]
    alpha = math.asin(r / (d - RAY_OFFSET_M))  # rays leave the surface RAY_OFFSET_M above it
    theta = (torch.arange(4000, dtype=torch.float64) + 0.5) * alpha / 4000
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand(len(theta), 3)
    wi = torch.stack([torch.sin(theta), torch.zeros_like(theta), torch.cos(theta)], -1)
    fd, fs = brdf.evaluate(
        n,
        n,
        wi,
        torch.full((len(theta), 3), 0.6, dtype=torch.float64),
        torch.full_like(theta, 0.7),
        torch.zeros_like(theta),
    )
    cone = float((2 * math.pi * (fd + fs)[:, 0] * torch.cos(theta) * torch.sin(theta)).sum() * alpha / 4000)
    expected = (0.2 - 1.0) * cone
    se = np.std(estimates, ddof=1) / math.sqrt(len(estimates))
    assert expected < -0.1  # a quarter of the hemisphere's cosine-weighted solid angle, dimmed by 0.8
    assert abs(np.mean(estimates) - expected) < 4 * se + 1e-6, (np.mean(estimates), expected, se)


def test_one_render_of_the_difference_equals_two_renders_subtracted():
    """With the same samples, the occlusion render equals the render with the object (its radiance on the
    rays it blocks) minus the render without it, under a light that varies with direction."""
    gb = wall(albedo=0.5, roughness=0.3, metallic=0.2)
    sphere = torch.tensor([[0.1, 0.05, -1.6, 0.2]], dtype=torch.float64)
    colour = torch.tensor([[0.3, 0.1, 0.05]])

    def sky(idx, origin, wi, image):
        return (1.0 + wi.clamp(min=0)) * torch.tensor([1.0, 0.8, 0.6], dtype=wi.dtype)

    def with_object(idx, origin, wi, image):
        t, _ = cast_shape(sphere, origin.double(), wi.double())
        return torch.where(torch.isfinite(t)[:, None], colour.to(wi.dtype), sky(idx, origin, wi, image))

    pixels, layer = torch.arange(SIZE * SIZE), MCRenderLayer(spp=64)
    difference = render_case(layer, gb, FOV, pixels, occlusion_light(sky, [sphere], colour, cast_shape), 7)
    explicit = render_case(layer, gb, FOV, pixels, with_object, 7) - render_case(layer, gb, FOV, pixels, sky, 7)
    assert difference.abs().max() > 1e-3  # the sphere blocks some rays of some pixels
    torch.testing.assert_close(difference, explicit, rtol=1e-5, atol=1e-6)
    behind = torch.tensor([[0.0, 0.0, -5.0, 0.5]], dtype=torch.float64)  # behind the wall: below its horizon
    blank = render_case(layer, gb, FOV, pixels, occlusion_light(sky, [behind], colour, cast_shape), 7)
    assert torch.count_nonzero(blank) == 0


def test_proxy_pixels_are_the_room_near_an_object_without_its_own_pixels():
    depth = torch.full((SIZE, SIZE), DEPTH)
    depth[0, 0] = 0.0  # no surface there
    sphere = torch.tensor([[0.0, 0.0, -DEPTH + 0.3, 0.25]], dtype=torch.float64)
    centre, radius = shape_bounds(sphere)
    assert radius == 0.25 and torch.equal(centre, sphere[0, :3])
    near = proxy_pixels(depth, FOV, [sphere], exclude=torch.tensor([12]), reach=3.0)
    assert 12 not in near.tolist() and 0 not in near.tolist() and len(near) > 0
    far = proxy_pixels(depth, FOV, [sphere], exclude=torch.tensor([], dtype=torch.long), reach=1.0)
    assert len(far) == 0  # the wall lies 0.3 m from the centre, more than one radius
    mesh = (torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=torch.float64), torch.tensor([[0, 1, 2]]))
    c, rad = shape_bounds(mesh)
    assert torch.allclose(c, torch.tensor([0.5, 0.5, 0.0], dtype=torch.float64)) and rad == math.sqrt(0.5)


def test_object_radiance_is_the_mean_over_each_objects_pixels():
    rgb = torch.tensor([[1.0, 1, 1], [3, 3, 3], [5, 0, 0]])
    out = object_radiance(rgb, torch.tensor([0, 0, 2]), 3)
    torch.testing.assert_close(out, torch.tensor([[2.0, 2, 2], [0, 0, 0], [5, 0, 0]]))


def test_normals_facing_away_from_the_camera_are_flipped_for_the_proxy():
    from pipeline.models.shadows import facing_camera

    gb = wall()
    gb["normal"][0, :, 1, 1] = torch.tensor([0.0, 0.0, -1.0])  # a wall pixel seen from behind
    out = facing_camera(gb, FOV)
    assert torch.equal(out["normal"][0, :, 1, 1], torch.tensor([0.0, 0.0, 1.0]))
    assert torch.equal(out["normal"][0, :, 2, 2], gb["normal"][0, :, 2, 2])  # facing it already: kept
    assert gb["normal"][0, 2, 1, 1] == -1.0  # the input untouched
