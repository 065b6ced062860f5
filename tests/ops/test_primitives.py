"""Analytic ray casting against sphere unions and the inserted objects' geometry."""

import math

import numpy as np
import pytest
import torch

from pipeline.ops.envmap import sphere_directions, sphere_lookup
from pipeline.ops.primitives import LIFT_M, object_spheres, raycast_spheres


def test_raycast_hits_the_nearest_front_surface_with_outward_normals():
    spheres = torch.tensor([[0.0, 0.0, -5.0, 1.0], [0.0, 0.0, -3.0, 0.5]], dtype=torch.float64)
    o = torch.zeros(4, 3, dtype=torch.float64)
    d = torch.tensor(
        [[0, 0, -1.0], [0, 1.0, 0], [0.0, math.sin(0.18), -math.cos(0.18)], [0.0, 0.0, 1.0]], dtype=torch.float64
    )
    t, n = raycast_spheres(o, d, spheres)
    assert t[0] == pytest.approx(2.5)  # the nearer, smaller sphere
    assert torch.allclose(n[0], torch.tensor([0, 0, 1.0], dtype=torch.float64))
    assert math.isinf(t[1]) and math.isinf(t[3]) and torch.all(n[1] == 0)
    # a ray grazing past the small sphere (angle 0.18 > asin(0.5/3), < asin(1/5)) hits the big one: exact chord geometry
    b = -5 * math.cos(0.18)
    assert t[2] == pytest.approx(-b - math.sqrt(b * b - 24.0), rel=1e-12)
    hit = o[2] + t[2] * d[2]
    assert torch.allclose(n[2], (hit - spheres[0, :3]) / 1.0)


def test_rays_starting_inside_a_sphere_do_not_hit_it():
    t, _ = raycast_spheres(torch.zeros(1, 3), torch.tensor([[1.0, 0, 0]]), torch.tensor([[0.0, 0, 0, 2.0]]))
    assert math.isinf(float(t[0]))


def test_snowman_is_two_overlapping_spheres_resting_on_its_base_along_the_axis():
    base, axis = torch.tensor([1.0, 0.5, -2.0]), torch.nn.functional.normalize(torch.tensor([0.2, 1.0, 0.1]), dim=0)
    s = object_spheres("snowman", base, axis, 0.3)
    (c1, r1), (c2, r2) = (s[0, :3], s[0, 3]), (s[1, :3], s[1, 3])
    assert float((c2 - c1).norm()) < float(r1 + r2)  # overlap: a concave neck between them
    lowest = c1 - axis.double() * r1
    assert torch.allclose(lowest, base.double() + axis.double() * LIFT_M)
    sphere = object_spheres("sphere", base, axis, 0.3, resting=False)
    assert torch.allclose(sphere[0, :3], base.double()) and float(sphere[0, 3]) == pytest.approx(0.3)
    floating = object_spheres("snowman", base, axis, 0.3, resting=False)  # centred on the point
    top = floating[1, :3] + axis.double() * floating[1, 3]
    bottom = floating[0, :3] - axis.double() * floating[0, 3]
    assert torch.allclose((top + bottom) / 2, base.double())
    with pytest.raises(ValueError, match="object kind"):
        object_spheres("cube", base, axis, 0.3)


def test_sphere_lookup_is_exact_at_texel_centres_and_periodic_in_azimuth():
    rows, cols = 6, 12
    maps = torch.rand(2, rows, cols, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    dirs = torch.from_numpy(sphere_directions(rows, cols)).reshape(-1, 3)
    for p in range(2):
        got = sphere_lookup(maps, torch.full((len(dirs),), p), dirs)
        assert torch.allclose(got, maps[p].reshape(-1, 3), atol=1e-12)
    # halfway between the last and first column of a row: the mean of the two (wraps around phi = 0)
    theta = (2 + 0.5) / rows * math.pi
    wi = torch.tensor([[0.0, math.cos(theta), -math.sin(theta)]], dtype=torch.float64)  # phi = 0
    got = sphere_lookup(maps, torch.zeros(1, dtype=torch.long), wi)
    assert torch.allclose(got[0], (maps[0, 2, 0] + maps[0, 2, -1]) / 2, atol=1e-12)
    assert np.isfinite(got.numpy()).all()
