"""Object insertion and material editing through the one render path (`MCRenderLayer.render_pixels`).

A case changes some pixels of one view: an inserted object brings its own G-buffers (albedo, normal,
z-depth, roughness, metallic) at the pixels where it lies in front of the scene; an edit replaces the
material of a region and keeps its geometry. The changed pixels are re-rendered under an incident
radiance callback and composited into the photo. The callback sees the scene *without* the object:
LightNet traces its secondary rays (SSRT) against the scene's depth, as a new object would see the room
(its own interreflection and the other objects' light on it are not modelled). The shadows and bounce light
objects cast on the room are added by differential rendering (`models.shadows`, `insert_into(shadows=True)`).
Objects are spheres, snowmen or triangle meshes (`InsertedObject`), several in one insertion.

All tensors are of one view: G-buffers depth (1, H, W) metres, normal/albedo (1, 3, H, W), material
(1, 2, H, W); pixels (M,) flat indices into H*W.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.models.light_net.branches import image_scale
from pipeline.models.material_net import predict_maps
from pipeline.models.render_layer import MCRenderLayer, PointRadianceFn
from pipeline.models.shadows import facing_camera, object_radiance, occlusion_light, proxy_pixels, shape_bounds
from pipeline.ops.camera import backproject, pixel_directions
from pipeline.ops.meshes import place_mesh, raycast_mesh
from pipeline.ops.primitives import LIFT_M, object_spheres, raycast_spheres


class InsertionError(ValueError):
    """An insertion or edit that cannot be done as asked (a pixel off the image or on no surface, an
    invisible object); the message names the argument."""


# materials of inserted objects: (albedo, roughness, metallic), the classes the `edit` stage scores
OBJECT_MATERIALS = {
    "mirror": ((0.95, 0.93, 0.88), 0.05, 1.0),
    "glossy": ((0.7, 0.12, 0.1), 0.25, 0.0),
    "diffuse": ((0.7, 0.7, 0.7), 0.9, 0.0),
}


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
    layer,
    shading: dict,
    fov_x: float,
    pixels: torch.Tensor,
    radiance: PointRadianceFn,
    seed: int,
    guide=None,
) -> torch.Tensor:
    """(M, 3) HDR radiance of `pixels` of the G-buffers `shading` under `radiance`, rendered by `layer` (an
    `MCRenderLayer`, or a `ScoringLayer` that may sample `guide`, an `ops.guide.SphereGuide`, beside the
    BRDF). Every unguided call with the same seed and layer draws the same sample directions wherever the
    shading G-buffers agree (paired comparisons)."""
    generator = torch.Generator().manual_seed(int(seed))
    extra = {} if guide is None else {"guide": guide}  # only the scoring layer takes a guide
    rgb, _ = layer.render_pixels(shading, fov_x, pixels, radiance, generator, **extra)
    return rgb


def light_net_radiance(net, ctx: dict, scene: dict, fov_x: float, seed: int) -> PointRadianceFn:
    """LightNet as the render layer's callback, its SSRT and local branch reading the scene G-buffers
    `scene` (not the composited ones) and `ctx` (`LightNet.encode` of the photo and that scene's depth)."""
    generator = torch.Generator().manual_seed(int(seed) + 1)

    def radiance(idx, origin, wi, image):
        return net(ctx, scene, fov_x, origin, wi, image, generator)["radiance"]

    return radiance


Shape = torch.Tensor | tuple[torch.Tensor, torch.Tensor]  # spheres (S, 4), or a mesh (vertices (V, 3), faces (F, 3))


def cast_shape(shape: Shape, origin: torch.Tensor, direction: torch.Tensor):
    """Nearest hits (t (N,), inf on a miss; unit normal (N, 3) facing the ray) of rays with an inserted
    shape: a union of spheres (`ops.primitives.raycast_spheres`) or a triangle mesh (`ops.meshes`), whose
    triangles are tested only by the rays that meet its bounding sphere."""
    if isinstance(shape, torch.Tensor):
        return raycast_spheres(origin, direction, shape)
    vertices, faces = shape
    vertices = vertices.to(origin.dtype)
    centre, radius = shape_bounds(shape)
    bound = torch.cat([centre.to(origin.dtype), torch.tensor([radius * 1.001], dtype=origin.dtype)])[None]
    t_bound, _ = raycast_spheres(origin, direction, bound)
    near = torch.nonzero(torch.isfinite(t_bound)).squeeze(-1)
    t = torch.full_like(t_bound, float("inf"))
    normal = torch.zeros_like(origin)
    if near.numel():
        t_near, n_near = raycast_mesh(origin[near], direction[near], vertices, faces)
        t, normal = t.index_put((near,), t_near), normal.index_put((near,), n_near)
    return t, normal


def object_gbuffer(shapes: list[Shape], scene_depth: torch.Tensor, fov_x: float) -> dict | None:
    """The G-buffer of inserted shapes (`cast_shape`; view space, metres) where they lie in front of the
    scene, each pixel showing the nearest shape: pixel (M,) flat, normal (M, 3), depth (M,) z-depth metres,
    shape (M,) long, the index of the shape seen; None if nothing is visible.
    scene_depth (H, W) metres, 0 or inf where the scene has no surface (an object is visible there)."""
    H, W = scene_depth.shape
    dirs = pixel_directions(H, W, fov_x, dtype=torch.float64).reshape(-1, 3)
    unit = torch.nn.functional.normalize(dirs, dim=-1)
    hits = [cast_shape(shape, torch.zeros_like(unit), unit) for shape in shapes]
    t, which = torch.stack([t for t, _ in hits]).min(0)  # the nearest shape along each ray
    normal = torch.stack([n for _, n in hits])[which, torch.arange(len(unit))]
    z = t * -unit[:, 2]
    scene = scene_depth.reshape(-1).to(z.dtype)
    behind_nothing = (scene <= 0) | ~torch.isfinite(scene)
    visible = torch.isfinite(t) & (behind_nothing | (z < scene))
    pix = torch.nonzero(visible).squeeze(-1)
    if not pix.numel():
        return None
    return {"pixel": pix, "normal": normal[pix], "depth": z[pix], "shape": which[pix]}


def composite_image(photo: torch.Tensor, pixels: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """photo (H, W, 3) with values (M, 3) written at flat pixels (M,)."""
    flat = photo.reshape(-1, 3).clone()
    flat[pixels] = values.to(flat.dtype)
    return flat.reshape(photo.shape)


def _chw(a: np.ndarray) -> torch.Tensor:
    """(H, W, C) array -> (1, C, H, W) float32 tensor."""
    return torch.from_numpy(np.ascontiguousarray(a)).float().permute(2, 0, 1)[None]


def gbuffers_from_maps(maps: dict, mask: np.ndarray | None = None) -> dict:
    """InteriorVerse-convention maps of one view (depth (H, W) or (H, W, 1) z-depth in millimetres, inf
    where invalid; normal, albedo (H, W, 3); material (H, W, >=2) roughness, metallic) -> the render
    layer's G-buffers: depth (1, H, W) metres, 0 where not finite or outside the boolean `mask` (H, W),
    normal/albedo (1, 3, H, W), material (1, 2, H, W)."""
    depth_mm = np.nan_to_num(np.asarray(maps["depth"], np.float64), posinf=0.0)
    depth = torch.from_numpy(depth_mm / 1000.0).float().reshape(maps["normal"].shape[:2])
    if mask is not None:
        depth = torch.where(torch.from_numpy(np.asarray(mask, bool)), depth, torch.zeros_like(depth))
    return {
        "depth": depth[None],
        "normal": _chw(maps["normal"]),
        "albedo": _chw(maps["albedo"]),
        "material": _chw(maps["material"][..., :2]),
    }


def edited_gbuffer(
    gbuffer: dict, pixels: torch.Tensor, albedo=None, roughness: float | None = None, metallic: float | None = None
) -> dict:
    """The G-buffers with a material edit at `pixels` (M,): albedo (3,) linear base colour, roughness and
    metallic where given; the G-buffers' own values for what is None."""
    alb = gbuffer["albedo"][0].reshape(3, -1)[:, pixels].T.clone()
    mat = gbuffer["material"][0].reshape(2, -1)[:, pixels].T.clone()
    if albedo is not None:
        alb[:] = torch.as_tensor(albedo, dtype=alb.dtype)
    if roughness is not None:
        mat[:, 0] = float(roughness)
    if metallic is not None:
        mat[:, 1] = float(metallic)
    return composite_gbuffer(gbuffer, pixels, albedo=alb, material=mat)


@dataclass
class PreparedView:
    """One photo made ready for insertion and editing, by `prepare_view`: photo (H, W, 3) and image
    (1, 3, H, W) the same linear pixels (float32), scale its mean radiance (0-dim, `image_scale`), fov its
    horizontal field of view (degrees), net LightNet (eval mode); pred the MaterialNet G-buffers of the
    photo and ctx_pred LightNet's context of the photo over their depth; with ground-truth maps also gt
    and ctx_gt, the same over the ground truth."""

    photo: torch.Tensor
    image: torch.Tensor
    scale: torch.Tensor
    fov: float
    net: torch.nn.Module
    pred: dict
    ctx_pred: dict
    gt: dict | None = None
    ctx_gt: dict | None = None


def prepare_view(
    im: np.ndarray,
    material_net,
    meta: dict,
    light_net,
    fov: float,
    mask: np.ndarray | None = None,
    gt_maps: dict | None = None,
    mask_prediction: bool = True,
) -> PreparedView:
    """A linear photo (H, W, 3) with its horizontal fov (degrees): MaterialNet's G-buffers of it and
    LightNet's context of them. `mask` (H, W) bool zeroes depth outside the view's valid pixels (as
    `train_lighting` feeds LightNet), in the predicted G-buffers only when `mask_prediction` (False: the
    predicted depth at lamps and windows too, `train_lighting`'s `lighting.ssrt_depth=every_pixel`);
    `gt_maps` (InteriorVerse maps of the view, `gbuffers_from_maps`) adds the ground-truth G-buffers,
    under the mask, and their context."""
    image = _chw(im)
    pred = gbuffers_from_maps(predict_maps(material_net, meta, im), mask if mask_prediction else None)
    gt = gbuffers_from_maps(gt_maps, mask) if gt_maps is not None else None
    net = light_net.eval()
    with torch.no_grad():
        ctx_pred = net.encode(image, pred["depth"], fov, normal=pred["normal"])
        ctx_gt = net.encode(image, gt["depth"], fov, normal=gt["normal"]) if gt is not None else None
    return PreparedView(
        photo=image[0].permute(1, 2, 0),
        image=image,
        scale=image_scale(image)[0],
        fov=float(fov),
        net=net,
        pred=pred,
        ctx_pred=ctx_pred,
        gt=gt,
        ctx_gt=ctx_gt,
    )


@dataclass
class InsertedObject:
    """One object of an insertion. shape: "sphere", "snowman" (`ops.primitives.object_spheres`) or a mesh
    (vertices (V, 3), faces (F, 3) long, its up axis +y: `ops.meshes`); (row, col) the pixel whose predicted
    surface it rests on (up along the predicted normal there); material (albedo (r, g, b) linear, roughness,
    metallic); size: its largest extent in metres (None: 1/8 of the view's width at its depth); turn: degrees
    about its up axis; label: how an error names it."""

    shape: str | tuple[torch.Tensor, torch.Tensor]
    row: int
    col: int
    material: tuple = OBJECT_MATERIALS["mirror"]
    size: float | None = None
    turn: float = 0.0
    label: str = "--at"


def place_object(view: PreparedView, obj: InsertedObject, stand_on: dict | None = None) -> Shape:
    """The object placed in view space (`Shape`), resting on the surface at its pixel: the predicted
    G-buffers' (or `stand_on`'s, depth (1, H, W) metres and normal (1, 3, H, W))."""
    gb, fov = (view.pred if stand_on is None else stand_on), view.fov
    H, W = view.photo.shape[:2]
    at = f"{obj.label} {obj.row},{obj.col}"
    if not (0 <= obj.row < H and 0 <= obj.col < W):
        raise InsertionError(f"{at}: pixel (row {obj.row}, col {obj.col}) is outside the {W}x{H} image")
    point = backproject(gb["depth"], fov)[0, obj.row, obj.col]
    z = float(gb["depth"][0, obj.row, obj.col])
    if not math.isfinite(z) or z <= 0:
        raise InsertionError(f"{at}: no valid surface at that pixel (predicted depth {z})")
    n = torch.nn.functional.normalize(gb["normal"][0, :, obj.row, obj.col], dim=0)
    if float(n @ point) > 0:  # a surface seen from behind (a prediction error): stand on its visible side
        n = -n
    f = (W / 2) / math.tan(math.radians(fov) / 2)
    size = float(obj.size) if obj.size is not None else z * (W / 8) / f
    depth = gb["depth"][0]
    room = float(depth[torch.isfinite(depth) & (depth > 0)].max())  # the farthest surface seen: the room's scale
    if not 0 < size <= room:
        raise InsertionError(f"--scale {obj.size}: must be positive and at most the room's depth ({room:.2f} m)")
    if isinstance(obj.shape, str):
        return object_spheres(obj.shape, point, n, size / 2)  # resting on the surface, up = its normal
    vertices, faces = obj.shape
    return place_mesh(vertices, point.double(), n.double(), size, obj.turn, LIFT_M), faces


def insert_into(
    view: PreparedView,
    objects: list[InsertedObject],
    spp: int,
    seed: int,
    shadows: bool = True,
    stand_on: dict | None = None,
):
    """Objects (`InsertedObject`) inserted into a `prepare_view` together, each pixel showing the nearest,
    rendered at `spp` under LightNet (which sees the room without them): (composited photo (H, W, 3), the
    objects' pixels (M,)). With `shadows`, the room around them also gets their shadows and bounce light
    by differential rendering (`models.shadows`, at the same spp). Objects stand on the predicted surface,
    or on `stand_on`'s (depth and normals of the view from elsewhere, e.g. the ground truth, to compare with
    a reference render), which then also decides what hides them and where the proxy lies; materials and
    light are the predictions'. An object seen nowhere (behind the scene, outside the view, or wholly behind
    another object) is refused, naming it."""
    if not objects:
        raise InsertionError("--object: nothing to insert")
    gb, fov = view.pred, view.fov
    geometry = gb if stand_on is None else {**gb, "depth": stand_on["depth"], "normal": stand_on["normal"]}
    shapes = [place_object(view, obj, geometry) for obj in objects]
    found = object_gbuffer(shapes, geometry["depth"][0], fov)
    for k, obj in enumerate(objects):
        if found is None or not (found["shape"] == k).any():
            where = f"{obj.label} {obj.row},{obj.col}"
            raise InsertionError(
                f"{where}: the object would not be visible (behind the scene or another object, or outside the view)"
            )
    albedo = torch.tensor([obj.material[0] for obj in objects], dtype=torch.float32)
    material = torch.tensor([obj.material[1:] for obj in objects], dtype=torch.float32)
    pixel, seen = found["pixel"], found["shape"]
    shading = composite_gbuffer(
        gb,
        pixel,
        albedo=albedo[seen],
        material=material[seen],
        normal=found["normal"].float(),
        depth=found["depth"].float(),
    )
    light = light_net_radiance(view.net, view.ctx_pred, gb, fov, seed)
    with torch.no_grad():
        rgb = render_case(MCRenderLayer(spp=spp), shading, fov, pixel, light, seed)
    photo = composite_image(view.photo, pixel, rgb)
    if shadows:
        radiance = object_radiance(rgb, seen, len(objects))
        photo = _with_shadows(view, geometry, photo, shapes, radiance, pixel, spp, seed)
    return photo, pixel


def _with_shadows(view, proxy_gb: dict, photo, shapes, radiance, pixel, spp: int, seed: int) -> torch.Tensor:
    """photo (H, W, 3) plus the objects' effect on the room around them (`models.shadows`): the difference
    of the proxy's (G-buffers `proxy_gb`) renders with and without them, the result clamped at 0 (a shadow
    darkens no pixel below black). LightNet reads the predicted G-buffers, as for the objects."""
    fov = view.fov
    proxy = proxy_pixels(proxy_gb["depth"][0], fov, shapes, pixel)
    if not proxy.numel():
        return photo
    light = light_net_radiance(view.net, view.ctx_pred, view.pred, fov, seed + 2)  # its own out-of-view samples
    blocked = occlusion_light(light, shapes, radiance, cast_shape)
    with torch.no_grad():
        delta = render_case(MCRenderLayer(spp=spp), facing_camera(proxy_gb, fov), fov, proxy, blocked, seed + 1)
    flat = photo.reshape(-1, 3).clone()
    flat[proxy] = (flat[proxy] + delta.to(flat.dtype)).clamp(min=0)
    return flat.reshape(photo.shape)
