"""`invrender predict`: MaterialNet on a user's own images, written in the InteriorVerse conventions.

Inputs: `.exr` is used as HDR linear radiance; `.png`/`.jpg`/`.jpeg` are 8-bit sRGB-ish photos turned
linear with the paper's inverse gamma (v/255)^2.2. The network runs at its training resolution (the
image is resized to it) and the maps are resized back to the input's resolution. Outputs per input
`<name>` (the file stem without a trailing `_im`): `<name>_albedo.exr` (H,W,3) linear, `<name>_normal.exr`
(H,W,3) unit view-space (OpenGL), `<name>_depth.exr` (H,W) z-depth in millimetres (the network's
scale-free depth times the median least-squares scale it needed on validation views), `<name>_material.exr`
(H,W,3) R roughness, G metallic, B 0, and `<name>_preview.png`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from pipeline.data.formats.exr import ExrError, read_exr, write_exr
from pipeline.models.material_net import MaterialNet

EXPORT_FORMAT = "invrender.material_net/1"
PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg")


class PredictError(Exception):
    """A bad input image or checkpoint; the message names the file."""


def save_material_model(
    path: str | Path, model: dict, net: MaterialNet, input_size, depth_scale: float, **extra
) -> Path:
    """Write the export `load_material_model` reads: plain weights (torch.load(weights_only=True)), the
    network config, the training resolution (h, w) and the scale that turns its depth into metres."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    blob = {
        "format": EXPORT_FORMAT,
        "model": dict(model),
        "input_size": [int(input_size[0]), int(input_size[1])],
        "depth_scale": float(depth_scale),
        "state_dict": {k: v.detach().cpu() for k, v in net.state_dict().items()},
        **extra,
    }
    torch.save(blob, path)
    return path


def load_material_model(path: str | Path) -> tuple[MaterialNet, dict]:
    """Load `model.pt` (exported by train_material) or a Lightning `.ckpt` of MaterialSystem, weights only.
    Returns the network in eval mode and its metadata (model config, resolution, depth scale)."""
    path = Path(path)
    if not path.is_file():
        raise PredictError(
            f"{path}: no such checkpoint (train it with `dvc repro train_material` or pass --checkpoint)"
        )
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # pickle/zip errors differ by cause; all mean "not a weights-only checkpoint"
        raise PredictError(f"{path}: not a weights-only torch checkpoint ({type(exc).__name__}: {exc})") from exc
    if not isinstance(blob, dict):
        raise PredictError(f"{path}: unexpected checkpoint content ({type(blob).__name__})")
    if blob.get("format") == EXPORT_FORMAT:
        meta, state = dict(blob), blob["state_dict"]
    elif "state_dict" in blob and "model" in blob.get("hyper_parameters", {}):
        meta = {"model": blob["hyper_parameters"]["model"]}
        state = {k.removeprefix("net."): v for k, v in blob["state_dict"].items() if k.startswith("net.")}
    else:
        raise PredictError(
            f"{path}: not a MaterialNet checkpoint (no {EXPORT_FORMAT!r} export, no MaterialSystem state)"
        )
    try:
        net = MaterialNet(**meta["model"])
        net.load_state_dict(state)
    except (TypeError, ValueError, RuntimeError, KeyError) as exc:
        raise PredictError(f"{path}: incompatible with MaterialNet ({exc})") from exc
    return net.eval(), meta


def read_input(path: str | Path) -> np.ndarray:
    """(H, W, 3) float32 linear radiance from an EXR (HDR) or a PNG/JPG (inverse gamma 2.2)."""
    path = Path(path)
    if not path.is_file():
        raise PredictError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".exr":
        try:
            im = read_exr(path)
        except ExrError as exc:
            raise PredictError(str(exc)) from exc
    elif suffix in PHOTO_SUFFIXES:
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(path) as img:
                im = (np.asarray(img.convert("RGB"), np.float32) / 255.0) ** 2.2
        except (UnidentifiedImageError, OSError) as exc:
            raise PredictError(f"{path}: cannot decode image ({exc})") from exc
    else:
        raise PredictError(f"{path}: unsupported input type {suffix!r} (use .exr, .png or .jpg)")
    if im.ndim == 2:
        im = np.repeat(im[..., None], 3, -1)
    if im.ndim != 3 or im.shape[-1] < 3:
        raise PredictError(f"{path}: expected an RGB image, got shape {im.shape}")
    im = im[..., :3]
    if not np.isfinite(im).all():
        raise PredictError(f"{path}: contains NaN or inf pixels")
    if (im < 0).any():
        raise PredictError(f"{path}: contains negative radiance")
    return np.ascontiguousarray(im, np.float32)


def output_name(path: Path) -> str:
    stem = path.stem
    return stem[:-3] if stem.endswith("_im") else stem


@torch.no_grad()
def predict_maps(
    net: MaterialNet, meta: dict, im: np.ndarray, renormalize_normals: bool = True
) -> dict[str, np.ndarray]:
    """One (H, W, 3) linear image -> maps at (H, W) in the InteriorVerse conventions (see module doc).
    Upsampled normals are renormalised unless `renormalize_normals` is off (the NYUv2 protocol scores
    the bilinearly resized prediction as it is)."""
    H, W = im.shape[:2]
    x = torch.from_numpy(im).permute(2, 0, 1)[None]
    size = meta.get("input_size")  # (h, w) the network was trained at
    if size:
        x = F.interpolate(x, size=tuple(size), mode="area" if size[0] < H else "bilinear", align_corners=None)
    pred = net(x)
    back = {k: F.interpolate(v, size=(H, W), mode="bilinear", align_corners=False) for k, v in pred.items()}
    if renormalize_normals:
        back["normal"] = F.normalize(back["normal"], dim=1, eps=1e-6)
    depth_m = back["depth"][0, 0] * float(meta.get("depth_scale", 1.0))
    material = back["material"][0].permute(1, 2, 0).clamp(0, 1)
    return {
        "albedo": back["albedo"][0].permute(1, 2, 0).clamp(0, 1).numpy(),
        "normal": back["normal"][0].permute(1, 2, 0).numpy(),
        "depth": (depth_m * 1000.0).numpy(),
        "material": torch.cat([material, torch.zeros_like(material[..., :1])], -1).numpy(),
    }


def predict_files(inputs: list[str | Path], out: str | Path, checkpoint: str | Path) -> list[Path]:
    """Run on every input (all are read and checked first, so a bad file fails before any output);
    returns the written files."""
    from pipeline.tracking.figures import prediction_sheet

    net, meta = load_material_model(checkpoint)
    images = [(Path(p), read_input(p)) for p in inputs]
    names = [output_name(p) for p, _ in images]
    if len(set(names)) != len(names):
        raise PredictError(f"inputs map to the same output name: {sorted(names)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for (path, im), name in zip(images, names, strict=True):
        maps = predict_maps(net, meta, im)
        for key, arr in maps.items():
            target = out / f"{name}_{key}.exr"
            write_exr(target, np.ascontiguousarray(arr, np.float32))
            written.append(target)
        written.append(prediction_sheet(im, maps, out / f"{name}_preview.png", title=path.name))
    return written
