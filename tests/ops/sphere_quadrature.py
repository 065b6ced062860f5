"""Deterministic integration over the sphere for peaked integrands, and a chi-square test for samplers.

Both use a polar grid centred on a direction c (for GGX lobes, the mirror direction of wo): radial
edges geometrically spaced from `inner` to pi, so a lobe of width ~alpha is resolved however narrow,
and each cell is integrated with a midpoint rule on `sub` x `sub` points (d omega = sin theta' dtheta' dphi').
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy import stats

from pipeline.ops.frames import from_local, orthonormal_basis


def polar_grid(inner: float, n_theta: int = 40, n_phi: int = 24, extra=()) -> tuple[np.ndarray, np.ndarray]:
    """Polar edges (theta', phi'); `extra` adds theta' edges where the integrand is known to jump."""
    edges_t = np.unique(np.concatenate([[0.0], np.geomspace(inner, math.pi, n_theta), list(extra)]))
    edges_p = np.linspace(0, 2 * math.pi, n_phi + 1)
    return edges_t, edges_p


def _cell_points(edges_t, edges_p, sub):
    """Midpoints (Tc, Pc, sub, sub) of theta/phi and their solid-angle weights."""
    f = (np.arange(sub) + 0.5) / sub
    t0, t1 = edges_t[:-1, None], edges_t[1:, None]
    p0, p1 = edges_p[:-1, None], edges_p[1:, None]
    th = t0 + (t1 - t0) * f  # (Tc, sub)
    ph = p0 + (p1 - p0) * f  # (Pc, sub)
    TH = th[:, None, :, None] + 0 * ph[None, :, None, :]
    PH = ph[None, :, None, :] + 0 * th[:, None, :, None]
    w = np.sin(TH) * ((t1 - t0) / sub)[:, None, :, None] * ((p1 - p0) / sub)[None, :, None, :]
    return TH, PH, w


def directions_around(centre: torch.Tensor, theta: np.ndarray, phi: np.ndarray) -> torch.Tensor:
    """Unit directions (..., 3) at polar angle theta, azimuth phi around `centre` (3,)."""
    c = centre.reshape(1, 3).to(torch.float64)
    t, b = orthonormal_basis(c)
    local = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    lv = torch.from_numpy(local.reshape(-1, 3))
    return from_local(lv, t.expand(len(lv), 3), b.expand(len(lv), 3), c.expand(len(lv), 3)).reshape(*theta.shape, 3)


def cell_integrals(fn, centre: torch.Tensor, inner: float, sub: int = 8, n_theta: int = 40, n_phi: int = 24, extra=()):
    """Integrals of fn(directions (M, 3)) -> (M,) or (M, C) over every polar cell: (Tc, Pc[, C])."""
    edges_t, edges_p = polar_grid(inner, n_theta, n_phi, extra)
    TH, PH, w = _cell_points(edges_t, edges_p, sub)
    dirs = directions_around(centre, TH, PH).reshape(-1, 3)
    vals = fn(dirs).detach().to(torch.float64).numpy()
    vals = vals.reshape(*TH.shape, *vals.shape[1:])
    w = w.reshape(*w.shape, *([1] * (vals.ndim - w.ndim)))
    return (vals * w).sum(axis=(2, 3))


def integrate_sphere(fn, centre: torch.Tensor, inner: float, sub: int = 8) -> np.ndarray:
    return cell_integrals(fn, centre, inner, sub).sum(axis=(0, 1))


def chi_square_pvalue(
    samples: torch.Tensor,
    pdf_fn,
    centre: torch.Tensor,
    inner: float,
    min_expected: float = 5.0,
    sub: int = 32,
    extra=(),
) -> tuple[float, float]:
    """Pearson chi-square p-value of sample directions (N, 3) against the density pdf_fn over the polar
    cells around `centre`; cells expecting fewer than `min_expected` samples are pooled. Also returns
    the total probability the quadrature finds (should be 1). Many sub-points per cell because pdfs
    jump to 0 at the edge of their support (the horizon, h reaching the tangent plane) inside cells."""
    n = samples.shape[0]
    probs = cell_integrals(pdf_fn, centre, inner, sub, extra=extra)
    edges_t, edges_p = polar_grid(inner, extra=extra)
    c = centre.reshape(1, 3).to(torch.float64)
    t, b = orthonormal_basis(c)
    s = samples.to(torch.float64)
    local = torch.stack([(s * t).sum(-1), (s * b).sum(-1), (s * c).sum(-1)], -1).numpy()
    th = np.arccos(np.clip(local[:, 2], -1, 1))
    ph = np.mod(np.arctan2(local[:, 1], local[:, 0]), 2 * math.pi)
    it = np.clip(np.searchsorted(edges_t, th, side="right") - 1, 0, len(edges_t) - 2)
    ip = np.clip(np.searchsorted(edges_p, ph, side="right") - 1, 0, len(edges_p) - 2)
    observed = np.zeros_like(probs)
    np.add.at(observed, (it, ip), 1)
    expected = probs * n
    obs, exp = observed.ravel(), expected.ravel()
    # Samples where the quadrature finds no probability at all: a handful happen in cells that only
    # graze the edge of the support (a piecewise-constant pdf, e.g. GGX at alpha = 1); many mean the
    # sampler draws where its pdf says it cannot.
    outside = int(obs[exp == 0].sum())
    if outside > max(10, 1e-4 * n):
        return 0.0, float(probs.sum())
    small = exp < min_expected
    obs = np.concatenate([obs[~small], [obs[small].sum()]])
    exp = np.concatenate([exp[~small], [exp[small].sum()]])
    keep = exp >= min_expected  # the pooled bin takes part only when it is itself well filled
    chi2 = float(((obs[keep] - exp[keep]) ** 2 / exp[keep]).sum())
    dof = int(keep.sum()) - 1
    return float(stats.chi2.sf(chi2, dof)), float(probs.sum())
