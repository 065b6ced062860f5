"""Positional (Fourier) encodings of directions and positions."""

from __future__ import annotations

import math

import torch


def fourier(x: torch.Tensor, frequencies: int, include_input: bool = True, pi: bool = True) -> torch.Tensor:
    """(..., D) -> (..., D * (2 * frequencies + include_input)): sin and cos of 2^k * pi * x for
    k = 0 .. frequencies - 1 (NeRF's encoding; without the factor pi when `pi` is off, as the released
    out-of-view NeRF encodes), optionally with x itself first."""
    if frequencies < 0:
        raise ValueError(f"frequencies={frequencies}: must be >= 0")
    scales = 2.0 ** torch.arange(frequencies, dtype=x.dtype, device=x.device)
    if pi:
        scales = scales * math.pi
    arg = x.unsqueeze(-1) * scales  # (..., D, F)
    parts = [torch.sin(arg).flatten(-2), torch.cos(arg).flatten(-2)]
    return torch.cat(([x] if include_input else []) + parts, -1)


def fourier_dim(dim: int, frequencies: int, include_input: bool = True) -> int:
    return dim * (2 * frequencies + int(include_input))


def random_fourier(x: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
    """Random Fourier features (Tancik et al. 2020): (..., D) with a basis (D, M) drawn once from
    N(0, sigma^2) -> (..., 2 M): [sin(2 pi x B), cos(2 pi x B)]."""
    arg = 2 * math.pi * (x @ basis.to(x.dtype))
    return torch.cat([torch.sin(arg), torch.cos(arg)], -1)
