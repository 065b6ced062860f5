"""Analytic ray casting against unions of spheres (inserted objects: a sphere, a snowman)."""

from __future__ import annotations

import torch


def raycast_spheres(origin: torch.Tensor, direction: torch.Tensor, spheres: torch.Tensor):
    """Nearest hit of rays with a union of spheres.

    origin, direction (N, 3) (direction unit); spheres (S, 4) rows (centre x, y, z, radius), same space
    and units (metres). Returns t (N,) the ray length to the nearest front-facing hit (inf on a miss) and
    normal (N, 3) the outward unit normal there (0 on a miss). Rays starting inside a sphere do not hit it."""
    oc = origin[:, None, :] - spheres[None, :, :3]  # (N, S, 3)
    b = (oc * direction[:, None, :]).sum(-1)
    c = (oc * oc).sum(-1) - spheres[None, :, 3] ** 2
    disc = b * b - c
    t = -b - torch.sqrt(disc.clamp(min=0))
    valid = (disc >= 0) & (c > 0) & (t > 0)
    t = torch.where(valid, t, torch.full_like(t, float("inf")))
    t_min, which = t.min(-1)
    hit_point = origin + t_min.nan_to_num(posinf=0.0)[:, None] * direction
    normal = (hit_point - spheres[which, :3]) / spheres[which, 3:4]
    normal = torch.where(torch.isfinite(t_min)[:, None], normal, torch.zeros_like(normal))
    return t_min, normal


OBJECT_KINDS = ("sphere", "snowman")
LIFT_M = 2e-3  # a resting object floats this far above its support, so it never touches it numerically


def object_spheres(kind: str, base: torch.Tensor, axis: torch.Tensor, radius: float, resting: bool = True):
    """(S, 4) spheres (centre, radius) of an inserted object of size `radius` (metres) along the unit
    `axis` (its up): resting on the point `base` (lifted by LIFT_M), or centred on it when not resting.
    A `sphere` is one sphere of that radius; a `snowman` a lower sphere of 0.6 r and an upper one of
    0.42 r overlapping it (their centres 0.6 r + 0.55 * 0.42 r apart), a non-convex shape with a neck."""
    base, axis = base.double(), axis.double()
    if kind == "sphere":
        centre = base + axis * (radius + LIFT_M) if resting else base
        return torch.cat([centre, centre.new_tensor([radius])])[None]
    if kind != "snowman":
        raise ValueError(f"object kind {kind!r}: choose one of {OBJECT_KINDS}")
    r1, r2 = 0.6 * radius, 0.42 * radius
    gap = r1 + 0.55 * r2
    bottom = base + axis * LIFT_M if resting else base - axis * (r1 + gap + r2) / 2
    c1 = bottom + axis * r1
    c2 = c1 + axis * gap
    return torch.stack([torch.cat([c1, c1.new_tensor([r1])]), torch.cat([c2, c2.new_tensor([r2])])])
