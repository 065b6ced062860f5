"""Pinhole camera (docs/design.md, section 3): OpenGL view space, pixel centres at +0.5, z-depth.

fov_x is the horizontal field of view in degrees; fx = fy = (W/2)/tan(fov_x/2), cx = W/2, cy = H/2.
The view-space point at pixel (i, j) with z-depth z is z * ((j+.5-cx)/fx, -(i+.5-cy)/fy, -1).
"""

from __future__ import annotations

import math

import torch


def focal(fov_x: float | torch.Tensor, width: int) -> torch.Tensor | float:
    """Focal length in pixels from the horizontal FOV (degrees); works on floats and tensors."""
    if torch.is_tensor(fov_x):
        return (width / 2) / torch.tan(torch.deg2rad(fov_x) / 2)
    return (width / 2) / math.tan(math.radians(fov_x) / 2)


def pixel_directions(height: int, width: int, fov_x: float, device=None, dtype=torch.float32) -> torch.Tensor:
    """(H, W, 3) view-space ray directions through pixel centres, scaled so that z = -1 (not unit)."""
    f = focal(fov_x, width)
    i = torch.arange(height, device=device, dtype=dtype) + 0.5
    j = torch.arange(width, device=device, dtype=dtype) + 0.5
    ii, jj = torch.meshgrid(i, j, indexing="ij")
    return torch.stack([(jj - width / 2) / f, -(ii - height / 2) / f, -torch.ones_like(ii)], -1)


def backproject(depth: torch.Tensor, fov_x: float) -> torch.Tensor:
    """z-depth (B, H, W) metres -> view-space points (B, H, W, 3)."""
    _, H, W = depth.shape
    return depth[..., None] * pixel_directions(H, W, fov_x, depth.device, depth.dtype)


def project(points: torch.Tensor, fov_x: float, height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """View-space points (N, 3) -> continuous pixel coordinates (N, 2) as (col x, row y), where pixel
    (i, j) covers [j, j+1) x [i, i+1), and z-depth (N,) (positive in front of the camera)."""
    f = focal(fov_x, width)
    z = -points[..., 2]
    x = points[..., 0] / z * f + width / 2
    y = -points[..., 1] / z * f + height / 2
    return torch.stack([x, y], -1), z


def backproject_views(depth: torch.Tensor, fov_x) -> torch.Tensor:
    """backproject for a batch whose views may differ in FOV: depth (B, H, W), fov_x float or (B,) degrees
    -> (B, H, W, 3)."""
    if not torch.is_tensor(fov_x) or fov_x.ndim == 0:
        return backproject(depth, float(fov_x))
    return torch.stack([backproject(depth[b : b + 1], float(fov_x[b]))[0] for b in range(depth.shape[0])])


RAY_OFFSET_M = 1e-3  # secondary rays (probe queries, re-render samples) start this far above their surface


def pixel_values(images: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor:
    """Values (M, C) of images (B, C, H, W) at flat pixel indices (M,) into B*H*W (as `grid_pixels` gives)."""
    return images.permute(0, 2, 3, 1).reshape(-1, images.shape[1])[pixels]


def grid_pixels(mask: torch.Tensor, stride: int) -> torch.Tensor:
    """Flat indices (into B*H*W) of the set pixels of mask (B, H, W) on every `stride`-th row and column."""
    grid = torch.zeros_like(mask)
    grid[:, ::stride, ::stride] = True
    return torch.nonzero((grid & mask).reshape(-1)).squeeze(-1)


def depth_range(depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Smallest and largest valid z-depth (B,) of (B, H, W) maps (invalid: 0 or non-finite; an image with
    none gets 1 for both)."""
    valid = torch.isfinite(depth) & (depth > 0)
    big = torch.finfo(depth.dtype).max
    lo = torch.where(valid, depth, torch.full_like(depth, big)).flatten(1).amin(1)
    hi = torch.where(valid, depth, torch.zeros_like(depth)).flatten(1).amax(1)
    none = ~valid.flatten(1).any(1)
    one = torch.ones_like(lo)
    return torch.where(none, one, lo), torch.where(none, one, hi)


def window_depth_difference(z_surface, z_ray, depth_min, depth_max) -> torch.Tensor:
    """The released SSRT's depth difference between a ray and the surface it passes behind, in OpenGL
    window depth [0, 1] (N,): view depth divided by the image's largest depth, projected with near plane
    n = depth_min / depth_max and far plane 1, so z_win(d) = (d - n) / (d (1 - n)). Its difference is
    n / (1 - n) * (1/d_surface - 1/d_ray) = depth_min depth_max / (depth_max - depth_min) (1/z_s - 1/z_r),
    with z in metres (N,) and the per-ray image range (N,). Hyperbolic in depth: a gap far from the camera
    weighs much less than the same gap near it."""
    span = (depth_max - depth_min).clamp(min=1e-6)
    return depth_min * depth_max / span * (1.0 / z_surface - 1.0 / z_ray)
