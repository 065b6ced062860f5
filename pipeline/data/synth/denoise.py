"""Denoising of the rendered HDR beauty image with Intel Open Image Denoise (CPU, via `pyoidn`).

A path tracer at the sample counts a CPU can afford leaves grain and fireflies (a small sun through the
window, glossy bounces) that real training sets do not have: their frames are rendered long or denoised.
Only the beauty image is denoised; the ground-truth maps come from exact per-pixel queries and the
lighting probes keep their own sample statistics.
"""

from __future__ import annotations

import numpy as np


class DenoiseError(RuntimeError):
    pass


def denoise_hdr(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) linear HDR radiance -> denoised (H, W, 3) float32, non-negative.

    Colour-only filtering (the `RT` filter in HDR mode): the base-colour and normal maps would be clean
    auxiliary inputs, but on mirrors and metals they describe the mirror rather than what it reflects,
    which the filter then smears."""
    try:
        import pyoidn
    except ImportError as exc:  # pragma: no cover - pyoidn is a pinned dependency
        raise DenoiseError("synth.denoise=true needs the `pyoidn` package (see requirements.lock)") from exc
    im = np.asarray(image)
    if im.ndim != 3 or im.shape[-1] != 3:
        raise DenoiseError(f"denoise: expected an (H, W, 3) image, got shape {im.shape}")
    if not np.isfinite(im).all():
        raise DenoiseError("denoise: the image holds NaN or inf radiance")
    out = pyoidn.denoise(np.ascontiguousarray(im, np.float32), hdr=True)
    return np.ascontiguousarray(np.maximum(out, 0.0), np.float32)
