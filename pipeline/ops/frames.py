"""Orthonormal frames around unit normals and changes of basis. Shapes: (..., 3)."""

from __future__ import annotations

import torch


def orthonormal_basis(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Tangent t and bitangent b completing unit normals n (..., 3) to right-handed frames (t, b, n).

    Branch-free: with s = sign(n_z) (+1 at 0) the construction divides by s + n_z, whose magnitude is
    1 + |n_z| >= 1, so it is stable for every direction including n = (0, 0, -1)."""
    x, y, z = n.unbind(-1)
    s = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (s + z)
    b = x * y * a
    t = torch.stack([1 + s * x * x * a, s * b, -s * x], -1)
    bt = torch.stack([b, s + y * y * a, -y], -1)
    return t, bt


def to_local(v: torch.Tensor, t: torch.Tensor, b: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """World/view vectors v (..., 3) -> coordinates in the frame (t, b, n)."""
    return torch.stack([(v * t).sum(-1), (v * b).sum(-1), (v * n).sum(-1)], -1)


def from_local(v: torch.Tensor, t: torch.Tensor, b: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """Frame coordinates v (..., 3) -> world/view vectors."""
    return v[..., :1] * t + v[..., 1:2] * b + v[..., 2:3] * n


def unit(v: torch.Tensor) -> torch.Tensor:
    """v (..., 3) scaled to unit length (zero vectors stay zero instead of becoming NaN)."""
    return v / v.norm(dim=-1, keepdim=True).clamp(min=1e-12)
