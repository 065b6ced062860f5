"""Environment-map layouts of the lighting ground truth, in one place for the writer and every reader.

Hemisphere maps (surface probes): rows over the polar angle theta in [0, pi/2] from the surface normal,
columns over the azimuth phi in [0, 2 pi) from the tangent of `frames.orthonormal_basis` towards its
bitangent; texel (a, b) is centred at theta = (a + .5)/rows * pi/2, phi = (b + .5)/cols * 2 pi.
Sphere maps (free points): rows over theta in [0, pi] from +y (up), columns over phi from -z (forward)
towards +x. Directions point where the light comes from (docs/design.md, section 3).

A texel's value is the mean radiance over its solid angle (as a box-filtered environment map), not the
radiance along its centre ray: `texel_directions` draws directions uniformly in solid angle inside
given texels (uniform in cos theta and phi over the texel's band), for the ground truth's renderer and
for every predictor that is scored against it.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pipeline.ops.frames import from_local, orthonormal_basis, to_local


def hemisphere_directions(normals: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """(P, rows, cols, 3) directions at texel centres: theta = (a+.5)/rows * pi/2 from the normal,
    phi = (b+.5)/cols * 2 pi from the tangent towards the bitangent of `ops.frames.orthonormal_basis`."""
    t, bt = (x.numpy() for x in orthonormal_basis(torch.from_numpy(np.asarray(normals, np.float64))))
    theta = (np.arange(rows) + 0.5) / rows * (math.pi / 2)
    phi = (np.arange(cols) + 0.5) / cols * (2 * math.pi)
    st, ct = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    sp, cp = np.sin(phi)[None, :, None], np.cos(phi)[None, :, None]
    local = [st * cp, st * sp, ct * np.ones_like(cp)]  # each (rows, cols, 1)
    return (
        local[0][None] * t[:, None, None] + local[1][None] * bt[:, None, None] + local[2][None] * normals[:, None, None]
    )


def sphere_directions(rows: int, cols: int) -> np.ndarray:
    """(rows, cols, 3) view-space directions: theta from +y (up), phi from -z (forward) towards +x."""
    theta = (np.arange(rows) + 0.5) / rows * math.pi
    phi = (np.arange(cols) + 0.5) / cols * (2 * math.pi)
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    return np.stack([np.sin(th) * np.sin(ph), np.cos(th), -np.sin(th) * np.cos(ph)], -1)


def _square_cells(k: int, dtype) -> torch.Tensor:
    """(k*k, 2) lower corners (i, j) of the cells of a k x k grid over [0, k)^2, row-major."""
    if k < 1:
        raise ValueError(f"k={k}: a k x k grid needs k >= 1")
    i, j = torch.meshgrid(torch.arange(k, dtype=dtype), torch.arange(k, dtype=dtype), indexing="ij")
    return torch.stack([i.reshape(-1), j.reshape(-1)], -1)


def square_centres(k: int, dtype=torch.float64) -> torch.Tensor:
    """(k*k, 2) centres of the cells of a k x k grid over [0, 1)^2, in `stratified_square`'s order (the
    deterministic stratified points: no random number)."""
    return (_square_cells(k, dtype) + 0.5) / k


def stratified_square(k: int, count: int, generator: torch.Generator, dtype=torch.float64) -> torch.Tensor:
    """(count, k*k, 2) points of [0, 1)^2, one per cell of a k x k grid, jittered uniformly inside its
    cell by `generator` (independently for each of `count` sets)."""
    cells = _square_cells(k, dtype).expand(count, -1, -1)
    return (cells + torch.rand(count, k * k, 2, generator=generator, dtype=dtype)) / k


def texel_directions(
    row: torch.Tensor, col: torch.Tensor, u: torch.Tensor, rows: int, cols: int, normal: torch.Tensor | None = None
) -> torch.Tensor:
    """Directions uniform in solid angle inside texels of hemisphere maps (`normal` (M, 3) given) or
    sphere maps (normal None), laid out as `hemisphere_directions` / `sphere_directions`.

    row, col (M,) long texel indices; u (M, S, 2) or (S, 2) points of [0, 1)^2 (u[..., 0] moves over the
    texel's cos(theta) band, u[..., 1] over its azimuth). Returns (M, S, 3) unit directions; u = (.5, .5)
    gives the direction at the texel's solid-angle centre (its cos-theta midpoint, not its theta midpoint)."""
    extent = math.pi / 2 if normal is not None else math.pi
    dtype = u.dtype
    u = u.expand(len(row), *u.shape[-2:]) if u.ndim == 2 else u
    r = row.to(dtype)[:, None]
    c0, c1 = torch.cos(r / rows * extent), torch.cos((r + 1) / rows * extent)
    ct = c0 + (c1 - c0) * u[..., 0]
    st = torch.sqrt((1 - ct * ct).clamp(min=0))
    phi = (col.to(dtype)[:, None] + u[..., 1]) / cols * (2 * math.pi)
    if normal is None:
        return torch.stack([st * torch.sin(phi), ct, -st * torch.cos(phi)], -1)
    n = normal.to(dtype)[:, None, :].expand(-1, u.shape[1], -1)
    t, bt = orthonormal_basis(n)
    return from_local(torch.stack([st * torch.cos(phi), st * torch.sin(phi), ct], -1), t, bt, n)


def texel_solid_angles(rows: int, cols: int, hemisphere: bool) -> np.ndarray:
    """(rows,) solid angle of one texel in each row, steradians (every column of a row is equal)."""
    extent = math.pi / 2 if hemisphere else math.pi
    edges = np.cos(np.arange(rows + 1) / rows * extent)
    return (edges[:-1] - edges[1:]) * (2 * math.pi / cols)


def hemisphere_lookup(
    radiance: torch.Tensor, probe: torch.Tensor, normal: torch.Tensor, wi: torch.Tensor
) -> torch.Tensor:
    """Bilinear lookup in hemisphere maps laid out by `hemisphere_directions` (texel centres at
    theta = (a + .5)/rows * pi/2 from the normal, phi = (b + .5)/cols * 2 pi from the tangent of
    `orthonormal_basis`).

    radiance (P, rows, cols, 3) probes; probe (K,) long, the probe of each query; normal (K, 3) its unit
    normal; wi (K, 3) unit query directions. Returns (K, 3): exact at texel centres, bilinear between
    them, periodic in phi, clamped in theta (directions below the horizon read the last row)."""
    t, bt = orthonormal_basis(normal)
    x, y, z = to_local(wi, t, bt, normal).unbind(-1)
    theta = torch.atan2(torch.sqrt(x * x + y * y), z).clamp(0, math.pi / 2)
    phi = torch.atan2(y, x) % (2 * math.pi)
    return _bilinear(radiance, probe, theta / (math.pi / 2), phi)


def sphere_lookup(radiance: torch.Tensor, probe: torch.Tensor, wi: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup in full-sphere maps laid out by `sphere_directions` (texel centres at
    theta = (a + .5)/rows * pi from +y, phi = (b + .5)/cols * 2 pi from -z towards +x).

    radiance (P, rows, cols, 3); probe (K,) long; wi (K, 3) unit view-space directions. Returns (K, 3):
    exact at texel centres, periodic in phi, clamped in theta at the poles' first and last rows."""
    x, y, z = wi.unbind(-1)
    theta = torch.acos(y.clamp(-1, 1))
    phi = torch.atan2(x, -z) % (2 * math.pi)
    return _bilinear(radiance, probe, theta / math.pi, phi)


def _bilinear(radiance: torch.Tensor, probe: torch.Tensor, v: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """Bilinear read of maps (P, rows, cols, 3) at row coordinate v in [0, 1] (texel centres at
    (a + .5)/rows, clamped at the first and last rows) and azimuth phi in [0, 2 pi) (periodic)."""
    _, rows, cols, _ = radiance.shape
    flat = radiance.reshape(-1, 3)
    a = (v * rows - 0.5).clamp(0, rows - 1)
    b = phi / (2 * math.pi) * cols - 0.5
    a0, b0 = a.floor(), b.floor()
    fa, fb = (a - a0)[:, None], (b - b0)[:, None]
    a0 = a0.long()
    a1 = (a0 + 1).clamp(max=rows - 1)
    b0l = b0.long() % cols
    b1l = (b0l + 1) % cols
    base = probe * rows

    def at(r, c):
        return flat[(base + r) * cols + c]

    return (1 - fa) * ((1 - fb) * at(a0, b0l) + fb * at(a0, b1l)) + fa * ((1 - fb) * at(a1, b0l) + fb * at(a1, b1l))
