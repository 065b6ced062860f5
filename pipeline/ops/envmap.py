"""Environment-map layouts of the lighting ground truth, in one place for the writer and every reader.

Hemisphere maps (surface probes): rows over the polar angle theta in [0, pi/2] from the surface normal,
columns over the azimuth phi in [0, 2 pi) from the tangent of `frames.orthonormal_basis` towards its
bitangent; texel (a, b) is centred at theta = (a + .5)/rows * pi/2, phi = (b + .5)/cols * 2 pi.
Sphere maps (free points): rows over theta in [0, pi] from +y (up), columns over phi from -z (forward)
towards +x. Directions point where the light comes from (DESIGN.md section 3).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pipeline.ops.frames import orthonormal_basis, to_local


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
