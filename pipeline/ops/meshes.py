"""Triangle meshes as inserted objects: placing one on a surface, and casting rays against it.

A mesh is vertices (V, 3) and faces (F, 3) long (counter-clockwise seen from outside). Its file's up axis
is +y (the convention of OBJ, PLY and glTF exporters); placing it maps that axis to the surface normal.
"""

from __future__ import annotations

import math

import torch

RAY_CHUNK = 4096  # rays per block of the ray-triangle test (rays x faces pairs are held at once)


def rotation_to(up: torch.Tensor) -> torch.Tensor:
    """(3, 3) rotation taking +y to the unit vector `up` (3,), the shortest one (about +y x up)."""
    y = up.new_tensor([0.0, 1.0, 0.0])
    v = torch.linalg.cross(y, up)
    c = float(y @ up)
    if c < -1 + 1e-9:  # upside down: half a turn about x
        return torch.diag(up.new_tensor([1.0, -1.0, -1.0]))
    k = up.new_tensor([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return torch.eye(3, dtype=up.dtype) + k + k @ k / (1 + c)


def place_mesh(
    vertices: torch.Tensor, base: torch.Tensor, up: torch.Tensor, size: float, turn_deg: float = 0.0, lift: float = 0.0
) -> torch.Tensor:
    """Vertices (V, 3) of a mesh scaled so that its largest extent is `size` metres, turned by `turn_deg`
    degrees about its own up axis (+y), its up mapped to the unit `up`, and moved so that its lowest point
    along `up` rests `lift` metres above the point `base` (3,), centred over it (its bounding box's centre
    across `up`)."""
    v = vertices.double()
    lo, hi = v.min(0).values, v.max(0).values
    extent = float((hi - lo).max())
    if not extent > 0:
        raise ValueError("the mesh has no extent (every vertex at one point)")
    v = (v - (lo + hi) / 2) * (size / extent)
    a = math.radians(turn_deg)
    turn = v.new_tensor([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])
    v = v @ turn.T @ rotation_to(up.double()).T
    height = v @ up.double()
    return v - up.double() * float(height.min()) + base.double() + up.double() * lift


def raycast_mesh(origin: torch.Tensor, direction: torch.Tensor, vertices: torch.Tensor, faces: torch.Tensor):
    """Nearest hit of rays with a triangle mesh (Moller and Trumbore's test: the ray against each
    triangle's plane, in the triangle's barycentric coordinates).

    origin, direction (N, 3) (direction unit); vertices (V, 3) metres, same space; faces (F, 3) long.
    Returns t (N,) the ray length to the nearest hit (inf on a miss) and normal (N, 3) the unit geometric
    normal of the triangle hit, turned to face the ray (0 on a miss). Both sides of a triangle are hit."""
    tri = vertices[faces].to(origin.dtype)  # (F, 3, 3)
    p0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    face_normal = torch.nn.functional.normalize(torch.linalg.cross(e1, e2), dim=-1)
    t_out = torch.full((len(origin),), float("inf"), dtype=origin.dtype, device=origin.device)
    which = torch.zeros(len(origin), dtype=torch.long, device=origin.device)
    eps = 1e-12
    for s in range(0, len(origin), RAY_CHUNK):
        o, d = origin[s : s + RAY_CHUNK, None, :], direction[s : s + RAY_CHUNK, None, :]  # (n, 1, 3)
        p = torch.linalg.cross(d.expand(-1, len(tri), -1), e2[None].expand(len(o), -1, -1))  # (n, F, 3)
        det = (e1[None] * p).sum(-1)
        inv = 1.0 / torch.where(det.abs() > eps, det, torch.ones_like(det))
        q0 = o - p0[None]
        u = (q0 * p).sum(-1) * inv
        q = torch.linalg.cross(q0, e1[None].expand(len(o), -1, -1))
        w = (d * q).sum(-1) * inv
        t = (e2[None] * q).sum(-1) * inv
        hit = (det.abs() > eps) & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 1e-9)
        t = torch.where(hit, t, torch.full_like(t, float("inf")))
        t_min, idx = t.min(-1)
        t_out[s : s + RAY_CHUNK], which[s : s + RAY_CHUNK] = t_min, idx
    normal = face_normal[which]
    normal = torch.where(((normal * direction).sum(-1) > 0)[:, None], -normal, normal)
    normal = torch.where(torch.isfinite(t_out)[:, None], normal, torch.zeros_like(normal))
    return t_out, normal


def lathe(profile: torch.Tensor, segments: int = 32) -> tuple[torch.Tensor, torch.Tensor]:
    """A closed surface of revolution about +y: profile (K, 2) rows (radius > 0, height) from bottom to top,
    turned through `segments` steps, capped at both ends. Returns vertices (K * segments + 2, 3) and
    faces (2 * segments * K, 3) long, counter-clockwise seen from outside (a manifold, watertight mesh)."""
    K = len(profile)
    a = torch.arange(segments, dtype=profile.dtype) * (2 * math.pi / segments)
    r, h = profile[:, 0:1], profile[:, 1:2]
    ring = torch.stack([r * torch.cos(a), h.expand(-1, segments), -r * torch.sin(a)], -1)  # (K, segments, 3)
    bottom, top = profile.new_tensor([[0.0, float(h[0]), 0.0]]), profile.new_tensor([[0.0, float(h[-1]), 0.0]])
    vertices = torch.cat([ring.reshape(-1, 3), bottom, top])
    idx = torch.arange(K * segments).reshape(K, segments)
    nxt = torch.roll(idx, -1, dims=1)
    a0, a1, b0, b1 = idx[:-1], nxt[:-1], idx[1:], nxt[1:]
    side = torch.cat([torch.stack([a0, a1, b1], -1).reshape(-1, 3), torch.stack([a0, b1, b0], -1).reshape(-1, 3)])
    cb, ct = K * segments, K * segments + 1
    caps_bottom = torch.stack([torch.full((segments,), cb), nxt[0], idx[0]], -1)
    caps_top = torch.stack([torch.full((segments,), ct), idx[-1], nxt[-1]], -1)
    return vertices, torch.cat([side, caps_bottom, caps_top])


VASE_PROFILE = ((0.30, 0.0), (0.45, 0.2), (0.50, 0.45), (0.35, 0.75), (0.20, 0.9), (0.25, 1.0))  # radius, height


def vase(segments: int = 32) -> tuple[torch.Tensor, torch.Tensor]:
    """The project's own mesh object: a vase (`lathe` of `VASE_PROFILE`, one unit tall and wide, its
    base at the origin, up +y), concave at its neck. Returns float64 vertices (V, 3) and long faces (F, 3)."""
    return lathe(torch.tensor(VASE_PROFILE, dtype=torch.float64), segments)
