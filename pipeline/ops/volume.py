"""Volume rendering along rays (emission-absorption, NeRF's quadrature).

A ray p + t w crosses S segments [t_i, t_{i+1}] with density sigma_i (1/m) and radiance c_i; segment i
contributes T_i (1 - exp(-sigma_i delta_i)) c_i, T_i = exp(-sum_{j<i} sigma_j delta_j). This is exact for
piecewise-constant fields. Samples are stratified inside [t_near, t_far]; random numbers come in as a
generator so results are reproducible.
"""

from __future__ import annotations

import torch

from pipeline.ops.camera import backproject_views


def stratified_edges(t_near: torch.Tensor, t_far: torch.Tensor, samples: int, generator: torch.Generator | None):
    """Segment edges (N, S+1) splitting [t_near, t_far] (N,) into S equal strata, and one jittered sample
    position per stratum (N, S) (the stratum midpoints when generator is None)."""
    if samples < 1:
        raise ValueError(f"samples={samples}: must be >= 1")
    u = torch.linspace(0.0, 1.0, samples + 1, dtype=t_near.dtype, device=t_near.device)
    edges = t_near[:, None] + (t_far - t_near)[:, None] * u
    if generator is None:
        jitter = torch.full((t_near.shape[0], samples), 0.5, dtype=t_near.dtype, device=t_near.device)
    else:
        jitter = torch.rand(t_near.shape[0], samples, generator=generator, dtype=t_near.dtype).to(t_near.device)
    mids = edges[:, :-1] + (edges[:, 1:] - edges[:, :-1]) * jitter
    return edges, mids


def composite(sigma: torch.Tensor, radiance: torch.Tensor, edges: torch.Tensor):
    """sigma (N, S) >= 0, radiance (N, S, C), edges (N, S+1) -> (radiance (N, C), weights (N, S),
    transmittance left after the last segment (N,))."""
    delta = (edges[:, 1:] - edges[:, :-1]).clamp(min=0)
    tau = sigma.clamp(min=0) * delta
    alpha = 1.0 - torch.exp(-tau)
    # transmittance before each segment: exp of minus the optical depth accumulated so far
    before = torch.exp(-torch.cumsum(torch.cat([torch.zeros_like(tau[:, :1]), tau[:, :-1]], 1), 1))
    weights = before * alpha
    left = torch.exp(-tau.sum(1))
    return (weights.unsqueeze(-1) * radiance).sum(1), weights, left


def ray_box(origin: torch.Tensor, direction: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor):
    """Entry and exit distances (N,) of rays with a box (slab method), clamped to t >= 0; rays that miss
    get an empty interval at 0."""
    inv = 1.0 / torch.where(direction.abs() > 1e-9, direction, torch.full_like(direction, 1e-9))
    t0, t1 = (lo - origin) * inv, (hi - origin) * inv
    t_near = torch.minimum(t0, t1).amax(-1).clamp(min=0)
    t_far = torch.maximum(t0, t1).amin(-1)
    t_far = torch.maximum(t_far, t_near)
    return t_near, t_far


def ray_sphere(origin: torch.Tensor, direction: torch.Tensor, radius: float) -> torch.Tensor:
    """Exit distance (N,) of rays o + t w (unit w) from the sphere |x| = radius about the view-space origin:
    the larger root of t^2 + 2 (o.w) t + |o|^2 - r^2 = 0; 0 for rays that miss it or leave it behind."""
    b = (origin * direction).sum(-1)
    c = (origin * origin).sum(-1) - radius**2
    disc = (b * b - c).clamp(min=0)
    return (-b + torch.sqrt(disc)).clamp(min=0)


def scene_bounds(depth: torch.Tensor, fov_x, margin: float = 0.1) -> torch.Tensor:
    """(B, H, W) z-depth (0 / non-finite = none), fov_x float or (B,) -> (B, 2, 3) view-space box of the
    visible surfaces and the camera, grown by `margin` of its size (the out-of-view scene is assumed to
    lie around them)."""
    pts = backproject_views(torch.where(torch.isfinite(depth), depth, torch.zeros_like(depth)), fov_x)
    valid = (torch.isfinite(depth) & (depth > 0)).unsqueeze(-1)
    big = torch.finfo(depth.dtype).max
    lo = torch.where(valid, pts, torch.full_like(pts, big)).flatten(1, 2).amin(1).clamp(max=0)
    hi = torch.where(valid, pts, torch.full_like(pts, -big)).flatten(1, 2).amax(1).clamp(min=0)
    pad = (hi - lo) * margin + 1e-2
    return torch.stack([lo - pad, hi + pad], 1)
