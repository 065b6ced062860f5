"""NYUv2 normal scores (docs/design.md, section 6.5): angles in degrees between a
prediction and the ground truth over a valid mask, per image; and the pooled statistics of all pixels."""

from __future__ import annotations

import numpy as np

THRESHOLDS = (11.25, 22.5, 30.0)


def angles(pred, gt, mask, renormalize: bool = False) -> np.ndarray:
    """Angles (degrees) at the masked pixels. pred, gt (H, W, 3), mask (H, W) bool. The ground truth is
    normalised; the prediction is not unless `renormalize` (the reference script dots the resized
    prediction as it is)."""
    p, g, m = np.asarray(pred, np.float64), np.asarray(gt, np.float64), np.asarray(mask, bool)
    if p.shape != g.shape or p.ndim != 3 or p.shape[-1] != 3 or m.shape != p.shape[:2]:
        raise ValueError(f"pred {p.shape}, gt {g.shape} must be (H, W, 3) and mask {m.shape} (H, W)")
    if not (np.isfinite(p[m]).all() and np.isfinite(g[m]).all()):
        raise ValueError("normals contain NaN or inf inside the mask")
    g = g / np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-12)
    if renormalize:
        p = p / np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), 1e-12)
    cos = np.clip((p * g).sum(-1), -1.0, 1.0)
    return np.degrees(np.arccos(cos))[m]


def mean_angular_error(pred, gt, mask, renormalize: bool = False) -> float:
    """Mean angle in degrees over the mask of one image (NaN if the mask is empty); the paper's score is
    the mean of this over the test images."""
    a = angles(pred, gt, mask, renormalize)
    return float(a.mean()) if a.size else float("nan")


def pooled_stats(all_angles: list[np.ndarray]) -> dict[str, float]:
    """Mean, median and % under 11.25/22.5/30 degrees over the pixels of all images together."""
    a = np.concatenate([np.asarray(x, np.float64).ravel() for x in all_angles]) if all_angles else np.zeros(0)
    if not a.size:
        raise ValueError("no valid normal pixels to pool")
    out = {"pooled_mean": float(a.mean()), "pooled_median": float(np.median(a))}
    out.update({f"pct_under_{t:g}": float(100.0 * np.mean(a < t)) for t in THRESHOLDS})
    return out
