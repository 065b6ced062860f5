"""Equirectangular maps in view space, the layout `invrender envmap` writes: a W x W/2 map whose row r has
polar angle theta = pi (r + .5) / (W/2) from +y (up) and whose column c has azimuth
phi = 2 pi ((c + .5) / W - .5), the direction being (sin theta sin phi, cos theta, -sin theta cos phi): the
`ops.envmap` sphere map turned half a turn in azimuth, so that the centre column looks forward (-z).
Directions point where the light comes from. Kept apart from `ops.envmap`, which the data stages read.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pipeline.ops.envmap import square_centres, texel_directions


def equirect_directions(width: int) -> np.ndarray:
    """(W/2, W, 3) unit view-space directions at the texel centres of a W x W/2 equirectangular map, the
    layout of `invrender envmap`: row r at polar angle theta = pi (r + .5) / (W/2) from +y (up), column c
    at azimuth phi = 2 pi ((c + .5) / W - .5); d = (sin theta sin phi, cos theta, -sin theta cos phi), so
    the centre column looks along the camera's forward -z and +x (phi = pi/2) is to its right. W even.

    It is a sphere map (`sphere_directions`) turned by half a turn in azimuth: column c of this layout
    is column (c + W/2) mod W of a sphere map of the same size."""
    if width < 2 or width % 2:
        raise ValueError(f"width={width}: an equirectangular map needs a positive even width")
    theta = (np.arange(width // 2) + 0.5) / (width // 2) * math.pi
    phi = 2 * math.pi * ((np.arange(width) + 0.5) / width - 0.5)
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    return np.stack([np.sin(th) * np.sin(ph), np.cos(th), -np.sin(th) * np.cos(ph)], -1)


def equirect_texel_directions(width: int, k: int, dtype=torch.float64) -> torch.Tensor:
    """(W/2, W, k*k, 3) unit view-space directions spread inside each texel of the `equirect_directions`
    layout: the centres of a k x k grid over the texel's solid angle (uniform in cos theta and phi, the
    `texel_directions` of the ground truth's probes with `square_centres(k)`), no random number. Their
    mean radiance is the texel's box-filtered value."""
    if width < 2 or width % 2:
        raise ValueError(f"width={width}: an equirectangular map needs a positive even width")
    rows = width // 2
    row = torch.arange(rows).repeat_interleave(width)
    col = (torch.arange(width).repeat(rows) + width // 2) % width  # the sphere-map column of each texel
    d = texel_directions(row, col, square_centres(k, dtype), rows, width)
    return d.reshape(rows, width, k * k, 3)
