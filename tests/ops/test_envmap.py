"""The ground-truth-probe baseline's bilinear hemisphere lookup against the synthesize stage's layout."""

import math

import numpy as np
import torch

from pipeline.ops.envmap import hemisphere_directions, hemisphere_lookup
from pipeline.ops.frames import orthonormal_basis


def _probes(normals: np.ndarray, rows: int, cols: int, field):
    dirs = torch.from_numpy(hemisphere_directions(normals, rows, cols)).float()  # (P, rows, cols, 3)
    return dirs, field(dirs)


def _smooth(d: torch.Tensor) -> torch.Tensor:  # a smooth RGB radiance field over directions
    v = torch.tensor([0.3, -0.5, 0.8])
    return torch.stack([1 + (d * v).sum(-1), 2 + d[..., 0] * d[..., 1], 1.5 + d[..., 2] ** 2], -1)


def test_texel_centres_are_exact():
    normals = torch.nn.functional.normalize(torch.randn(5, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    dirs, rad = _probes(normals.double().numpy(), 8, 16, _smooth)
    P, R, C, _ = dirs.shape
    probe = torch.arange(P).repeat_interleave(R * C)
    got = hemisphere_lookup(rad, probe, normals[probe], dirs.reshape(-1, 3))
    torch.testing.assert_close(got, rad.reshape(-1, 3), atol=1e-4, rtol=0)


def test_interpolates_between_rows_and_wraps_in_phi():
    n = torch.tensor([[0.0, 0.0, 1.0]])
    rows, cols = 4, 8
    dirs, _ = _probes(n.double().numpy(), rows, cols, _smooth)
    a_idx = torch.arange(rows).float()[None, :, None, None].expand(1, rows, cols, 1)
    b_idx = torch.arange(cols).float()[None, None, :, None].expand(1, rows, cols, 1)
    rad = torch.cat([a_idx, b_idx, torch.ones_like(a_idx)], -1)  # radiance = (row, col, 1)
    # halfway in theta between rows 1 and 2, on column 3's centre
    theta = 2.0 / rows * (math.pi / 2)
    phi = 3.5 / cols * 2 * math.pi
    t, bt = orthonormal_basis(n)
    wi = math.sin(theta) * (math.cos(phi) * t + math.sin(phi) * bt) + math.cos(theta) * n
    got = hemisphere_lookup(rad, torch.zeros(1, dtype=torch.long), n, wi)
    torch.testing.assert_close(got, torch.tensor([[1.5, 3.0, 1.0]]), atol=1e-4, rtol=0)
    # a quarter texel before phi = 0: 3/4 of the first column, 1/4 of the last
    phi = -0.25 / cols * 2 * math.pi + 0.5 / cols * 2 * math.pi
    theta = 0.5 / rows * (math.pi / 2)
    wi = math.sin(theta) * (math.cos(phi) * t + math.sin(phi) * bt) + math.cos(theta) * n
    got = hemisphere_lookup(rad, torch.zeros(1, dtype=torch.long), n, wi)
    torch.testing.assert_close(got, torch.tensor([[0.0, 0.25 * (cols - 1), 1.0]]), atol=1e-4, rtol=0)


def test_error_shrinks_with_probe_resolution():
    gen = torch.Generator().manual_seed(1)
    normals = torch.nn.functional.normalize(torch.randn(20, 3, generator=gen), dim=-1)
    wi = torch.nn.functional.normalize(torch.randn(20, 3, generator=gen), dim=-1)
    wi = torch.where(((wi * normals).sum(-1) < 0)[:, None], -wi, wi)  # upper hemisphere
    errors = []
    for rows, cols in ((4, 8), (8, 16), (16, 32)):
        _, rad = _probes(normals.double().numpy(), rows, cols, _smooth)
        got = hemisphere_lookup(rad, torch.arange(20), normals, wi)
        errors.append(float((got - _smooth(wi)).abs().max()))
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.02
