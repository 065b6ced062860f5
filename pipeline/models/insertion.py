"""Object insertion and material editing through the one render path (`MCRenderLayer.render_pixels`).

A case changes some pixels of one view: an inserted object brings its own G-buffers (albedo, normal,
z-depth, roughness, metallic) at the pixels where it lies in front of the scene; an edit replaces the
material of a region and keeps its geometry. The changed pixels are re-rendered under an incident
radiance callback and composited into the photo. The callback sees the scene *without* the object:
LightNet traces its secondary rays (SSRT) against the scene's depth, as a new object would see the room
(its own interreflection and the shadows it would cast on the room are not modelled).

All tensors are of one view: G-buffers depth (1, H, W) metres, normal/albedo (1, 3, H, W), material
(1, 2, H, W); pixels (M,) flat indices into H*W.
"""

from __future__ import annotations

import torch

from pipeline.models.render_layer import MCRenderLayer, PointRadianceFn
from pipeline.ops.camera import pixel_directions
from pipeline.ops.primitives import raycast_spheres


def composite_gbuffer(
    gbuffer: dict,
    pixels: torch.Tensor,
    albedo: torch.Tensor | None = None,
    material: torch.Tensor | None = None,
    normal: torch.Tensor | None = None,
    depth: torch.Tensor | None = None,
) -> dict:
    """A copy of one view's G-buffers with the given per-pixel values (M, C) / (M,) written at `pixels`;
    None keeps the scene's."""
    out = {}
    for key, value in (("albedo", albedo), ("material", material), ("normal", normal), ("depth", depth)):
        g = gbuffer[key]
        if value is None:
            out[key] = g
            continue
        if g.dim() == 3:  # depth (1, H, W)
            flat = g.reshape(-1).clone()
            flat[pixels] = value.to(g.dtype).reshape(-1)
            out[key] = flat.reshape(g.shape)
        else:
            C = g.shape[1]
            flat = g[0].reshape(C, -1).clone()
            flat[:, pixels] = value.to(g.dtype).T
            out[key] = flat.reshape(g.shape)
    return out


def render_case(
    layer: MCRenderLayer,
    shading: dict,
    fov_x: float,
    pixels: torch.Tensor,
    radiance: PointRadianceFn,
    seed: int,
) -> torch.Tensor:
    """(M, 3) HDR radiance of `pixels` of the G-buffers `shading` under `radiance`. Every call with the same
    seed draws the same sample directions wherever the shading G-buffers agree (paired comparisons)."""
    generator = torch.Generator().manual_seed(int(seed))
    rgb, _ = layer.render_pixels(shading, fov_x, pixels, radiance, generator)
    return rgb


def light_net_radiance(net, ctx: dict, scene: dict, fov_x: float, seed: int) -> PointRadianceFn:
    """LightNet as the render layer's callback, its SSRT and local branch reading the scene G-buffers
    `scene` (not the composited ones) and `ctx` (`LightNet.encode` of the photo and that scene's depth)."""
    generator = torch.Generator().manual_seed(int(seed) + 1)

    def radiance(idx, origin, wi, image):
        return net(ctx, scene, fov_x, origin, wi, image, generator)["radiance"]

    return radiance


def object_gbuffer(spheres: torch.Tensor, scene_depth: torch.Tensor, fov_x: float) -> dict | None:
    """The G-buffer of an inserted union of spheres (S, 4) (view space, metres) where it lies in front of
    the scene: pixel (M,) flat, normal (M, 3), depth (M,) z-depth metres; None if nothing is visible.
    scene_depth (H, W) metres, 0 or inf where the scene has no surface (the object is visible there)."""
    H, W = scene_depth.shape
    dirs = pixel_directions(H, W, fov_x, dtype=spheres.dtype).reshape(-1, 3)
    unit = torch.nn.functional.normalize(dirs, dim=-1)
    t, normal = raycast_spheres(torch.zeros_like(unit), unit, spheres)
    z = t * -unit[:, 2]
    scene = scene_depth.reshape(-1).to(z.dtype)
    behind_nothing = (scene <= 0) | ~torch.isfinite(scene)
    visible = torch.isfinite(t) & (behind_nothing | (z < scene))
    pix = torch.nonzero(visible).squeeze(-1)
    if not pix.numel():
        return None
    return {"pixel": pix, "normal": normal[pix], "depth": z[pix]}


def composite_image(photo: torch.Tensor, pixels: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """photo (H, W, 3) with values (M, 3) written at flat pixels (M,)."""
    flat = photo.reshape(-1, 3).clone()
    flat[pixels] = values.to(flat.dtype)
    return flat.reshape(photo.shape)
