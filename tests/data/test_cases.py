"""Insertion and editing cases written by `synthesize`: present for val/test views, checked on read,
physically placed (clear of the room, resting on a support), and their G-buffers are the objects'."""

import json
import shutil

import numpy as np
import pytest
import torch

from pipeline.data import cases as case_io
from pipeline.data import interiorverse as iv
from pipeline.data.interiorverse import DatasetError
from pipeline.data.synth import cases as synth_cases
from pipeline.data.synth import mitsuba_backend as mb
from pipeline.data.synth.cases import CaseConfig
from pipeline.data.synth.scene import Room

pytestmark = pytest.mark.slow


def _views(root, splits=("val", "test")):
    return [(s, v) for sp in splits for s in iv.read_split(root, sp) for v in iv.list_views(root, s)]


def _read(root, scene, view):
    maps = iv.read_view(root, scene, view).maps
    H, W = maps["im"].shape[:2]
    return maps, case_io.read_cases(root, scene, view, H, W)


def test_val_and_test_views_have_cases_and_train_views_none(micro_root):
    assert all(case_io.has_cases(micro_root, s, v) for s, v in _views(micro_root))
    assert not any(case_io.has_cases(micro_root, s, v) for s, v in _views(micro_root, ("train",)))
    kinds = {c.kind for s, v in _views(micro_root) for c in _read(micro_root, s, v)[1]}
    assert kinds == {"object", "edit"}
    for s, v in _views(micro_root):
        desc = json.loads(case_io.paths(micro_root, s, v)[0].read_text())
        kinds = [obj["kind"] for obj in desc["objects"]]
        assert kinds == list(synth_cases.CASE_OBJECTS[: len(kinds)])  # a sphere and a mesh in every view
        for obj in desc["objects"]:
            assert obj["material_class"] in ("mirror", "glossy", "diffuse")
            assert len(obj["spheres"]) == (2 if obj["kind"] == "snowman" else 1)
            assert (obj["mesh"] is not None) == (obj["kind"] in synth_cases.MESHES)


def _distance_to_shape(p: np.ndarray, shape) -> float:
    """Exact distance (m) from a point to a room primitive of `scene.json` (negative inside a sphere, 0 inside
    a box): the generator's ray-based clearance checked against the geometry itself."""
    m = np.asarray(shape.to_world)
    a, c = m[:3, :3], m[:3, 3]
    if shape.kind == "sphere":
        return float(np.linalg.norm(p - c) - np.linalg.norm(a[:, 0]))
    half = np.linalg.norm(a, axis=0)
    axes = a / half
    local = axes.T @ (p - c)
    if shape.kind == "rectangle":
        half = np.array([half[0], half[1], 0.0])
    return float(np.linalg.norm(local - np.clip(local, -half, half)))


def test_objects_are_clear_of_the_room_and_resting_ones_stand_on_a_surface(micro_root, mitsuba_variant):
    from pipeline.data.synth import mitsuba_backend as mb
    from pipeline.data.synth.scene import Room
    from pipeline.ops.primitives import LIFT_M

    checked = meshes = 0
    for s, v in _views(micro_root):
        room = Room.from_json(json.loads((micro_root / s / "scene.json").read_text()))
        scene = mb.load_scene(room)
        for c in _read(micro_root, s, v)[1]:
            if c.kind != "object":
                continue
            mesh = c.description["mesh"]
            if mesh is not None:  # every vertex outside every shape of the room (a box's inside is 0 away)
                for p in np.asarray(mesh["vertices"])[::3]:
                    gap = min(_distance_to_shape(p, shape) for shape in room.shapes)
                    assert gap > 0, (s, v, c.name, gap)
                meshes += 1
            for x, y, z, r in [] if mesh is not None else c.description["spheres"]:
                gap = min(_distance_to_shape(np.array([x, y, z]), shape) for shape in room.shapes) - r
                assert gap > 0, (s, v, c.name, gap)
            if c.description["support"] == "resting":
                if mesh is not None:
                    vertices = np.asarray(mesh["vertices"])
                    x, y, z = vertices[np.argmin(vertices[:, 1])]
                    r = 0.0
                else:
                    x, y, z, r = c.description["spheres"][0]
                foot = np.array([[x, y - r + 0.01, z]])
                hit = mb.intersect(scene, foot, np.array([[0.0, -1.0, 0.0]]))
                assert hit["t"][0] == pytest.approx(0.01 + LIFT_M, abs=1e-4), (s, v, c.name)
            checked += 1
    assert checked >= 2 and meshes >= 1


def test_object_gbuffers_match_analytic_ray_casting(micro_root):
    """Mitsuba's hits at pixel centres (what synthesize stores) against `models.insertion.object_gbuffer`'s
    analytic sphere and mesh intersection, occluded by the view's ground-truth depth."""
    from pipeline.data.synth.mitsuba_backend import world_from_view
    from pipeline.models.insertion import object_gbuffer
    from pipeline.systems.ring_scoring import view_shape

    for s, v in _views(micro_root):
        maps, cases = _read(micro_root, s, v)
        cam = iv.read_cameras(micro_root, s)[v]
        w2v = world_from_view(
            type("C", (), json.loads((micro_root / s / "scene.json").read_text())["cameras"][int(v)])()
        )
        assert np.allclose(w2v, np.asarray(cam["world_from_view"]))
        depth = torch.from_numpy(np.nan_to_num(maps["depth"][..., 0], posinf=0.0) / 1000.0).double()
        for c in cases:
            if c.kind != "object":
                continue
            g = object_gbuffer([view_shape(c.description, w2v)], depth, float(cam["fov_x_deg"]))
            same = np.intersect1d(g["pixel"].numpy(), c.pixel.numpy())
            # pixel sets agree but where a silhouette or a contact crosses a pixel centre within float32
            # noise: a couple of pixels, or 5 % of a large object
            differ = max(len(c.pixel), len(g["pixel"])) - len(same)
            assert differ <= max(2, 0.05 * len(c.pixel)), (s, v, c.name, differ)
            ia = np.searchsorted(g["pixel"].numpy(), same)
            ib = np.searchsorted(c.pixel.numpy(), same)
            assert torch.allclose(g["depth"][ia].float(), c.depth[ib], atol=1e-4)
            assert torch.allclose(g["normal"][ia].float(), c.normal[ib], atol=1e-3)
            assert torch.allclose(c.albedo, torch.tensor(c.description["albedo"]).expand_as(c.albedo), atol=1e-6)


def _object_cases(root):
    for s, v in _views(root):
        room = Room.from_json(json.loads((root / s / "scene.json").read_text()))
        for c in _read(root, s, v)[1]:
            if c.kind == "object":
                yield s, v, room, c


def test_surroundings_lie_around_the_object_and_darken_under_resting_ones(micro_root, mitsuba_variant):
    """The ring: room pixels only (none of the object's), each within `ring_reach` bounding radii of the
    object; below resting objects Mitsuba's change is a shadow on balance."""
    reach = CaseConfig().ring_reach
    resting_change, checked = 0.0, 0
    for s, v, room, c in _object_cases(micro_root):
        maps = iv.read_view(micro_root, s, v).maps
        H, W = maps["im"].shape[:2]
        assert not set(c.ring_pixel.tolist()) & set(c.pixel.tolist()), (s, v, c.name)
        assert torch.all(c.ring_stderr >= 0)
        ring = c.ring_pixel.numpy()
        if not len(ring):  # an object far from every surface
            continue
        o, d = synth_cases._camera_rays(room.cameras[int(v)], W, H, ring)
        scene = mb.load_scene(room)
        points = o + d * mb.intersect(scene, o, d)["t"][:, None]
        centre, bound = synth_cases._bounding(c.description["spheres"])
        assert np.all(np.linalg.norm(points - centre, axis=1) <= reach * bound * 1.001), (s, v, c.name)
        if c.description["support"] == "resting":
            resting_change += float(c.ring_delta.sum())
        checked += 1
    assert checked >= 2 and resting_change < 0


def test_paired_difference_matches_independent_renders_with_less_noise(micro_root, mitsuba_variant):
    """`radiance_difference` (both scenes from the same random streams) estimates the same difference as
    two independent renders, within 4 combined standard errors summed over the ring, and at the same
    samples its standard error is smaller; a scene against itself differs by exactly 0 (llvm)."""
    s, v, room, c = next((s, v, room, c) for s, v, room, c in _object_cases(micro_root) if len(c.ring_pixel))
    maps = iv.read_view(micro_root, s, v).maps
    H, W = maps["im"].shape[:2]
    o, d = synth_cases._camera_rays(room.cameras[int(v)], W, H, c.ring_pixel.numpy())
    obj = synth_cases.InsertedObject(**c.description)
    with_obj, without = mb.load_scene(synth_cases.room_with_object(room, obj)), mb.load_scene(room)
    spp = 64
    diff, se = mb.radiance_difference(with_obj, without, o, d, spp, seed=3)
    a, se_a = mb.radiance(with_obj, o, d, spp, seed=5)
    b, se_b = mb.radiance(without, o, d, spp, seed=7)
    total, total_se = float(diff.sum()), float(np.sqrt((se**2).sum()))
    independent, independent_se = float((a - b).sum()), float(np.sqrt((se_a**2 + se_b**2).sum()))
    assert abs(total - independent) <= 4 * np.hypot(total_se, independent_se)
    assert total_se < independent_se
    if mitsuba_variant.startswith("llvm"):
        same, same_se = mb.radiance_difference(without, without, o, d, 8, seed=3)
        assert np.all(same == 0) and np.all(same_se == 0)


def test_edited_ground_truth_carries_the_new_material(micro_root):
    edits = [c for s, v in _views(micro_root) for c in _read(micro_root, s, v)[1] if c.kind == "edit"]
    assert edits
    for c in edits:
        d = c.description
        assert torch.allclose(c.albedo, torch.tensor(d["albedo"]).expand_as(c.albedo), atol=1e-6)
        if d["kind"] == "metal":
            assert torch.all(c.material[:, 1] == 1.0) and torch.allclose(c.material[:, 0], torch.tensor(0.1))
        assert torch.all(c.radiance >= 0) and torch.all(c.stderr >= 0)


DAMAGES = ("missing_json", "corrupt_npz", "missing_key", "missing_ring", "nan", "out_of_view", "ring_out_of_view")


@pytest.mark.parametrize("damage", [*DAMAGES, "wrong_size"])
def test_damaged_case_files_are_refused_naming_the_file(micro_root, tmp_path, damage):
    scene, view = next((s, v) for s, v in _views(micro_root) if _read(micro_root, s, v)[1])
    shutil.copytree(micro_root / scene, tmp_path / scene)
    js, npz = case_io.paths(tmp_path, scene, view)
    with np.load(npz) as z:
        arrays = {k: z[k] for k in z.files}
    H, W = (int(x) for x in arrays["size"])
    if damage == "missing_json":
        js.unlink()
    elif damage == "corrupt_npz":
        npz.write_bytes(npz.read_bytes()[:100])
    else:
        if damage == "missing_key":
            arrays.pop("object0_normal" if "object0_normal" in arrays else "edit0_albedo")
        elif damage == "missing_ring":
            arrays.pop(next(k for k in arrays if k.endswith("_ring_delta")))
        elif damage == "ring_out_of_view":
            key = next(k for k in arrays if k.endswith("_ring_pixel") and len(arrays[k]))
            arrays[key][-1] = H * W
        elif damage == "nan":
            key = next(k for k in arrays if k.endswith("_radiance"))
            arrays[key][0, 0] = np.nan
        elif damage == "out_of_view":
            key = next(k for k in arrays if k.endswith("_pixel"))
            arrays[key][0] = H * W
        np.savez(npz, **arrays)
    h, w = (H, W + 1) if damage == "wrong_size" else (H, W)
    with pytest.raises(DatasetError, match=f"{scene}/{view}_cases"):
        case_io.read_cases(tmp_path, scene, view, h, w)


@pytest.mark.parametrize("damage", ["nan_vertex", "face_out_of_range", "flat_vertices", "no_faces", "float_faces"])
def test_a_damaged_mesh_object_is_refused_naming_the_file_and_object(micro_root, tmp_path, damage):
    """A mesh object's triangles in the case JSON: finite (V, 3) vertices and (F >= 1, 3) integer faces
    that index them, or the read is refused naming the file and the object."""
    scene, view, k = next(
        (s, v, i)
        for s, v in _views(micro_root)
        for i, o in enumerate(json.loads(case_io.paths(micro_root, s, v)[0].read_text())["objects"])
        if o["mesh"] is not None
    )
    shutil.copytree(micro_root / scene, tmp_path / scene)
    js, _ = case_io.paths(tmp_path, scene, view)
    desc = json.loads(js.read_text())
    mesh = desc["objects"][k]["mesh"]
    if damage == "nan_vertex":
        mesh["vertices"][0][1] = float("nan")
    elif damage == "face_out_of_range":
        mesh["faces"][-1][2] = len(mesh["vertices"])
    elif damage == "flat_vertices":
        mesh["vertices"] = [x for v in mesh["vertices"] for x in v]
    elif damage == "no_faces":
        del mesh["faces"]
    else:
        mesh["faces"] = [[float(i) for i in f] for f in mesh["faces"]]
    js.write_text(json.dumps(desc))
    maps = iv.read_view(tmp_path, scene, view).maps
    H, W = maps["im"].shape[:2]
    with pytest.raises(DatasetError, match=rf"{view}_cases.json: objects\[{k}\].mesh"):
        case_io.read_cases(tmp_path, scene, view, H, W)
