"""ops.meshes: ray casting against a triangle mesh agrees with an analytic box, and placing a mesh scales,
turns and rests it as documented."""

import math

import torch

from pipeline.ops.meshes import lathe, place_mesh, raycast_mesh, rotation_to


def _cube() -> tuple[torch.Tensor, torch.Tensor]:
    """The unit cube [0, 1]^3 as 12 outward counter-clockwise triangles."""
    v = torch.tensor([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=torch.float64)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = [tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))]
    return v, torch.tensor(f)


def _slab_hit(origin, direction):
    """Analytic nearest hit with the unit cube (slab method) from outside: t (N,), inf on a miss."""
    inv = 1.0 / direction
    t0, t1 = (0 - origin) * inv, (1 - origin) * inv
    near = torch.minimum(t0, t1).max(-1).values
    far = torch.maximum(t0, t1).min(-1).values
    return torch.where((far >= near) & (near > 0), near, torch.full_like(near, float("inf")))


def test_raycast_matches_the_analytic_cube():
    g = torch.Generator().manual_seed(0)
    origin = torch.rand(2000, 3, generator=g, dtype=torch.float64) * 6 - 3
    origin = origin[((origin < -0.1) | (origin > 1.1)).any(-1)]  # outside the cube
    target = torch.rand(len(origin), 3, generator=g, dtype=torch.float64) * 1.6 - 0.3
    direction = torch.nn.functional.normalize(target - origin, dim=-1)
    t, normal = raycast_mesh(origin, direction, *_cube())
    ref = _slab_hit(origin, direction)
    assert (torch.isfinite(t) == torch.isfinite(ref)).all()
    hit = torch.isfinite(ref)
    assert hit.sum() > 300 and (~hit).sum() > 100
    torch.testing.assert_close(t[hit], ref[hit], rtol=1e-9, atol=1e-9)
    point = origin[hit] + t[hit, None] * direction[hit]
    # the normal is the axis of the face hit, facing the ray
    axis = (torch.minimum(point, 1 - point).abs() < 1e-7).double()
    assert torch.allclose(normal[hit].abs(), axis, atol=1e-9)
    assert ((normal[hit] * direction[hit]).sum(-1) < 0).all()
    assert (normal[~hit] == 0).all()


def test_place_mesh_scales_turns_and_rests_on_the_surface():
    v, _ = _cube()
    v = v * torch.tensor([2.0, 1.0, 0.5], dtype=torch.float64)  # extents 2 x 1 x 0.5
    up = torch.nn.functional.normalize(torch.tensor([0.3, 0.9, -0.2], dtype=torch.float64), dim=0)
    base = torch.tensor([1.0, -0.5, -3.0], dtype=torch.float64)
    placed = place_mesh(v, base, up, size=0.4, turn_deg=90.0, lift=0.002)
    assert math.isclose(float((placed @ up).min()), float(base @ up) + 0.002, abs_tol=1e-12)
    # sizes are preserved by the rigid part: the longest edge of the box is 0.4 m
    edges = torch.cdist(placed, placed)
    assert math.isclose(float(edges[0, 4]), 0.4, rel_tol=1e-9)  # the x edge (vertex 0 to 4), the longest
    # its own bounding box's centre (the mean of the box's 8 corners) straight above the base
    off = placed.mean(0) - base
    assert float((off - (off @ up) * up).norm()) < 1e-9
    R = rotation_to(up)
    torch.testing.assert_close(R @ torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), up)
    torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=torch.float64))
    down = rotation_to(torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(
        down @ torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    )


def test_lathe_is_a_closed_outward_surface_of_the_right_volume():
    import trimesh

    r, h, n = 0.4, 1.5, 24
    v, f = lathe(torch.tensor([[r, 0.0], [r, h / 2], [r, h]], dtype=torch.float64), n)
    mesh = trimesh.Trimesh(v.numpy(), f.numpy(), process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    # a regular n-gon prism: volume n/2 r^2 sin(2 pi / n) h, positive when the faces point outwards
    assert math.isclose(mesh.volume, n / 2 * r**2 * math.sin(2 * math.pi / n) * h, rel_tol=1e-9)
