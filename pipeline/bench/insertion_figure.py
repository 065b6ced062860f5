"""`python -m pipeline.bench.insertion_figure`: objects inserted as a user inserts them, with and without
the shadows and bounce light of differential rendering, beside Mitsuba's render of the same objects.

Objects: a mirror sphere, a glossy and a diffuse vase (meshes, `bench.real_photo.objects_at`) resting on
the floor at three pixels found from the normals (`bench.real_photo.floor_pixels`).
- A test view of the synthetic set (`--view SCENE/VIEW`, default the first test view with a floor for all
  three): the objects stand on the ground-truth surface (`insert_into(stand_on=...)`), so that Mitsuba can
  render the same objects in the same room (`scene.json`; the vases as PLY meshes written by trimesh),
  with and without them from the same random streams (`--mitsuba-spp`). Its reference is the photo plus
  Mitsuba's change on the objects and the room near them, as the `edit` stage's ring scoring takes it.
  PSNR (the stage's tone map) over the objects' own pixels and over the room's pixels around them (within
  `models.shadows.SHADOW_REACH` bounding radii on the true surface) that Mitsuba changes by more than
  `CHANGED` of the photo's luminance.
- A real photograph (`bench.real_photo.photo`, scikit-image's `stereo_motorcycle`, scaled by `--photo-scale`):
  everything predicted, as `invrender insert` does it.
Needs the trained exports and `synthesize`'s test views. Writes reports/bench/insertion_figure.png and
.json (the pixels, PSNRs, seconds).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure

from pipeline.bench.common import publish
from pipeline.bench.real_photo import floor_pixels, objects_at, photo
from pipeline.data import interiorverse as iv
from pipeline.data.formats.photo import tonemap as display
from pipeline.data.synth import mitsuba_backend as mb
from pipeline.data.synth.materials import Material
from pipeline.data.synth.scene import Room
from pipeline.metrics.image import psnr_tonemapped
from pipeline.models.insertion import insert_into, place_object, prepare_view
from pipeline.models.light_net import load_light_export
from pipeline.models.material_net import load_material_export
from pipeline.models.shadows import proxy_pixels
from pipeline.ops.brdf import LUMA

CHANGED = 0.02  # a room pixel Mitsuba changes: its luminance moves by more than this share of the photo's
LUMINANCE = np.asarray(LUMA)


def world_shapes(shapes: list, world_from_view: np.ndarray) -> list:
    """View-space shapes (spheres (S, 4) or (vertices (V, 3), faces)) in world space, as numpy arrays."""
    rot, origin = world_from_view[:3, :3], world_from_view[:3, 3]
    out = []
    for shape in shapes:
        if isinstance(shape, torch.Tensor):
            s = shape.double().numpy()
            out.append(np.concatenate([s[:, :3] @ rot.T + origin, s[:, 3:]], 1))
        else:
            vertices, faces = shape
            out.append((vertices.double().numpy() @ rot.T + origin, faces.numpy()))
    return out


def mitsuba_scene(room: Room, shapes: list, materials: list, max_depth: int, folder: Path):
    """The room with world-space `shapes` added, each with its (albedo, roughness, metallic); meshes go
    through PLY files written into `folder`."""
    import mitsuba as mi

    d = mb.scene_dict(room, max_depth)
    for k, (shape, (albedo, rough, metal)) in enumerate(zip(shapes, materials, strict=True)):
        bsdf = mb.bsdf_dict(mi, Material("inserted", list(albedo), float(rough), float(metal)))
        if isinstance(shape, np.ndarray):
            for j, (x, y, z, r) in enumerate(shape):
                d[f"inserted_{k}_{j}"] = {"type": "sphere", "center": [x, y, z], "radius": float(r), "bsdf": bsdf}
        else:
            path = folder / f"inserted_{k}.ply"
            mb.write_mesh_ply({"vertices": shape[0], "faces": shape[1]}, path)
            d[f"inserted_{k}"] = {"type": "ply", "filename": str(path), "bsdf": bsdf, "face_normals": True}
    return mi.load_dict(d, parallel=False, optimize=False)


def _psnr(pred: np.ndarray, target: np.ndarray, mask: np.ndarray, scale: float) -> float:
    if not mask.any():
        return float("nan")
    p, t = (torch.from_numpy(x[mask].astype(np.float64)) for x in (pred, target))
    return float(psnr_tonemapped(p, t, torch.full((len(p),), scale, dtype=torch.float64)))


def test_view(root: Path, material, net, view_id: str | None, spp: int, mitsuba_spp: int, seed: int) -> dict:
    """The objects in a test view, with and without shadows, and Mitsuba's reference (module docstring)."""
    candidates = [(s, v) for s in iv.read_split(root, "test") for v in iv.list_views(root, s)]
    if view_id is not None:
        candidates = [(s, v) for s, v in candidates if f"{s}/{v}" == view_id]
        if not candidates:
            raise ValueError(f"--view {view_id}: not a test view of {root}")
    max_depth = int(json.loads((root / "dataset.json").read_text())["config"]["max_depth"])
    for scene, view in candidates:
        maps = iv.read_view(root, scene, view).maps
        camera = iv.read_cameras(root, scene)[view]
        fov = float(camera["fov_x_deg"])
        prepared = prepare_view(maps["im"], *material, net, fov, mask=maps["mask"][..., 0] > 0.5, gt_maps=maps)
        try:
            pixels = floor_pixels(prepared.gt["normal"][0], prepared.gt["depth"][0])
            objects = objects_at(pixels)
            t0 = time.perf_counter()
            with_shadows, object_pixels = insert_into(prepared, objects, spp, seed, stand_on=prepared.gt)
            seconds = time.perf_counter() - t0
        except ValueError:  # no floor for three objects here (InsertionError is a ValueError)
            if view_id is not None:
                raise
            continue
        without, _ = insert_into(prepared, objects, spp, seed, shadows=False, stand_on=prepared.gt)
        room = Room.from_json(json.loads((root / scene / "scene.json").read_text()))
        placed = [place_object(prepared, o, prepared.gt) for o in objects]
        shapes = world_shapes(placed, np.asarray(camera["world_from_view"]))
        H, W = maps["im"].shape[:2]
        with tempfile.TemporaryDirectory() as folder:
            scene_with = mitsuba_scene(room, shapes, [o.material for o in objects], max_depth, Path(folder))
            rendered = mb.render_view(scene_with, room.cameras[int(view)], W, H, mitsuba_spp, seed)
        bare = mb.render_view(mb.load_scene(room, max_depth), room.cameras[int(view)], W, H, mitsuba_spp, seed)
        im = maps["im"].astype(np.float64)
        change = rendered.astype(np.float64) - bare
        on_object = np.zeros(H * W, bool)
        on_object[object_pixels.numpy()] = True
        on_object = on_object.reshape(H, W)
        # the room around the objects (the proxy's pixels: within SHADOW_REACH radii on the true surface)
        near = np.zeros(H * W, bool)
        near[proxy_pixels(prepared.gt["depth"][0], fov, placed, object_pixels).numpy()] = True
        near = near.reshape(H, W)
        ring = near & (np.abs(change @ LUMINANCE) > CHANGED * np.abs(im @ LUMINANCE))
        # Mitsuba's change where ours can be (the objects and the room near them); farther away its
        # change is the objects' faint indirect light and the two renders' noise
        reference = np.where((on_object | near)[..., None], np.clip(im + change, 0, None), im)
        scale = float(prepared.scale)
        psnr = {
            name: {
                "objects": _psnr(image.numpy(), reference, on_object, scale),
                "room changed by Mitsuba": _psnr(image.numpy(), reference, ring, scale),
            }
            for name, image in (("with shadows", with_shadows), ("without shadows", without))
        }
        return {
            "view": f"{scene}/{view}",
            "pixels": pixels,
            "seconds (three objects, with shadows)": seconds,
            "object_pixels": int(on_object.sum()),
            "room_pixels_changed_by_mitsuba": int(ring.sum()),
            "psnr": psnr,
            "images": {
                "photo": maps["im"],
                "Mitsuba": reference.astype(np.float32),
                "with shadows": with_shadows.numpy(),
                "without shadows": without.numpy(),
            },
            "crop": np.nonzero(on_object),
        }
    raise ValueError(f"{root}: no test view has a floor for three objects")


def real_photo(material, net, spp: int, seed: int, scale: float) -> dict:
    """The objects in the real photo, everything predicted, with and without shadows."""
    im, _, fov = photo()
    if scale != 1:
        size = (int(round(im.shape[1] * scale)), int(round(im.shape[0] * scale)))
        im = np.asarray(
            torch.nn.functional.interpolate(torch.from_numpy(im).permute(2, 0, 1)[None], size=size[::-1], mode="area")[
                0
            ].permute(1, 2, 0)
        )
    prepared = prepare_view(np.ascontiguousarray(im), *material, net, fov)
    pixels = floor_pixels(prepared.pred["normal"][0], prepared.pred["depth"][0])
    objects = objects_at(pixels)
    t0 = time.perf_counter()
    with_shadows, _ = insert_into(prepared, objects, spp, seed)
    seconds = time.perf_counter() - t0
    without, _ = insert_into(prepared, objects, spp, seed, shadows=False)
    return {
        "size": list(im.shape[:2]),
        "pixels": pixels,
        "seconds (three objects, with shadows)": seconds,
        "images": {"photo": im, "with shadows": with_shadows.numpy(), "without shadows": without.numpy()},
    }


def run(
    root: str,
    material_path: str,
    light_path: str,
    view: str | None,
    spp: int,
    mitsuba_spp: int,
    seed: int,
    photo_scale: float,
) -> dict:
    mb.init_mitsuba(mb.choose_variant("auto"))
    material = load_material_export(material_path)
    net, _ = load_light_export(light_path)
    net.eval()
    settings = {"spp": spp, "mitsuba_spp": mitsuba_spp, "seed": seed, "photo_scale": photo_scale}
    settings.update({"material_path": material_path, "light_path": light_path, "changed_share": CHANGED})
    synthetic = test_view(Path(root), material, net, view, spp, mitsuba_spp, seed)
    real = real_photo(material, net, spp, seed, photo_scale)
    measured = {
        "test view: objects' pixels": synthetic["object_pixels"],
        "test view: room pixels Mitsuba changes": synthetic["room_pixels_changed_by_mitsuba"],
        "test view: seconds, three objects with shadows": synthetic["seconds (three objects, with shadows)"],
        "real photo: seconds, three objects with shadows": real["seconds (three objects, with shadows)"],
        f"PSNR (dB) on test view {synthetic['view']} against Mitsuba's render": [
            {"LightNet": name, **{f"{k} (dB)": v for k, v in p.items()}} for name, p in synthetic["psnr"].items()
        ],
    }
    return {"settings": settings, "measured": measured, "test_view": synthetic, "real_photo": real}


def plot(report: dict, path: Path) -> None:
    tv, rp = report["test_view"], report["real_photo"]
    columns = ["photo", "Mitsuba", "with shadows", "without shadows"]  # keys of the images
    fig = Figure(figsize=(10, 7.6))
    axes = fig.subplots(3, 4)
    rows_px, cols_px = tv["crop"]
    H, W = tv["images"]["photo"].shape[:2]
    pad = 12
    crop = (
        slice(max(rows_px.min() - pad, 0), min(rows_px.max() + pad + 1, H)),
        slice(max(cols_px.min() - pad, 0), min(cols_px.max() + pad + 1, W)),
    )
    exposure = 0.3 / max(float(np.median(tv["images"]["photo"])), 1e-6)
    for k, name in enumerate(columns):
        image = tv["images"][name]
        axes[0, k].imshow(display(image, exposure))
        axes[1, k].imshow(display(image[crop], exposure), interpolation="nearest")
        title = name if name in ("photo", "Mitsuba") else f"LightNet, {name}"
        if name in tv["psnr"]:
            p = tv["psnr"][name]
            title += f"\nobjects {p['objects']:.1f} dB, room {p['room changed by Mitsuba']:.1f} dB"
        axes[0, k].set_title(title, fontsize=7)
        if name == "Mitsuba":
            axes[2, k].text(0.5, 0.5, "no reference\nfor a real photo", ha="center", va="center", fontsize=8)
        else:
            axes[2, k].imshow(display(rp["images"][name], 0.3 / max(float(np.median(rp["images"]["photo"])), 1e-6)))
    axes[1, 0].set_ylabel("crop", fontsize=7)
    axes[0, 0].set_ylabel(f"test view {tv['view']}", fontsize=7)
    axes[2, 0].set_ylabel("stereo_motorcycle", fontsize=7)
    for ax in axes.ravel():
        ax.set_xticks([]), ax.set_yticks([])
    spp = report["settings"]
    fig.suptitle(
        f"a mirror sphere, a glossy and a diffuse vase inserted at {spp['spp']} spp (Mitsuba {spp['mitsuba_spp']} spp; "
        "the test view's objects stand on the true floor, the photo's on the predicted one)",
        fontsize=8,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data-root", default="outputs/synthesize")
    p.add_argument("--material-net", default="outputs/train_material/model.pt")
    p.add_argument("--light-net", default="outputs/train_lighting/model.pt")
    p.add_argument("--view", default=None, help="the test view (scene/view); default the first with a floor for three")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel of the insertion (`invrender insert`'s)")
    p.add_argument("--mitsuba-spp", type=int, default=512)
    p.add_argument("--photo-scale", type=float, default=0.5, help="the real photo's scale (1: 741x500)")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    if a.spp < 1 or a.mitsuba_spp < 1 or not 0 < a.photo_scale <= 1:
        p.error("--spp and --mitsuba-spp must be >= 1 and --photo-scale in (0, 1]")
    try:
        report = run(a.data_root, a.material_net, a.light_net, a.view, a.spp, a.mitsuba_spp, a.seed, a.photo_scale)
    except (ValueError, OSError) as exc:
        p.error(str(exc))
    images = {part: report[part].pop("images") for part in ("test_view", "real_photo")}
    crop = report["test_view"].pop("crop")

    def draw(r, out):
        plot(
            {
                **r,
                "test_view": {**r["test_view"], "images": images["test_view"], "crop": crop},
                "real_photo": {**r["real_photo"], "images": images["real_photo"]},
            },
            out,
        )

    print(publish("insertion_figure", report, draw))


if __name__ == "__main__":
    main()
