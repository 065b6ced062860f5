"""`invrender` command line: dataset checks, figures, and MaterialNet predictions on your own images."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path


def _validate(args) -> int:
    from pipeline.data import interiorverse as iv
    from pipeline.data.preprocess import _fov as camera_fov

    root = Path(args.root)
    splits = iv.read_splits(root)
    jobs = iv.split_views(root, splits)
    rejected = []
    cameras: dict[str, dict | None] = {}
    for split, scene, view in jobs:
        rejected.extend(iv.read_view(root, scene, view, args.max_inconsistent_fraction).rejections(split))
        # preprocess stops on an unreadable cameras.json or a view without its FOV: so does validate
        if scene not in cameras:
            cameras[scene] = iv.read_cameras(root, scene)
        if cameras[scene] is not None:
            camera_fov(root, scene, view, cameras[scene], None)
    bad_views = len({(r["scene"], r["view"]) for r in rejected})
    for r in rejected:
        print(f"REJECT {r['file']}: {r['reason']}")
    print(
        json.dumps(
            {
                "root": str(root),
                "views": len(jobs),
                "rejected_views": bad_views,
                "scenes": {k: len(v) for k, v in splits.items()},
            }
        )
    )
    return 1 if rejected else 0


def _sheet(args) -> int:
    from pipeline.data import interiorverse as iv
    from pipeline.data.synth.figures import contact_sheet

    root = Path(args.root)
    views = [(s, v) for s in iv.read_split(root, args.split) for v in iv.list_views(root, s)][: args.views]
    print(contact_sheet(root, views, args.out))
    return 0


MIN_SIDE, MAX_SIDE = 8, 4096  # pixels a side of an input photo (checked from its header, before decoding)


def check_photo_size(path: str | Path) -> None:
    """Refuse a photo smaller than MIN_SIDE or larger than MAX_SIDE pixels a side, reading only its header
    (an 8000x8000 PNG would take gigabytes to decode). Unreadable headers are left to the decoder, which
    names the file."""
    path = Path(path)
    size = None
    try:
        if path.suffix.lower() == ".exr":
            import OpenEXR

            with OpenEXR.File(str(path), header_only=True) as f:
                (x0, y0), (x1, y1) = f.header()["dataWindow"]
            size = (int(x1 - x0 + 1), int(y1 - y0 + 1))
        else:
            from PIL import Image

            with Image.open(path) as img:
                size = img.size
    except Exception:  # noqa: BLE001 - any header failure is reported by the full decoder with the file named
        return
    if min(size) < MIN_SIDE or max(size) > MAX_SIDE:
        raise EditError(f"{path}: {size[0]}x{size[1]} pixels; photos must be {MIN_SIDE} to {MAX_SIDE} pixels a side")


def output_folder(out: str | Path) -> Path:
    """The output folder, created if missing; refused (naming it) when it cannot be created or written."""
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise EditError(f"--out {out}: cannot create the folder ({exc.strerror or exc})") from exc
    if not os.access(out, os.W_OK):
        raise EditError(f"--out {out}: the folder is not writable")
    return out


def output_name(path: Path) -> str:
    """The output prefix of an input: its stem without a trailing `_im` (InteriorVerse names)."""
    stem = path.stem
    return stem[:-3] if stem.endswith("_im") else stem


def predict_files(inputs: list[str | Path], out: str | Path, checkpoint: str | Path) -> list[Path]:
    """`invrender predict`: MaterialNet maps of each input in the InteriorVerse conventions,
    `<name>_{albedo,normal,depth,material}.exr` (depth in millimetres through the export's depth scale;
    material R roughness, G metallic) and `<name>_preview.png`. Every input is read and checked, and the
    export loaded, before anything is written; returns the written files."""
    import numpy as np

    from pipeline.data.formats.exr import write_exr
    from pipeline.data.formats.photo import PhotoError, read_linear
    from pipeline.models.material_net import load_material_export, predict_maps
    from pipeline.tracking.figures import prediction_sheet

    net, meta = load_material_export(checkpoint)
    for p in inputs:
        check_photo_size(p)
    images = [(Path(p), read_linear(p)) for p in inputs]
    names = [output_name(p) for p, _ in images]
    if len(set(names)) != len(names):
        raise PhotoError(f"inputs map to the same output name: {sorted(names)}")
    out = output_folder(out)
    written = []
    for (path, im), name in zip(images, names, strict=True):
        maps = predict_maps(net, meta, im)
        for key, arr in maps.items():
            target = out / f"{name}_{key}.exr"
            write_exr(target, np.ascontiguousarray(arr, np.float32))
            written.append(target)
        written.append(prediction_sheet(im, maps, out / f"{name}_preview.png", title=path.name))
    return written


def _predict(args) -> int:
    written = predict_files(args.inputs, args.out, args.checkpoint)
    for path in written:
        print(path)
    return 0


class EditError(ValueError):
    """A bad `insert` / `edit` argument; the message names it."""


MATERIAL_CLASSES = ("diffuse", "glossy", "mirror")  # models.insertion.OBJECT_MATERIALS

DEFAULT_LIGHT = str(Path("outputs") / "train_lighting" / "model.pt")
DEFAULT_MATERIAL = str(Path("outputs") / "train_material" / "model.pt")


def _parse_floats(text: str, n: int, name: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise EditError(f"{name} {text!r}: expected {n} comma-separated numbers")
    return vals


def _parse_pixel(text: str) -> tuple[int, int]:
    """`--at ROW,COL` as two integers."""
    try:
        row, col = (int(v) for v in text.split(","))
    except ValueError:
        raise EditError(f"--at {text!r}: expected ROW,COL as two integers (pixel row and column)") from None
    return row, col


def _output_paths(out: str | Path) -> tuple[Path, Path]:
    """(PNG, EXR) paths of an --out FILE (.png or .exr); its folder must exist and be writable."""
    out = Path(out)
    if out.suffix.lower() not in (".png", ".exr"):
        raise EditError(f"--out {out}: give a .png or .exr file name (both are written)")
    if not out.parent.is_dir() or not os.access(out.parent, os.W_OK):
        raise EditError(f"--out {out}: folder {out.parent} does not exist or is not writable")
    pair = out.with_suffix(".png"), out.with_suffix(".exr")
    for p in pair:
        if p.is_dir():
            raise EditError(f"--out {out}: {p} is a folder")
    return pair


def _write_result(image, png: Path, exr: Path, hdr_input: bool) -> list[Path]:
    """The composited (H, W, 3) linear image as EXR and as an sRGB PNG (an 8-bit input's own encoding;
    an HDR input through the display tone map). Written to temporary names and renamed, so a failure
    leaves neither file behind."""
    import numpy as np
    from PIL import Image

    from pipeline.data.formats.exr import write_exr
    from pipeline.data.formats.photo import linear_to_srgb, tonemap

    tmp_png, tmp_exr = png.with_name(f".{png.name}.part"), exr.with_name(f".{exr.name}.part.exr")
    try:
        write_exr(tmp_exr, np.ascontiguousarray(image, np.float32))
        display = tonemap(image) if hdr_input else linear_to_srgb(np.clip(image, 0, 1))
        Image.fromarray(np.round(display * 255).astype(np.uint8)).save(tmp_png, format="PNG")
        os.replace(tmp_exr, exr)
        os.replace(tmp_png, png)
    except OSError as exc:
        raise EditError(f"--out {png.with_suffix('')}: cannot write ({exc.strerror or exc})") from exc
    finally:
        for t in (tmp_png, tmp_exr):
            t.unlink(missing_ok=True)
    return [png, exr]


def _prepare_photo(photo: str | Path, material_path, light_path, fov: float):
    """Read the photo and both exports (everything checked before any work) and prepare it: its
    G-buffers predicted and LightNet's context of them (`models.insertion.PreparedView`)."""
    from pipeline.data.formats.photo import read_linear
    from pipeline.models.light_net import load_light_export
    from pipeline.models.material_net import load_material_export

    if not 1.0 <= fov <= 170.0:
        raise EditError(f"--fov {fov}: must be a horizontal field of view in degrees (1-170)")
    material_net, meta = load_material_export(material_path)
    light_net, _ = load_light_export(light_path)
    check_photo_size(photo)
    im = read_linear(photo)
    if min(im.shape[:2]) < MIN_SIDE or max(im.shape[:2]) > MAX_SIDE:
        raise EditError(f"{photo}: {im.shape[1]}x{im.shape[0]} pixels; photos must be {MIN_SIDE} to {MAX_SIDE} a side")
    if float(im.mean()) <= 0:
        raise EditError(f"{photo}: the image is black; there is no light to estimate")
    from pipeline.models.insertion import prepare_view

    return prepare_view(im, material_net, meta, light_net, fov)


def _material_spec(spec: str) -> tuple:
    """`--material`: a class of `models.insertion.OBJECT_MATERIALS`, or a YAML file with `albedo` (R, G, B
    linear in [0, 1]), `roughness` and `metallic` (each in [0, 1])."""
    from pipeline.models.insertion import OBJECT_MATERIALS

    if spec in OBJECT_MATERIALS:
        return OBJECT_MATERIALS[spec]
    path = Path(spec)
    if path.suffix.lower() not in (".yaml", ".yml"):
        raise EditError(f"--material {spec!r}: choose one of {sorted(OBJECT_MATERIALS)} or give a .yaml file")
    import yaml

    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise EditError(f"--material {path}: unreadable ({type(exc).__name__})") from exc
    if not isinstance(data, dict):
        raise EditError(f"--material {path}: expected a mapping with albedo, roughness, metallic")
    missing = [k for k in ("albedo", "roughness", "metallic") if k not in data]
    if missing:
        raise EditError(f"--material {path}: missing key {missing[0]!r}")
    try:
        albedo = tuple(float(v) for v in data["albedo"])
        rough, metal = float(data["roughness"]), float(data["metallic"])
    except (TypeError, ValueError):
        raise EditError(f"--material {path}: albedo must be three numbers, roughness and metallic numbers") from None
    if len(albedo) != 3 or not all(0 <= v <= 1 for v in albedo):
        raise EditError(f"--material {path}: albedo must be three numbers in [0, 1]")
    for key, v in (("roughness", rough), ("metallic", metal)):
        if not 0 <= v <= 1:
            raise EditError(f"--material {path}: {key} {v} must be in [0, 1]")
    return albedo, rough, metal


def _object_shape(spec: str):
    """`--object`: sphere, snowman, or a mesh file (OBJ, PLY, GLB) read as (vertices, faces) tensors."""
    if spec in ("sphere", "snowman"):
        return spec
    import torch

    from pipeline.data.formats.mesh import MeshError, read_mesh

    try:
        vertices, faces = read_mesh(spec)
    except MeshError as exc:
        raise EditError(f"--object {exc}") from None
    return torch.from_numpy(vertices), torch.from_numpy(faces)


def _per_object(values: list | None, name: str, count: int, default) -> list:
    """One value of a repeatable option per object: given once (every object), once per --at, or not (default)."""
    if not values:
        return [default] * count
    if len(values) == 1:
        return values * count
    if len(values) != count:
        raise EditError(f"{name}: given {len(values)} times for {count} --at; give it once or once per --at")
    return list(values)


def insertion_objects(at: list[str], objects=None, scales=None, turns=None, materials=None) -> list:
    """`models.insertion.InsertedObject`s from the repeatable `insert` options, each paired with its --at in
    order; every value checked (and every mesh read) before any model is loaded."""
    from pipeline.models.insertion import InsertedObject

    count = len(at)
    shapes = [_object_shape(o) for o in _per_object(objects, "--object", count, "sphere")]
    sizes = _per_object(scales, "--scale", count, None)
    angles = _per_object(turns, "--turn", count, 0.0)
    looks = [_material_spec(m) for m in _per_object(materials, "--material", count, "mirror")]
    out = []
    for k in range(count):
        row, col = _parse_pixel(at[k])
        if sizes[k] is not None and not (math.isfinite(sizes[k]) and sizes[k] > 0):
            raise EditError(f"--scale {sizes[k]}: must be a positive size in metres")
        if not math.isfinite(angles[k]):
            raise EditError(f"--turn {angles[k]}: must be a finite angle in degrees")
        label = "--at" if count == 1 else f"--at #{k + 1}"
        out.append(InsertedObject(shapes[k], row, col, looks[k], sizes[k], float(angles[k]), label))
    return out


def insert_object(
    photo,
    at: str | list[str],
    out,
    kind: str | list[str] = "sphere",
    material: str | list[str] = "mirror",
    scale: float | list[float] | None = None,
    turn: float | list[float] = 0.0,
    fov: float = 70.0,
    spp: int = 64,
    seed: int = 0,
    material_path=DEFAULT_MATERIAL,
    light_path=DEFAULT_LIGHT,
    shadows: bool = True,
) -> list[Path]:
    """`invrender insert`: objects, each resting on the predicted surface at its pixel `at` ("row,col"),
    lit by LightNet through the MC render layer, composited into the photo with (`shadows`) their shadows
    and bounce light on the room; writes <out>.png and <out>.exr. Every option is one value (all objects)
    or a list of one per `at` (`insertion_objects`)."""
    from pipeline.models.insertion import insert_into

    listed = lambda v: v if isinstance(v, list) else ([v] if v is not None else None)  # noqa: E731
    png, exr = _output_paths(out)
    if spp < 1:
        raise EditError(f"--spp {spp}: must be >= 1")
    objects = insertion_objects(listed(at), listed(kind), listed(scale), listed(turn), listed(material))
    view = _prepare_photo(photo, material_path, light_path, fov)
    result, _ = insert_into(view, objects, spp, seed, shadows)
    return _write_result(result.numpy(), png, exr, Path(photo).suffix.lower() == ".exr")


def edit_material(
    photo,
    mask,
    out,
    roughness: float | None = None,
    metallic: float | None = None,
    albedo: str | None = None,
    fov: float = 70.0,
    spp: int = 64,
    seed: int = 0,
    material_path=DEFAULT_MATERIAL,
    light_path=DEFAULT_LIGHT,
) -> list[Path]:
    """`invrender edit`: the masked region's material replaced (the given fields; the predicted ones
    elsewhere), re-rendered under LightNet and composited into the photo; writes <out>.png and <out>.exr."""
    import numpy as np
    import torch
    from PIL import Image, UnidentifiedImageError

    from pipeline.models.insertion import composite_image, edited_gbuffer, light_net_radiance, render_case
    from pipeline.models.render_layer import MCRenderLayer

    png, exr = _output_paths(out)
    if roughness is None and metallic is None and albedo is None:
        raise EditError("edit: give at least one of --roughness, --metallic, --albedo")
    for name, v in (("--roughness", roughness), ("--metallic", metallic)):
        if v is not None and not 0.0 <= v <= 1.0:
            raise EditError(f"{name} {v}: must be in [0, 1]")
    rgb_albedo = _parse_floats(albedo, 3, "--albedo") if albedo is not None else None
    if rgb_albedo is not None and not all(0.0 <= v <= 1.0 for v in rgb_albedo):
        raise EditError(f"--albedo {albedo}: each channel must be in [0, 1] (linear base colour)")
    if spp < 1:
        raise EditError(f"--spp {spp}: must be >= 1")
    mask_path = Path(mask)
    if not mask_path.is_file():
        raise EditError(f"--mask {mask}: no such file")
    try:
        with Image.open(mask_path) as img:
            m = np.asarray(img.convert("L"), np.float32) / 255.0
    except (UnidentifiedImageError, OSError) as exc:
        raise EditError(f"--mask {mask}: cannot decode image ({exc})") from exc
    view = _prepare_photo(photo, material_path, light_path, fov)
    H, W = view.photo.shape[:2]
    if m.shape != (H, W):
        raise EditError(f"--mask {mask}: {m.shape[1]}x{m.shape[0]} pixels, the photo is {W}x{H}")
    pixels = torch.from_numpy(np.flatnonzero(m.reshape(-1) > 0.5))
    if not len(pixels):
        raise EditError(f"--mask {mask}: selects no pixel (white = edit)")
    gb, fov = view.pred, view.fov
    shading = edited_gbuffer(gb, pixels, rgb_albedo, roughness, metallic)
    light = light_net_radiance(view.net, view.ctx_pred, gb, fov, seed)
    with torch.no_grad():
        rgb = render_case(MCRenderLayer(spp=spp), shading, fov, pixels, light, seed)
    result = composite_image(view.photo, pixels, rgb).numpy()
    return _write_result(result, png, exr, Path(photo).suffix.lower() == ".exr")


ENVMAP_FOV = 70.0  # horizontal field of view assumed for the photo (degrees): insert's and edit's default
ENVMAP_SEED = 0  # LightNet's out-of-view samples: the same call writes the same file
ENVMAP_RAYS = 1 << 16  # LightNet queries per chunk (memory stays bounded for wide maps)
MAX_ENVMAP_WIDTH = MAX_SIDE


def envmap_at(
    photo,
    at: str,
    out,
    width: int = 64,
    offset: float = 0.05,
    material_path=DEFAULT_MATERIAL,
    light_path=DEFAULT_LIGHT,
) -> Path:
    """`invrender envmap`: LightNet's incident radiance at the predicted surface point under pixel `at`
    ("row,col"), lifted `offset` metres along its predicted normal (turned towards the camera where the
    prediction faces away), as a `width` x `width`/2 equirectangular HDR map in the photo's linear units
    (layout `ops.equirect.equirect_directions`: row r at theta = pi (r + .5)/(W/2) from +y, column c at
    phi = 2 pi ((c + .5)/W - .5) from -z towards +x). Each texel is the mean over the centres of a k x k
    grid of its solid angle (`ops.equirect.equirect_texel_directions`, k = `data.lighting.EVAL_TEXEL_STRATA`),
    as the evaluation scores LightNet against the ground truth's texel means. Writes the float32 EXR
    `out` and returns its path."""
    import numpy as np
    import torch

    from pipeline.data.formats.exr import write_exr
    from pipeline.data.lighting import EVAL_TEXEL_STRATA
    from pipeline.ops.camera import backproject
    from pipeline.ops.equirect import equirect_texel_directions

    out = Path(out)
    if out.suffix.lower() != ".exr":
        raise EditError(f"--out {out}: give a .exr file name (the map is written as float32 EXR)")
    if not out.parent.is_dir() or not os.access(out.parent, os.W_OK):
        raise EditError(f"--out {out}: folder {out.parent} does not exist or is not writable")
    if out.is_dir():
        raise EditError(f"--out {out}: is a folder")
    if width < 2 or width % 2 or width > MAX_ENVMAP_WIDTH:
        raise EditError(f"--width {width}: must be a positive even integer (at most {MAX_ENVMAP_WIDTH})")
    if not math.isfinite(offset) or offset < 0:
        raise EditError(f"--offset {offset}: must be a finite distance in metres, >= 0")
    row, col = _parse_pixel(at)
    view = _prepare_photo(photo, material_path, light_path, ENVMAP_FOV)
    gb, fov = view.pred, view.fov
    H, W = view.photo.shape[:2]
    if not (0 <= row < H and 0 <= col < W):
        raise EditError(f"--at {at}: pixel (row {row}, col {col}) is outside the {W}x{H} image")
    z = float(gb["depth"][0, row, col])
    n = gb["normal"][0, :, row, col].double()
    if not math.isfinite(z) or z <= 0 or not bool(torch.isfinite(n).all()) or float(n.norm()) < 1e-6:
        raise EditError(f"--at {at}: no valid surface at that pixel (predicted depth {z})")
    point = backproject(gb["depth"], fov)[0, row, col].double()
    n = n / n.norm()
    if float(n @ point) > 0:  # a surface seen from behind (a prediction error): lift it on its visible side
        n = -n
    origin = (point + offset * n).float()
    rows = width // 2
    dirs = equirect_texel_directions(width, EVAL_TEXEL_STRATA).float()  # (rows, W, S, 3)
    S = dirs.shape[2]
    generator = torch.Generator().manual_seed(ENVMAP_SEED)
    chunk = max(1, ENVMAP_RAYS // (width * S))  # map rows per LightNet call
    parts = []
    with torch.no_grad():
        for r0 in range(0, rows, chunk):
            wi = dirs[r0 : r0 + chunk].reshape(-1, 3)
            radiance = view.net(
                view.ctx_pred,
                gb,
                fov,
                origin.expand(len(wi), 3).contiguous(),
                wi,
                torch.zeros(len(wi), dtype=torch.long),
                generator,
            )["radiance"]
            parts.append(radiance.reshape(-1, width, S, 3).mean(2))
    envmap = np.ascontiguousarray(torch.cat(parts).numpy(), np.float32)  # (rows, W, 3)
    tmp = out.with_name(f".{out.name}.part.exr")
    try:
        write_exr(tmp, envmap)
        os.replace(tmp, out)
    except OSError as exc:
        raise EditError(f"--out {out}: cannot write ({exc.strerror or exc})") from exc
    finally:
        tmp.unlink(missing_ok=True)
    return out


def _envmap(args) -> int:
    kwargs = {"material_path": args.material_net, "light_path": args.light_net}
    print(envmap_at(args.photo, args.at, args.out, args.width, args.offset, **kwargs))
    return 0


def _render_kwargs(args) -> dict:
    """The options `insert` and `edit` share (`_add_render_args`)."""
    return {
        "fov": args.fov,
        "spp": args.spp,
        "seed": args.seed,
        "material_path": args.material_net,
        "light_path": args.light_net,
    }


def _insert(args) -> int:
    kwargs = {"kind": args.object, "material": args.material, "scale": args.scale, "turn": args.turn}
    kwargs.update(_render_kwargs(args), shadows=args.shadows)
    print("\n".join(str(p) for p in insert_object(args.photo, args.at, args.out, **kwargs)))
    return 0


def _edit(args) -> int:
    kwargs = {"roughness": args.roughness, "metallic": args.metallic, "albedo": args.albedo, **_render_kwargs(args)}
    print("\n".join(str(p) for p in edit_material(args.photo, args.mask, args.out, **kwargs)))
    return 0


def _add_render_args(p) -> None:
    p.add_argument("--out", required=True, help="output .png or .exr (both are written)")
    p.add_argument("--fov", type=float, default=70.0, help="horizontal field of view in degrees (default %(default)s)")
    p.add_argument("--spp", type=int, default=64, help="render-layer samples per pixel (default %(default)s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--material-net", default=DEFAULT_MATERIAL, help="MaterialNet export (default: %(default)s)")
    p.add_argument("--light-net", default=DEFAULT_LIGHT, help="LightNet export (default: %(default)s)")


def _whdr(args) -> int:
    from pipeline.data import iiw
    from pipeline.data.formats.photo import srgb_to_linear
    from pipeline.metrics.whdr import whdr

    photo = iiw.read_photo(Path(args.reflectance).parent, Path(args.reflectance).stem) / 255.0
    # like the IIW script: an 8-bit PNG is sRGB and decoded to linear unless --linear says it already is
    reflectance = photo if args.linear else srgb_to_linear(photo)
    path = Path(args.judgements)
    judgements = iiw.read_judgements(path.parent, path.stem) if path.suffix == ".json" else None
    if judgements is None:
        raise iiw.IIWError(f"{path}: judgements must be a .json file")
    print(whdr(reflectance, judgements, delta=args.delta, convention="linear"))
    return 0


def _import_released(args) -> int:
    """`invrender import-released {mgnet,lightnet} FILE --out FILE.pt`: the authors' released weights as an
    invrender export under the `paper` profile (pipeline.models.released)."""
    from pipeline.models import released

    if args.network == "mgnet":
        summary = released.import_mgnet(args.checkpoint, args.out, depth_scale=args.depth_scale)
    else:
        summary = released.import_lightnet(args.checkpoint, args.out)
    print(f"{summary['out']}: {summary['imported']} tensors imported")
    for prefix, count in summary["skipped"].items():
        print(f"skipped (unused at inference) {prefix}: {count}")
    for line in summary.get("notes", []):
        print(line)
    return 0


class _Parser(argparse.ArgumentParser):
    """argparse with its usage errors on one line (`error: invrender insert: argument --at: ...`), exit 2."""

    def error(self, message: str):
        self.exit(2, f"error: {self.prog}: {message}\n")


def main(argv: list[str] | None = None) -> int:
    parser = _Parser(prog="invrender", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    v = sub.add_parser("validate", help="check every view of an InteriorVerse-layout root")
    v.add_argument("root")
    v.add_argument("--max-inconsistent-fraction", type=float, default=0.01)
    v.set_defaults(func=_validate)
    s = sub.add_parser("sheet", help="contact sheet PNG (image + every map) of a few views")
    s.add_argument("root")
    s.add_argument("--out", required=True)
    s.add_argument("--split", default="test", choices=("train", "val", "test"))
    s.add_argument("--views", type=int, default=4)
    s.set_defaults(func=_sheet)
    p = sub.add_parser(
        "predict",
        help="albedo, normal, depth and material maps of your own images (EXR = linear HDR; PNG/JPG = sRGB)",
    )
    p.add_argument("inputs", nargs="+", help="images: .exr (linear HDR), .png, .jpg")
    p.add_argument("--out", required=True, help="folder for <name>_{albedo,normal,depth,material}.exr + preview")
    p.add_argument(
        "--checkpoint",
        default=str(Path("outputs") / "train_material" / "model.pt"),
        help="MaterialNet export (model.pt of train_material or finetune; default: %(default)s)",
    )
    p.set_defaults(func=_predict)
    w = sub.add_parser("whdr", help="WHDR of a reflectance PNG against IIW judgements (as the IIW script)")
    w.add_argument("reflectance", help="8-bit PNG, sRGB-encoded unless --linear")
    w.add_argument("judgements", help="IIW <id>.json")
    w.add_argument("--linear", action="store_true", help="the PNG holds linear reflectance: score it as read")
    w.add_argument("--delta", type=float, default=0.1)
    w.set_defaults(func=_whdr)
    i = sub.add_parser("insert", help="insert an object lit by LightNet into a photo (EXR linear, PNG/JPG sRGB)")
    i.add_argument("photo")
    i.add_argument(
        "--at",
        required=True,
        action="append",
        help="ROW,COL: the pixel whose predicted surface an object rests on (up along the predicted normal); "
        "repeat it to insert several objects, the k-th --at with the k-th value of each option below",
    )
    i.add_argument(
        "--object",
        action="append",
        help="sphere (default), snowman, or a mesh file (.obj, .ply, .glb; its up axis +y): once for every "
        "object or once per --at",
    )
    i.add_argument(
        "--material",
        action="append",
        help=f"one of {', '.join(MATERIAL_CLASSES)} (default mirror), or a .yaml file with albedo [R, G, B] "
        "(linear, 0-1), roughness and metallic: once or once per --at",
    )
    i.add_argument(
        "--scale",
        type=float,
        action="append",
        help="the object's largest extent in metres (default: 1/8 of the view's width at its depth; at most "
        "the room's depth): once or once per --at",
    )
    i.add_argument(
        "--turn",
        type=float,
        action="append",
        help="degrees about the object's up axis (default 0): once or once per --at",
    )
    i.add_argument(
        "--shadows",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="add the objects' shadows and bounce light on the room around them by differential rendering "
        "(the predicted room near each object rendered with and without it; default: on)",
    )
    _add_render_args(i)
    i.set_defaults(func=_insert)
    e = sub.add_parser("edit", help="give a masked region another material, re-rendered under LightNet")
    e.add_argument("photo")
    e.add_argument("--mask", required=True, help="PNG of the photo's size, white = the region to edit")
    e.add_argument("--roughness", type=float, default=None)
    e.add_argument("--metallic", type=float, default=None)
    e.add_argument("--albedo", default=None, help="R,G,B linear base colour in [0, 1]")
    _add_render_args(e)
    e.set_defaults(func=_edit)
    m = sub.add_parser(
        "envmap", help="LightNet's incident light at a pixel's surface point as an equirectangular HDR EXR"
    )
    m.add_argument("photo")
    m.add_argument("--at", required=True, help="ROW,COL: the pixel whose predicted surface point the map is taken at")
    m.add_argument("--out", required=True, help="output .exr (W x W/2, float32, the photo's linear units)")
    m.add_argument("--width", type=int, default=64, help="map width W, even (default %(default)s)")
    m.add_argument(
        "--offset", type=float, default=0.05, help="metres above the surface, along its normal (default %(default)s)"
    )
    m.add_argument("--material-net", default=DEFAULT_MATERIAL, help="MaterialNet export (default: %(default)s)")
    m.add_argument("--light-net", default=DEFAULT_LIGHT, help="LightNet export (default: %(default)s)")
    m.set_defaults(func=_envmap)
    r = sub.add_parser(
        "import-released",
        help="the authors' released MGNet checkpoint or LightNet weights as an invrender export (paper profile)",
    )
    r.add_argument("network", choices=("mgnet", "lightnet"))
    r.add_argument("checkpoint", help="released file: MGNet Lightning .ckpt, LightNet .pth (read weights-only)")
    r.add_argument("--out", required=True, help="the export to write, e.g. released_mgnet.pt")
    r.add_argument(
        "--depth-scale",
        type=float,
        default=1.0,
        help="mgnet: metres per unit of the released relative depth (1: the farthest depth; default %(default)s)",
    )
    r.set_defaults(func=_import_released)
    args = parser.parse_args(argv)
    from pipeline.data.formats.photo import PhotoError
    from pipeline.data.iiw import IIWError
    from pipeline.data.interiorverse import DatasetError
    from pipeline.models.export import ExportError
    from pipeline.models.insertion import InsertionError

    try:
        return args.func(args)
    except (DatasetError, PhotoError, ExportError, IIWError, EditError, InsertionError) as exc:
        # one line: library messages (torch's unpickler, OpenEXR) can run to paragraphs
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        print(f"error: {first}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
