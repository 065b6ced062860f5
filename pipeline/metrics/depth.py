"""NYUv2 depth scores (docs/design.md, section 6.6). One image at a time, (H, W) arrays
in metres; the prediction may have any scale (all scores here are scale-invariant)."""

from __future__ import annotations

import numpy as np

EPS = 1e-20  # as the reference script: log(d + 1e-20)
MIN_M, MAX_M = 1.0, 10.0  # the score's mask: 1 m < D < 10 m


def _check(pred, gt) -> tuple[np.ndarray, np.ndarray]:
    p, g = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    if p.shape != g.shape or p.ndim != 2:
        raise ValueError(f"pred {p.shape} and gt {g.shape} must be equal (H, W) arrays (resize the prediction first)")
    if not (np.isfinite(p).all() and np.isfinite(g).all()):
        raise ValueError("depth maps contain NaN or inf")
    if (p < 0).any() or (g < 0).any():
        raise ValueError("depth maps contain negative values")
    return p, g


def si_error(pred, gt) -> float:
    """e = masked mean of (a - b)^2 with a = log D^ - mean(log D^), b = log D - mean(log D); the means run
    over *all* pixels (as the reference code does), the mask is 1 m < D < 10 m. NaN if the mask is empty."""
    p, g = _check(pred, gt)
    a = np.log(p + EPS)
    b = np.log(g + EPS)
    a, b = a - a.mean(), b - b.mean()
    m = (g > MIN_M) & (g < MAX_M)
    return float(((a - b) ** 2)[m].mean()) if m.any() else float("nan")


def si_rmse(pred, gt) -> float:
    """The paper's NYUv2 depth "si-MSE" for one image: sqrt(si_error); the benchmark averages it over images."""
    return float(np.sqrt(si_error(pred, gt)))


def median_scaled(pred, gt) -> dict[str, float]:
    """AbsRel and delta < 1.25 after scaling the prediction by median(D) / median(D^) over the mask."""
    p, g = _check(pred, gt)
    m = (g > MIN_M) & (g < MAX_M) & (p > 0)
    if not m.any():
        return {"abs_rel": float("nan"), "delta_1.25": float("nan")}
    s = np.median(g[m]) / np.median(p[m])
    ps, gs = p[m] * s, g[m]
    ratio = np.maximum(ps / gs, gs / ps)
    return {"abs_rel": float(np.mean(np.abs(ps - gs) / gs)), "delta_1.25": float(np.mean(ratio < 1.25))}
