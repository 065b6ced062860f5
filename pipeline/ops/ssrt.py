"""Screen-space ray tracing against z-depth maps with a hierarchical min-depth (Hi-Z) traversal.

A ray p + t w (view space) is clipped to the near plane and to the image, projected to a 2-D segment
P(s) = P0 + s (P1 - P0), s in [0, 1], along which its z-depth is perspective-correct:
1/z(s) = (1 - s)/z0 + s/z1. The march visits the pixels the segment crosses, in order, and reports
the first one where the ray *passes behind* the surface (its depth over the pixel reaches the depth map)
while *facing* it (n . w < 0) and does not cross the pixel's facet (the plane through the pixel's centre
point with its normal) only further ahead: a depth map is a staircase, and a ray grazing a plane dips
behind its steps long before it reaches the plane. The gap is 0 when the ray crosses the facet inside
the pixel (a confident hit); otherwise it is how far behind the surface the ray already was when it
entered the pixel, large when it slipped behind a foreground object's silhouette (docs/design.md,
section 5: u = tanh(k gap) then hands the ray to the out-of-view branch).

Speed: a min-depth pyramid lets a ray skip a whole 2^L x 2^L cell when its depth over the cell stays in
front of the nearest surface in it; the level goes up after every skip and down when a cell cannot be
skipped, so free space costs O(log size) steps instead of one step per pixel. All rays advance together
in one elementwise step function (fusable by torch.compile); finished rays are masked out and leave
the working set once a quarter of it has finished (no per-ray Python, little work on finished rays).
Results equal a pixel-by-pixel march with the same hit rule. No gradients flow (the outputs are
indices, a flag and a gap used as a confidence).
"""

from __future__ import annotations

import math

import torch

from pipeline.ops.camera import backproject, focal

NEAR = 1e-3  # metres: rays are clipped to z-depth >= NEAR
SYNC_EVERY = 4  # steps between checks of how many rays are still marching


def min_pyramid(depth: torch.Tensor) -> list[torch.Tensor]:
    """Min-depth mip chain of (B, H, W) maps (invalid = inf); level l has cells of 2^l pixels, sizes rounded
    up (padding cells hold inf), down to 1 x 1."""
    levels = [depth]
    while levels[-1].shape[-1] > 1 or levels[-1].shape[-2] > 1:
        d = levels[-1]
        H, W = d.shape[-2:]
        d = torch.nn.functional.pad(d, (0, W % 2, 0, H % 2), value=math.inf)
        levels.append(-torch.nn.functional.max_pool2d(-d.unsqueeze(1), 2).squeeze(1))
    return levels


def _step_geometry(st: torch.Tensor, s: torch.Tensor, flat_small: torch.Tensor, scale: torch.Tensor):
    """Cell (A, 2) entered at a level with cells of `scale` (A,) pixels from the position at s, and the s
    where the ray leaves it. On a boundary the cell ahead is taken per axis (floor moving +, ceil - 1
    moving -): a forward nudge would vanish below float32 resolution on the slow axis and stall the ray.
    Every exit lies at least 1e-6 ahead, so the march always progresses."""
    scale = scale.unsqueeze(-1)
    p0, dd, idd = st[:, 0:2], st[:, 2:4], st[:, 4:6]
    q = torch.addcmul(p0, s.unsqueeze(-1), dd) / scale
    neg = dd < 0
    cell = torch.where(neg, torch.ceil(q) - 1, torch.floor(q))
    t_axis = ((cell + (~neg).to(st.dtype)) * scale - p0) * idd
    t_axis = t_axis.masked_fill(flat_small, math.inf)
    return cell.int(), torch.maximum(t_axis.amin(-1), s + 1e-6).clamp(max=1.0)


def _step(st, s, flat_small, lvl, ray, b_of, live, res, scene, top: int):
    """One traversal step for A working rays, elementwise apart from gathers (so it fuses when compiled).

    st (A, 8) per-ray segment constants (see `trace`), s (A,) position on the segment, flat_small (A, 2)
    degenerate axes, lvl (A,) level, ray (A, 6) view-space origin and unit direction, b_of (A,) image,
    live (A,) unfinished, res (A, 3) hit row, col (-1 before a hit) and gap; scene is (level_table,
    inv_levels, n_flat, plane_c, cam, H, W) with cam (3,) = focal length, W/2, H/2 in pixels, a tensor:
    scalars derived from a Python float inside a compiled step are recomputed per element in double.
    Returns the new s, level, live flags and res."""
    level_table, inv_levels, n_flat, plane_c, cam, H, W = scene
    take = torch.index_select  # plain row gathers: leaner than advanced indexing on CPU
    tab = take(level_table, 0, lvl)
    rows, cols = tab[:, 0], tab[:, 1]
    cell, s_out = _step_geometry(st, s, flat_small, (1 << lvl).to(st.dtype))
    cx = torch.minimum(cell[:, 0].clamp(min=0), cols - 1)
    cy = torch.minimum(cell[:, 1].clamp(min=0), rows - 1)
    iz_cell = take(inv_levels, 0, tab[:, 2] + (b_of * rows + cy) * cols + cx)
    iz_in = torch.addcmul(st[:, 6], s, st[:, 7])
    iz_out = torch.addcmul(st[:, 6], s_out, st[:, 7])
    behind = torch.minimum(iz_in, iz_out) <= iz_cell  # the ray's far end reaches the nearest surface
    leaf = behind & (lvl == 0) & live
    # At a pixel: does the ray face the surface, and where does it cross the pixel's facet (the plane
    # n . x = c through its centre point)? Ahead of this pixel: the ray only grazes the depth map's
    # staircase and goes on. Inside it: a confident hit (gap 0). Before it: the ray slipped behind.
    pix_flat = ((b_of * H + cy) * W + cx).where(leaf, torch.zeros_like(cx))
    o, d = ray[:, 0:3], ray[:, 3:6]
    n = take(n_flat, 0, pix_flat)
    nd = (n * d).sum(-1)
    t_star = (take(plane_c, 0, pix_flat) - (n * o).sum(-1)) / torch.where(nd < 0, nd, -torch.ones_like(nd))
    x = o + t_star.clamp(min=0).unsqueeze(-1) * d
    # the crossing's s along the screen segment, read on its longer screen axis (the segment's x or y is
    # affine in s with slope D; 1/D is in st): one projected coordinate, no division by |D|^2
    iz_x = cam[0] / (-x[:, 2]).clamp(min=NEAR)
    dd = st[:, 2:4]
    on_x = dd[:, 0].abs() >= dd[:, 1].abs()
    s_star = torch.where(
        on_x,
        (x[:, 0] * iz_x + cam[1] - st[:, 0]) * st[:, 4],
        (cam[2] - x[:, 1] * iz_x - st[:, 1]) * st[:, 5],
    )
    beyond = (t_star > 0) & (s_star > s_out)
    crossing = (t_star > 0) & ~beyond & (s_star >= s)
    done = leaf & (nd < 0) & ~beyond
    gap = torch.where(crossing, 0.0, (1.0 / torch.maximum(iz_in, iz_out) - 1.0 / iz_cell).clamp(min=0))
    # clear: past the cell and one level up (to skip more next time); blocked above the pixel level: one
    # level down; a non-hit pixel: past it
    advance = ~behind | (leaf & ~done)
    s_new = torch.where(advance, s_out, s)
    lvl = (lvl + (~behind).int() - (behind & (lvl > 0)).int()).clamp(max=top)
    res = torch.where(done.unsqueeze(-1), torch.stack([cy.to(st.dtype), cx.to(st.dtype), gap], -1), res)
    return s_new, lvl, live & ~done & (s_new < 1), res


def _segments(o, d, far, cam, H: int, W: int):
    """Per-ray screen segments, elementwise over N rays on 1-D columns (so it vectorises when compiled).

    o (N, 3) view-space origins, d (N, 3) unit directions, far (0-d) metres beyond every surface, cam (3,)
    focal length, W/2, H/2 in pixels. Returns st (N, 8) segment constants (columns P0x P0y Dx Dy 1/Dx
    1/Dy inv0 (inv1 - inv0), see `trace`), small (N, 2) degenerate screen axes, s0 (N,) the start, and
    ok (N,) whether the ray has any part in front of the near plane and inside the image."""
    ox, oy, oz = o.unbind(-1)
    dx, dy, dz = d.unbind(-1)
    # --- clip the 3-D ray: in front of the near plane, within a far distance beyond every surface ----
    toward = dz > 0  # moving towards the camera plane: stop at z = -NEAR
    t_near = (-NEAR - oz) / torch.where(toward, dz, torch.ones_like(dz))
    t_end = torch.where(toward, torch.minimum(far, t_near), far)
    ok = (oz < -NEAR) & (t_end > 0)

    def proj(x, y, z):  # rays that start behind the near plane are dropped by `ok`; keep numbers finite
        z = (-z).clamp(min=NEAR)
        k = cam[0] / z
        return x * k + cam[1], cam[2] - y * k, z

    px0, py0, z0 = proj(ox, oy, oz)
    px1, py1, z1 = proj(ox + t_end * dx, oy + t_end * dy, oz + t_end * dz)
    # --- clip the 2-D segment to the image rectangle [0, W] x [0, H] ----------------------------------
    lo, hi = torch.zeros_like(t_end), torch.ones_like(t_end)
    for p0, p1, size in ((px0, px1, W), (py0, py1, H)):
        dd = p1 - p0
        moving = dd.abs() > 1e-12
        safe = torch.where(moving, dd, torch.ones_like(dd))
        a, b = (0 - p0) / safe, (size - p0) / safe
        lo = torch.where(moving, torch.maximum(lo, torch.minimum(a, b)), lo)
        hi = torch.where(moving, torch.minimum(hi, torch.maximum(a, b)), hi)
        ok = ok & (moving | ((p0 >= 0) & (p0 <= size)))
    ok = ok & (lo < hi)
    # re-parametrise over the clipped part: a near-plane clip can put P1 ~1e6 px away, where float32 could
    # no longer resolve one pixel step; within the image every quantity stays well conditioned
    inv0, inv1 = 1.0 / z0, 1.0 / z1
    lo_c, hi_c = lo.clamp(0, 1), hi.clamp(0, 1)
    inv0, inv1 = (1 - lo_c) * inv0 + lo_c * inv1, (1 - hi_c) * inv0 + hi_c * inv1
    cols, small, exits = [], [], []
    for p0, p1 in ((px0, px1), (py0, py1)):
        dd = p1 - p0
        q0, q1 = p0 + lo_c * dd, p0 + hi_c * dd
        D = q1 - q0
        flat = D.abs() <= 1e-12
        inv_d = 1.0 / torch.where(flat, torch.ones_like(D), D)
        # the start: just past the origin's own pixel (its surface is the ray's origin, not a hit); the
        # exit of that pixel per axis as in `_step_geometry` at s = 0, scale 1
        neg = D < 0
        cell = torch.where(neg, torch.ceil(q0) - 1, torch.floor(q0))
        t_axis = ((cell + (~neg).to(q0.dtype)) - q0) * inv_d
        exits.append(torch.where(flat, torch.full_like(q0, math.inf), t_axis))
        cols.append((q0, D, inv_d))
        small.append(flat)
    s_first = torch.maximum(torch.minimum(exits[0], exits[1]), torch.full_like(lo, 1e-6)).clamp(max=1.0)
    # a ray whose origin projects outside the image starts where it enters it
    s0 = torch.where(lo <= 0, s_first, torch.zeros_like(s_first))
    (qx, Dx, ix), (qy, Dy, iy) = cols
    st = torch.stack([qx, qy, Dx, Dy, ix, iy, inv0, inv1 - inv0], -1)
    return st, torch.stack(small, -1), s0, ok


_COMPILED: dict[str, object] = {}


def _kernel(fn, compiled: bool):
    """fn itself, or fn as one fused torch.compile kernel (dynamic shapes: the ray count changes)."""
    if not compiled:
        return fn
    if fn.__name__ not in _COMPILED:
        _COMPILED[fn.__name__] = torch.compile(fn, dynamic=True)
    return _COMPILED[fn.__name__]


@torch.no_grad()
def trace(
    depth: torch.Tensor,
    normal: torch.Tensor,
    fov_x: float,
    origin: torch.Tensor,
    direction: torch.Tensor,
    batch_index: torch.Tensor | None = None,
    max_steps: int = 4096,
    max_level: int | None = None,
    compiled: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """March rays across depth maps.

    depth (B, H, W) z-depth in metres (0 or non-finite = no surface, e.g. sky); normal (B, 3, H, W) view
    space; fov_x degrees; origin, direction (N, 3) view space; batch_index (N,) long (None = image 0).
    Returns pixel (N, 2) long (row, col) of the hit (-1 on misses), hit (N,) bool and gap (N,) metres
    (ray depth minus surface depth on entering the hit pixel, >= 0; 0 on misses). Rays that leave the
    image, reach the near plane or never pass behind a facing surface are misses. max_level caps the
    pyramid level a ray may skip at (0 = a plain pixel-by-pixel march, for comparison); the hits do not
    depend on it. compiled=True runs the ray setup and each step as fused torch.compile kernels (about
    3x faster on CPU; the first call compiles for tens of seconds and needs a C++ compiler, or Triton on
    CUDA)."""
    B, H, W = depth.shape
    dev, dt = depth.device, depth.dtype
    N = origin.shape[0]
    bidx = torch.zeros(N, dtype=torch.long, device=dev) if batch_index is None else batch_index.to(dev).long()
    d = torch.nn.functional.normalize(direction.to(dt), dim=-1)
    o = origin.to(dt)
    clean = torch.where(torch.isfinite(depth) & (depth > 0), depth, torch.full_like(depth, math.inf))
    levels = min_pyramid(clean)
    sizes = torch.tensor([lv.shape[-2:] for lv in levels], device=dev)  # (L, 2) rows, cols
    offsets = torch.tensor([0] + [lv.numel() for lv in levels], device=dev).cumsum(0)[:-1]
    top = len(levels) - 1 if max_level is None else min(len(levels) - 1, int(max_level))
    n_flat = normal.permute(0, 2, 3, 1).reshape(-1, 3).to(dt)
    points = backproject(torch.where(torch.isfinite(clean), clean, torch.zeros_like(clean)), fov_x).reshape(-1, 3)
    plane_c = (n_flat * points).sum(-1)  # each pixel's facet: n . x = c

    finite = clean[torch.isfinite(clean)]
    far = 4.0 * (float(finite.max()) if finite.numel() else 10.0) + float(o.norm(dim=-1).max()) if N else 1.0
    cam = torch.tensor([float(focal(fov_x, W)), W / 2, H / 2], dtype=dt, device=dev)
    st, small, s, ok = _kernel(_segments, compiled)(o, d, torch.tensor(far, dtype=dt, device=dev), cam, H, W)

    # Working set: one packed float state per ray plus its ray id and level, compacted as rays finish.
    # Depths are compared as inverse depths (1/z is affine along the screen segment), against a pyramid
    # of max(1/z) = 1/min(z), so a step needs no division.
    inv_levels = torch.cat([(1.0 / lv).reshape(-1) for lv in levels])  # inf -> 0: never "behind"
    # per level: rows, cols, offset into inv_levels -- one gather per step instead of three
    level_table = torch.cat([sizes, offsets[:, None]], 1).int()
    take = torch.index_select
    ids = torch.nonzero(ok).squeeze(-1)
    st, s, flat_small = take(st, 0, ids), take(s, 0, ids), take(small, 0, ids)
    lvl = torch.zeros(len(ids), dtype=torch.int32, device=dev)
    b_of = take(bidx, 0, ids).int()
    live = s < 1
    ray = take(torch.cat([o, d], 1), 0, ids)
    # per ray: hit row, col (-1 = none) and gap; working rays' results are copied out when they leave
    out = torch.zeros(N, 3, dtype=dt, device=dev)
    out[:, :2] = -1.0
    res = take(out, 0, ids)
    scene = (level_table, inv_levels, n_flat, plane_c, cam, H, W)
    step = _kernel(_step, compiled)

    for it in range(max_steps):
        # reading the live count waits for the device and (compiled) re-enters Python guards: do it every
        # few steps only; steps on finished rays change nothing
        if it % SYNC_EVERY == 0:
            n_live = int(live.sum())
            if n_live == 0:
                break
            if n_live < 0.75 * live.numel():  # compact by one shared index once enough rays have finished
                done = torch.nonzero(~live).squeeze(-1)
                out.index_copy_(0, take(ids, 0, done), take(res, 0, done))
                keep = torch.nonzero(live).squeeze(-1)
                ids, st, s, flat_small, ray, lvl, b_of, live, res = (
                    take(x, 0, keep) for x in (ids, st, s, flat_small, ray, lvl, b_of, live, res)
                )
        s, lvl, live, res = step(st, s, flat_small, lvl, ray, b_of, live, res, scene, top)
    out.index_copy_(0, ids, res)
    return out[:, :2].long(), out[:, 0] >= 0, out[:, 2].contiguous()
