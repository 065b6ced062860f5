"""Photos at the pipeline's edge: the one sRGB curve, the one display tone map and the one
photo-to-linear reader.

Inside the pipeline images are linear RGB (docs/design.md, section 3). Every 8-bit photo that enters (IIW,
NYUv2, `invrender predict`, stand-ins) is decoded with the sRGB curve (IEC 61966-2-1), and every
linear image written as a photo is encoded with its inverse. HDR radiance shown to people (figures, the
PNG beside an HDR `invrender insert` result) goes through `tonemap`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.data.formats.exr import ExrError, read_exr

PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg")


class PhotoError(ValueError):
    """An unreadable or unusable input image; the message names the file."""


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    """The sRGB decoding curve on values in [0, 1] (float64): v/12.92 below 0.04045, else
    ((v + 0.055)/1.055)^2.4. Anchors: 0.5 -> 0.21404, 1 -> 1."""
    v = np.asarray(v, np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(v: np.ndarray) -> np.ndarray:
    """The sRGB encoding curve (inverse of `srgb_to_linear`), clipping to [0, 1] first."""
    v = np.clip(np.asarray(v, np.float64), 0.0, 1.0)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)


def tonemap(hdr: np.ndarray, exposure: float | None = None) -> np.ndarray:
    """The display tone map for HDR radiance (..., 3), values in [0, 1]: times `exposure` (by default the
    one that puts the median positive value at 0.3), Reinhard x / (1 + x), then a 1/2.2 gamma. NaN and
    +inf show as 0."""
    x = np.nan_to_num(np.asarray(hdr, float), nan=0.0, posinf=0.0)
    if exposure is None:
        med = np.median(x[x > 0]) if (x > 0).any() else 1.0
        exposure = 0.3 / max(med, 1e-6)
    x = x * exposure
    return np.clip((x / (1 + x)) ** (1 / 2.2), 0, 1)


def srgb8_to_linear(photo: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 sRGB -> (H, W, 3) float32 linear in [0, 1]."""
    return srgb_to_linear(np.asarray(photo) / 255.0).astype(np.float32)


def read_linear(path: str | Path) -> np.ndarray:
    """(H, W, 3) float32 linear radiance of an image file: an EXR as stored (HDR), a PNG/JPG through the
    sRGB curve. Refuses other types, non-RGB shapes, NaN/inf and negative values, naming the file."""
    path = Path(path)
    if not path.is_file():
        raise PhotoError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".exr":
        try:
            im = read_exr(path)
        except ExrError as exc:
            raise PhotoError(str(exc)) from exc
    elif suffix in PHOTO_SUFFIXES:
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(path) as img:
                im = srgb8_to_linear(np.asarray(img.convert("RGB")))
        except (UnidentifiedImageError, OSError) as exc:
            raise PhotoError(f"{path}: cannot decode image ({exc})") from exc
    else:
        raise PhotoError(f"{path}: unsupported input type {suffix!r} (use .exr, .png or .jpg)")
    if im.ndim == 2:
        im = np.repeat(im[..., None], 3, -1)
    if im.ndim != 3 or im.shape[-1] < 3:
        raise PhotoError(f"{path}: expected an RGB image, got shape {im.shape}")
    im = im[..., :3]
    if not np.isfinite(im).all():
        raise PhotoError(f"{path}: contains NaN or inf pixels")
    if (im < 0).any():
        raise PhotoError(f"{path}: contains negative radiance")
    return np.ascontiguousarray(im, np.float32)
