"""Shadows and bounce light of inserted objects on the room, by differential rendering (Debevec 1998).

An inserted object changes the room around it: it blocks light from the surfaces beneath and beside it
(its shadow) and sends its own light onto them (bounce). The room near the object is taken from the photo's
predicted G-buffers (depth, normals, materials: the local scene proxy) and rendered through the one render
path twice, with the same sample directions: once as the photo shows it, once with the objects in the
room; the photo is corrected by the difference, so what the proxy gets wrong cancels and only the
object's effect is added. Both renders share every sample ray that misses the objects, so the difference
is one render whose incident radiance is zero on those rays and, on a ray that meets an object, the
object's radiance minus the light the ray would have had (`occlusion_light`): the light is queried only
on the rays the objects block.

An object's radiance towards the room is taken as the mean of its rendered pixels (what the camera sees
of it; exact for a diffuse object under uniform light, an estimate otherwise). The objects' own pixels
are rendered by `models.insertion` (their rays see the room without the shadows they cast).

Shapes are those of `models.insertion.cast_shape` (view space, metres): spheres (S, 4) or a mesh
(vertices (V, 3), faces (F, 3)).
"""

from __future__ import annotations

import torch

from pipeline.models.render_layer import PointRadianceFn
from pipeline.ops.camera import backproject

SHADOW_REACH = 3.0  # proxy pixels: room points within this many object radii of an object's centre


def shape_bounds(shape) -> tuple[torch.Tensor, float]:
    """(centre (3,) float64, radius metres) of a sphere bounding a shape (spheres (S, 4) or a mesh)."""
    if isinstance(shape, torch.Tensor):
        spheres = shape.double()
        lo = (spheres[:, :3] - spheres[:, 3:]).min(0).values
        hi = (spheres[:, :3] + spheres[:, 3:]).max(0).values
        centre = (lo + hi) / 2
        return centre, float(((spheres[:, :3] - centre).norm(dim=-1) + spheres[:, 3]).max())
    vertices = shape[0].double()
    centre = (vertices.max(0).values + vertices.min(0).values) / 2
    return centre, float((vertices - centre).norm(dim=-1).max())


def proxy_pixels(
    depth: torch.Tensor, fov_x: float, shapes: list, exclude: torch.Tensor, reach: float = SHADOW_REACH
) -> torch.Tensor:
    """(K,) flat pixels of the room's proxy: pixels with a valid predicted depth (H, W) metres whose
    surface point lies within `reach` bounding radii of some object's centre, minus `exclude` (the
    objects' own pixels)."""
    points = backproject(depth[None], fov_x)[0].reshape(-1, 3).double()
    valid = torch.isfinite(depth.reshape(-1)) & (depth.reshape(-1) > 0)
    near = torch.zeros_like(valid)
    for shape in shapes:
        centre, radius = shape_bounds(shape)
        near |= (points - centre).norm(dim=-1) <= reach * radius
    keep = valid & near
    keep[exclude] = False
    return torch.nonzero(keep).squeeze(-1)


def facing_camera(gbuffer: dict, fov_x: float) -> dict:
    """A copy of G-buffers (depth (1, H, W), normal (1, 3, H, W)) whose normals that face away from the
    camera are flipped: a visible surface faces the camera, and a predicted normal that does not (a
    prediction error) would put the objects standing on it below its horizon, casting no shadow."""
    points = backproject(gbuffer["depth"], fov_x)  # (1, H, W, 3)
    normal = gbuffer["normal"]
    away = (normal.permute(0, 2, 3, 1) * points).sum(-1) > 0  # (1, H, W): n . (p - camera) > 0
    sign = 1.0 - 2.0 * away.to(normal.dtype)
    return {**gbuffer, "normal": normal * sign[:, None]}


def occlusion_light(light: PointRadianceFn, shapes: list, object_radiance: torch.Tensor, cast) -> PointRadianceFn:
    """The render layer's callback of the difference between the room with and without the objects: on a
    ray (origin, wi) that meets an object (`cast(shape, origin, wi)` -> (t (N,), normal)), the nearest
    object's radiance (object_radiance (S, 3), one per shape) minus `light` on that ray; 0 elsewhere.
    `light` is called on the blocked rays only."""

    def radiance(idx, origin, wi, image):
        hits = torch.stack([cast(shape, origin.double(), wi.double())[0] for shape in shapes])  # (S, N)
        t, which = hits.min(0)
        blocked = torch.nonzero(torch.isfinite(t)).squeeze(-1)
        out = torch.zeros(len(wi), 3, dtype=wi.dtype)
        if blocked.numel():
            seen = light(idx[blocked], origin[blocked], wi[blocked], image[blocked])
            out[blocked] = object_radiance[which[blocked]].to(out.dtype) - seen.to(out.dtype)
        return out

    return radiance


def object_radiance(rgb: torch.Tensor, seen: torch.Tensor, count: int) -> torch.Tensor:
    """(count, 3): each object's mean rendered radiance over its pixels; rgb (M, 3) the objects' pixels,
    seen (M,) long the object each shows."""
    out = torch.zeros(count, 3, dtype=rgb.dtype)
    out.index_add_(0, seen, rgb)
    return out / torch.bincount(seen, minlength=count).clamp(min=1).to(rgb.dtype)[:, None]
