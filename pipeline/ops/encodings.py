"""Positional (Fourier) encodings of directions and positions."""

from __future__ import annotations

import math

import torch


def fourier(x: torch.Tensor, frequencies: int, include_input: bool = True) -> torch.Tensor:
    """(..., D) -> (..., D * (2 * frequencies + include_input)): sin and cos of 2^k * pi * x for
    k = 0 .. frequencies - 1 (NeRF's encoding), optionally with x itself first."""
    if frequencies < 0:
        raise ValueError(f"frequencies={frequencies}: must be >= 0")
    scales = (2.0 ** torch.arange(frequencies, dtype=x.dtype, device=x.device)) * math.pi
    arg = x.unsqueeze(-1) * scales  # (..., D, F)
    parts = [torch.sin(arg).flatten(-2), torch.cos(arg).flatten(-2)]
    return torch.cat(([x] if include_input else []) + parts, -1)


def fourier_dim(dim: int, frequencies: int, include_input: bool = True) -> int:
    return dim * (2 * frequencies + int(include_input))
