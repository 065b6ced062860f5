"""Object-insertion and material-editing cases with Mitsuba ground truth, for val and test views.

Insertion: a new object (a sphere, a `snowman` of two overlapping spheres, or a `vase`, the project's
triangle mesh `ops.meshes.vase`; the last two non-convex) of one material class, either resting on a
visible horizontal surface (floor, table or cabinet top) or floating at a free point in view, clear of
the room. Editing: one visible material (a furniture piece or the floor) given another material (polished
metal, or a new base colour).

Each case is rendered by Mitsuba's `path` integrator (the view's own integrator and depth) in the room
with the change applied, at the pixel centres the case covers: one camera ray per pixel centre, `spp`
samples, not denoised, so the ground truth lines up with the G-buffers (exact at pixel centres, as the
view's own maps) and carries its standard error instead of a denoiser's bias. An object covers a few
hundred pixels, so a high sample count costs little.

Around each object, the room's pixels whose surface lies within `ring_reach` bounding radii of it (its
surroundings, where its shadow and bounce light fall) carry the change the object makes there: Mitsuba's
render with the object minus without it, both from the same random streams (`mb.radiance_difference`),
so that only the paths the object changes differ.

Descriptions are plain JSON (`<view>_cases.json`); arrays go to `<view>_cases.npz` keyed
`object<k>_*` / `edit<k>_*` (see docs/data.md and `pipeline.data.cases`, the reader).
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from pipeline.data.synth import mitsuba_backend as mb
from pipeline.data.synth.materials import Material, hsv_colour, metal_colour
from pipeline.data.synth.scene import Camera, Room, Shape, sphere_matrix
from pipeline.ops.meshes import place_mesh, vase
from pipeline.ops.primitives import LIFT_M, object_spheres

# material classes of inserted objects: (roughness, metallic); albedo is drawn per object
OBJECT_CLASSES = {"mirror": (0.05, 1.0), "glossy": (0.25, 0.0), "diffuse": (0.9, 0.0)}
EDIT_KINDS = ("metal", "albedo")
CASE_OBJECTS = ("sphere", "vase", "snowman")  # the k-th object of a view is of the k-th kind
MESHES = {"vase": vase}  # object kinds that are triangle meshes: their (vertices, faces) in unit size
RESTING_CHECK_BELOW = -0.75  # a resting mesh's room is checked along directions with y above this


@dataclass
class CaseConfig:
    """Cases per val/test view (the `synth.cases` group)."""

    enabled: bool = True
    objects: tuple[int, int] = (2, 3)  # objects per view, each its own case
    edits: tuple[int, int] = (1, 2)  # material edits per view
    spp: int = 512  # path samples per ground-truth pixel of an object (a few hundred pixels: cheap)
    edit_spp: int = 128  # per pixel of an edited region (up to `edit_fraction` of the view)
    ring_spp: int = 64  # per pixel of an object's surroundings (the change it makes there: paired renders)
    ring_reach: float = 3.0  # surroundings: room points within this many bounding radii of the object
    radius_px: tuple[float, float] = (7.0, 12.0)  # projected radius of an object, pixels (at 160 px wide)
    min_pixels: int = 30  # an object case needs this many visible pixels
    edit_fraction: tuple[float, float] = (0.01, 0.2)  # an edit covers this share of the view
    floating_probability: float = 0.35
    attempts: int = 60  # placements tried per object and round (3 rounds) before giving up on it


@dataclass
class InsertedObject:
    """spheres: [[x, y, z, radius], ...] world metres (one for a sphere, two for a snowman; a mesh's
    bounding sphere). mesh: a mesh object's triangles, {"vertices": (V, 3) world metres, "faces": (F, 3)
    vertex indices}, None for the spheres."""

    kind: str
    spheres: list[list[float]]
    material_class: str
    albedo: list[float]
    roughness: float
    metallic: float
    support: str  # resting | floating
    anchor_pixel: list[int]  # (row, col) the placement started from
    mesh: dict | None = None

    def material(self) -> Material:
        return Material("inserted", list(self.albedo), float(self.roughness), float(self.metallic))


@dataclass
class MaterialEdit:
    """The room's material `material_index` (used by `target` shapes) with the fields that are not None
    replaced."""

    kind: str  # metal | albedo
    target: str  # furniture | floor | wall (walls only where a view has no other candidate)
    material_index: int
    albedo: list[float] | None = None
    roughness: float | None = None
    metallic: float | None = None


@dataclass
class ViewCases:
    objects: list[InsertedObject] = field(default_factory=list)
    edits: list[MaterialEdit] = field(default_factory=list)
    spp: int = 0
    edit_spp: int = 0

    def to_json(self) -> dict:
        return {"version": 3, **asdict(self)}


# ----------------------------------------------------------------------------------------------------
# Scenes with a case applied (also used by the oracle of the `edit` stage)


def room_with_object(room: Room, obj: InsertedObject) -> Room:
    """A copy of `room` with the object's spheres, or its mesh, added (one shared material)."""
    out = copy.deepcopy(room)
    out.materials.append(obj.material())
    m = len(out.materials) - 1
    if obj.mesh is not None:
        out.shapes.append(Shape("mesh", np.eye(4).tolist(), m, "inserted", mesh=obj.mesh))
        return out
    for x, y, z, r in obj.spheres:
        out.shapes.append(Shape("sphere", sphere_matrix([x, y, z], r), m, "inserted"))
    return out


def edited_material(original: Material, edit: MaterialEdit) -> Material:
    """The original material with the edit's fields replaced. A new base colour replaces both colours of
    a texture (its pattern may still vary the roughness)."""
    m = copy.deepcopy(original)
    if edit.albedo is not None:
        m.albedo = list(edit.albedo)
        if m.texture is not None:
            m.texture["albedo2"] = list(edit.albedo)
    if edit.roughness is not None:
        m.roughness = float(edit.roughness)
        if m.texture is not None:
            m.texture["roughness2"] = None
    if edit.metallic is not None:
        m.metallic = float(edit.metallic)
    return m


def room_with_edit(room: Room, edit: MaterialEdit) -> Room:
    out = copy.deepcopy(room)
    out.materials[edit.material_index] = edited_material(room.materials[edit.material_index], edit)
    return out


def _object_only_room(room: Room, obj: InsertedObject) -> Room:
    empty = Room(seed=room.seed, size=room.size, materials=[], shapes=[], windows=[], sky=None)
    return room_with_object(empty, obj)


# ----------------------------------------------------------------------------------------------------
# Geometry checks


def fibonacci_directions(n: int) -> np.ndarray:
    """(n, 3) unit directions spread evenly over the sphere."""
    k = np.arange(n) + 0.5
    y = 1 - 2 * k / n
    r = np.sqrt(1 - y * y)
    phi = k * math.pi * (3 - math.sqrt(5))
    return np.stack([r * np.cos(phi), y, r * np.sin(phi)], -1)


CLEARANCE_DIRECTIONS = fibonacci_directions(256)


def clearance(scene, centre: np.ndarray, min_y: float = -1.0) -> float:
    """Distance (m) from `centre` to the nearest surface along the 256 even directions whose y is at least
    `min_y` (all by default; inf if none is hit)."""
    d = CLEARANCE_DIRECTIONS[CLEARANCE_DIRECTIONS[:, 1] >= min_y]
    hit = mb.intersect(scene, np.broadcast_to(centre, d.shape).copy(), d)
    return float(np.min(hit["t"]))


def _supported(scene, base: np.ndarray, radius: float) -> bool:
    """The surface under a resting sphere at `base` (its contact point) is flat and present where the
    object's footprint lies: rays straight down from points around it land at the contact height."""
    offsets = np.array([[1, 0, 0], [-1, 0, 0], [0, 0, 1], [0, 0, -1], [0, 0, 0]]) * 0.7 * radius
    o = base + offsets + np.array([0, 0.05, 0])
    hit = mb.intersect(scene, o, np.broadcast_to([0.0, -1.0, 0.0], o.shape).copy())
    return bool(np.all(np.abs(hit["t"] - 0.05) < 0.01))


def _geometry_for(kind: str, point: np.ndarray, radius: float, resting: bool) -> tuple[list[list[float]], dict | None]:
    """World-space geometry of an object of size `radius` (metres; a mesh's largest extent is 2 radius)
    standing on (resting) or centred on `point`, up = +y: its sphere list and, for a mesh kind, its
    triangles (the spheres then its bounding sphere)."""
    up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    point_t = torch.from_numpy(np.asarray(point, np.float64))
    if kind not in MESHES:
        return object_spheres(kind, point_t, up, radius, resting).tolist(), None
    vertices, faces = MESHES[kind]()
    size = 2.0 * radius
    extent = vertices.max(0).values - vertices.min(0).values
    height = float(extent[1] / extent.max()) * size  # along up, once scaled to its largest extent
    base = point_t if resting else point_t - up * height / 2
    placed = place_mesh(vertices, base, up, size, lift=LIFT_M if resting else 0.0).numpy()
    centre = (placed.min(0) + placed.max(0)) / 2
    bound = float(np.linalg.norm(placed - centre, axis=1).max())
    mesh = {"vertices": placed.tolist(), "faces": faces.numpy().tolist()}
    return [[*centre.tolist(), bound]], mesh


def _bounding(spheres: list[list[float]]) -> tuple[np.ndarray, float]:
    s = np.asarray(spheres)
    centre = s[:, :3].mean(0)
    return centre, float(np.max(np.linalg.norm(s[:, :3] - centre, axis=1) + s[:, 3]))


# ----------------------------------------------------------------------------------------------------
# Case generation


def _object_gbuffer(obj_scene, camera: Camera, t_scene: np.ndarray, width: int, height: int) -> dict | None:
    """Pixels where the object lies in front of the room: flat pixel (M,), albedo (M, 3), normal (M, 3)
    view space, depth_m (M,) z-depth, material (M, 2); None if nothing is visible."""
    w2v = mb.world_from_view(camera)
    dirs_view = mb.view_rays(camera.fov_x_deg, width, height)
    dirs = dirs_view @ w2v[:3, :3].T
    hit = mb.intersect(obj_scene, np.broadcast_to(w2v[:3, 3], dirs.shape).copy(), dirs)
    visible = hit["hit"] & (hit["t"] < t_scene.reshape(-1) - 1e-4)
    pix = np.flatnonzero(visible)
    if not len(pix):
        return None
    return {
        "pixel": pix.astype(np.int32),
        "albedo": hit["albedo"][pix].astype(np.float32),
        "normal": (hit["normal"][pix] @ w2v[:3, :3]).astype(np.float32),
        "depth_m": (hit["t"][pix] * -dirs_view[pix, 2]).astype(np.float32),
        "material": np.stack([hit["roughness"][pix], hit["metallic"][pix]], -1).astype(np.float32),
        "occluded_fraction": 1.0 - len(pix) / max(int(hit["hit"].sum()), 1),
    }


def surrounding_pixels(
    camera: Camera, t_scene: np.ndarray, mask: np.ndarray, spheres: list[list[float]], reach: float, exclude
) -> np.ndarray:
    """(K,) flat pixels of the room around an object: valid pixels (mask (H, W) > 0, finite ray length
    t_scene (H, W) metres) whose surface point lies within `reach` bounding radii of the object's bounding
    centre, minus `exclude` (the object's own pixels)."""
    height, width = mask.shape
    origins, dirs = _camera_rays(camera, width, height, np.arange(height * width))
    t = t_scene.reshape(-1)
    centre, bound = _bounding(spheres)
    valid = (mask.reshape(-1) > 0) & np.isfinite(t)
    points = origins + dirs * np.where(valid, t, 0.0)[:, None]
    near = valid & (np.linalg.norm(points - centre, axis=1) <= reach * bound)
    near[np.asarray(exclude, np.int64)] = False
    return np.flatnonzero(near).astype(np.int32)


def _camera_rays(camera: Camera, width: int, height: int, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-space origins and directions (M, 3) of the camera rays through flat pixel centres."""
    w2v = mb.world_from_view(camera)
    dirs = mb.view_rays(camera.fov_x_deg, width, height)[pixels] @ w2v[:3, :3].T
    return np.broadcast_to(w2v[:3, 3], dirs.shape).copy(), dirs


def _place_object(scene, camera, gb, kind, cls, rng, cfg: CaseConfig) -> InsertedObject | None:
    height, width = gb["mask"].shape
    w2v = mb.world_from_view(camera)
    rot, origin = w2v[:3, :3], w2v[:3, 3]
    f = float(mb.intrinsics(camera.fov_x_deg, width, height)["fx"])
    dirs_view = mb.view_rays(camera.fov_x_deg, width, height)
    normal_world = gb["normal"].reshape(-1, 3).astype(np.float64) @ rot.T
    t = gb["t"].reshape(-1)
    z = gb["depth"].reshape(-1) / 1000.0
    rows, cols = np.divmod(np.arange(height * width), width)
    inner = (rows > 0.1 * height) & (rows < 0.9 * height) & (cols > 0.1 * width) & (cols < 0.9 * width)
    valid = (gb["mask"].reshape(-1) > 0) & np.isfinite(t) & inner
    resting_px = np.flatnonzero(valid & (normal_world[:, 1] > 0.97))
    floating_px = np.flatnonzero(valid & (t > 1.5))
    px_scale = width / 160.0  # radius_px is given for 160-pixel-wide views
    if not len(resting_px) and not len(floating_px):
        return None
    for _ in range(cfg.attempts):
        floating = rng.uniform() < cfg.floating_probability
        if not len(floating_px if floating else resting_px):  # the other placement where one has no pixel
            floating = not floating
        pool = floating_px if floating else resting_px
        p = int(pool[rng.integers(len(pool))])
        frac = float(rng.uniform(0.35, 0.65)) if floating else 1.0
        radius = float(np.clip(rng.uniform(*cfg.radius_px) * px_scale * z[p] * frac / f, 0.05, 0.35))
        point = origin + (dirs_view[p] @ rot.T) * t[p] * frac
        spheres, mesh = _geometry_for(kind, point, radius, resting=not floating)
        centre, bound = _bounding(spheres)
        if np.linalg.norm(centre - origin) < bound + 0.3:
            continue
        if floating:
            if clearance(scene, centre) < bound + 0.05:
                continue
        else:
            if mesh is not None:  # its bounding sphere reaches below its support: the room above and around
                clear = clearance(scene, centre, RESTING_CHECK_BELOW) >= bound + LIFT_M / 2
            else:
                clear = all(clearance(scene, np.asarray(s[:3])) >= s[3] + LIFT_M / 2 for s in spheres)
            if not clear or not _supported(scene, point, spheres[0][3]):
                continue
        if cls == "mirror":
            albedo = metal_colour(rng)
        else:
            albedo = hsv_colour(rng, (0.0, 1.0), (0.2, 0.8), (0.25, 0.8))
        rough, metal = OBJECT_CLASSES[cls]
        return InsertedObject(
            kind,
            spheres,
            cls,
            albedo,
            rough,
            metal,
            "floating" if floating else "resting",
            [int(rows[p]), int(cols[p])],
            mesh,
        )
    return None


def _edit_candidates(room: Room, camera: Camera, gb: dict, cfg: CaseConfig) -> dict[int, np.ndarray]:
    """{material index: flat pixels (M,)} of every furniture or floor material covering an acceptable share
    of the view. One intersection pass with each candidate material given a unique sentinel colour."""
    height, width = gb["mask"].shape
    roles = {s.material: s.role for s in room.shapes if s.role in ("furniture", "floor", "wall")}
    probe = copy.deepcopy(room)
    code = {}
    for k, m in enumerate(sorted(roles)):
        sentinel = [0.01 * (k + 1), 0.5, 0.123]
        probe.materials[m] = Material("probe", sentinel, 0.777, 0.0)
        code[m] = sentinel[0]
    scene = mb.load_scene(probe)
    origins, dirs = _camera_rays(camera, width, height, np.arange(height * width))
    hit = mb.intersect(scene, origins, dirs)
    valid = (gb["mask"].reshape(-1) > 0) & hit["hit"]
    is_probe = valid & (np.abs(hit["roughness"] - 0.777) < 1e-4) & (np.abs(hit["albedo"][:, 2] - 0.123) < 1e-4)
    shares = {}
    for m, c in code.items():
        pix = np.flatnonzero(is_probe & (np.abs(hit["albedo"][:, 0] - c) < 1e-4))
        shares[m] = (len(pix) / (height * width), pix)
    lo, hi = cfg.edit_fraction
    # furniture and floor within the share range; the walls (one material for all of them) and shares
    # outside it only when a view has nothing else, so that every view gets its edits
    for allowed, a, b in ((("furniture", "floor"), lo, hi), (("furniture", "floor", "wall"), 0.003, 0.6)):
        out = {m: pix for m, (share, pix) in shares.items() if roles[m] in allowed and a <= share <= b}
        if out:
            return out
    return {}


def _draw_edit(room: Room, m: int, kind: str, rng) -> MaterialEdit:
    target = next(s.role for s in room.shapes if s.material == m)
    if kind == "metal":
        return MaterialEdit(kind, target, m, albedo=metal_colour(rng), roughness=0.1, metallic=1.0)
    return MaterialEdit(kind, target, m, albedo=hsv_colour(rng, (0.0, 1.0), (0.4, 0.9), (0.2, 0.8)))


def generate_cases(
    room: Room, scene, camera: Camera, gb: dict, cfg: CaseConfig, rng: np.random.Generator, seed: int, max_depth: int
) -> tuple[ViewCases, dict[str, np.ndarray]]:
    """Draw and render the insertion and editing cases of one view. gb: the view's `views.gbuffer`.
    Returns the description and the arrays of `<view>_cases.npz`."""
    height, width = gb["mask"].shape
    cases, arrays = ViewCases(spp=int(cfg.spp), edit_spp=int(cfg.edit_spp)), {}
    n_obj = int(rng.integers(cfg.objects[0], cfg.objects[1] + 1))
    kinds = [CASE_OBJECTS[k % len(CASE_OBJECTS)] for k in range(n_obj)]
    classes = [list(OBJECT_CLASSES)[i] for i in rng.permutation(len(OBJECT_CLASSES))]
    for k, kind in enumerate(kinds[:n_obj]):
        for _round in range(3):  # a placement can be rejected as too hidden: draw another
            obj = _place_object(scene, camera, gb, kind, classes[k % len(classes)], rng, cfg)
            if obj is None:
                break
            g = _object_gbuffer(mb.load_scene(_object_only_room(room, obj)), camera, gb["t"], width, height)
            if g is not None and len(g["pixel"]) >= cfg.min_pixels and g.pop("occluded_fraction") <= 0.5:
                break
            obj = None
        if obj is None:
            continue
        full = mb.load_scene(room_with_object(room, obj), max_depth)
        o, d = _camera_rays(camera, width, height, g["pixel"])
        L, se = mb.radiance(full, o, d, cfg.spp, seed=seed * 16 + len(cases.objects))
        i = len(cases.objects)
        cases.objects.append(obj)
        arrays.update({f"object{i}_{key}": v for key, v in g.items()})
        arrays[f"object{i}_radiance"] = L.astype(np.float32)
        arrays[f"object{i}_stderr"] = se.astype(np.float32)
        ring = surrounding_pixels(camera, gb["t"], gb["mask"], obj.spheres, cfg.ring_reach, g["pixel"])
        o, d = _camera_rays(camera, width, height, ring)
        delta, delta_se = mb.radiance_difference(full, scene, o, d, cfg.ring_spp, seed=seed * 16 + 12 + i)
        arrays[f"object{i}_ring_pixel"] = ring
        arrays[f"object{i}_ring_delta"] = delta.astype(np.float32)
        arrays[f"object{i}_ring_stderr"] = delta_se.astype(np.float32)
    candidates = _edit_candidates(room, camera, gb, cfg)
    order = sorted(candidates)
    n_edit = min(int(rng.integers(cfg.edits[0], cfg.edits[1] + 1)), len(order))
    picks = [order[i] for i in rng.permutation(len(order))[:n_edit]]
    for j, m in enumerate(picks):
        edit = _draw_edit(room, m, EDIT_KINDS[j % len(EDIT_KINDS)], rng)
        scene_edit = mb.load_scene(room_with_edit(room, edit), max_depth)
        pix = candidates[m]
        o, d = _camera_rays(camera, width, height, pix)
        hit = mb.intersect(scene_edit, o, d)
        L, se = mb.radiance(scene_edit, o, d, cfg.edit_spp, seed=seed * 16 + 8 + j)
        cases.edits.append(edit)
        arrays[f"edit{j}_pixel"] = pix.astype(np.int32)
        arrays[f"edit{j}_albedo"] = hit["albedo"].astype(np.float32)
        arrays[f"edit{j}_material"] = np.stack([hit["roughness"], hit["metallic"]], -1).astype(np.float32)
        arrays[f"edit{j}_radiance"] = L.astype(np.float32)
        arrays[f"edit{j}_stderr"] = se.astype(np.float32)
    arrays["size"] = np.array([height, width], np.int32)
    return cases, arrays
