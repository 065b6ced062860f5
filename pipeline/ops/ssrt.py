"""Screen-space ray tracing against z-depth maps with a hierarchical min-depth (Hi-Z) traversal.

A ray p + t w (view space) is clipped to the near plane and to the image, projected to a 2-D segment
P(s) = P0 + s (P1 - P0), s in [0, 1], along which its z-depth is perspective-correct:
1/z(s) = (1 - s)/z0 + s/z1. The march visits the pixels the segment crosses, in order, and reports
the first one where the ray *passes behind* the surface (its depth over the pixel reaches the depth map)
while *facing* it (n . w < 0) and does not cross the pixel's facet (the plane through the pixel's centre
point with its normal) only further ahead: a depth map is a staircase, and a ray grazing a plane dips
behind its steps long before it reaches the plane. The gap is 0 when the ray crosses the facet inside
the pixel (a confident hit); otherwise it is how far behind the surface the ray already was when it
entered the pixel, large when it slipped behind a foreground object's silhouette (DESIGN.md:
u = tanh(k gap) then hands the ray to the out-of-view branch).

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

from pipeline.ops.camera import backproject, project

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


def _step(st, s, flat_small, lvl, ray, b_of, live, res, scene, top: int, fov_x: float):
    """One traversal step for A working rays, elementwise apart from gathers (so it fuses when compiled).

    st (A, 8) per-ray segment constants (see `trace`), s (A,) position on the segment, flat_small (A, 2)
    degenerate axes, lvl (A,) level, ray (A, 6) view-space origin and unit direction, b_of (A,) image,
    live (A,) unfinished, res (A, 3) hit row, col (-1 before a hit) and gap; scene is (level_table,
    level_scale, inv_levels, n_flat, points, H, W). Returns the new s, level, live flags and res."""
    level_table, level_scale, inv_levels, n_flat, points, H, W = scene
    take = torch.index_select  # plain row gathers: leaner than advanced indexing on CPU
    tab = take(level_table, 0, lvl)
    rows, cols = tab[:, 0], tab[:, 1]
    cell, s_out = _step_geometry(st, s, flat_small, take(level_scale, 0, lvl))
    cx = torch.minimum(cell[:, 0].clamp(min=0), cols - 1)
    cy = torch.minimum(cell[:, 1].clamp(min=0), rows - 1)
    iz_cell = take(inv_levels, 0, tab[:, 2] + (b_of * rows + cy) * cols + cx)
    iz_in = torch.addcmul(st[:, 6], s, st[:, 7])
    iz_out = torch.addcmul(st[:, 6], s_out, st[:, 7])
    behind = torch.minimum(iz_in, iz_out) <= iz_cell  # the ray's far end reaches the nearest surface
    leaf = behind & (lvl == 0) & live
    # At a pixel: does the ray face the surface, and where does it cross the pixel's facet (the plane
    # through its centre point, with its normal)? Ahead of this pixel: the ray only grazes the depth
    # map's staircase and goes on. Inside it: a confident hit (gap 0). Before it: the ray slipped behind.
    pix_flat = ((b_of * H + cy) * W + cx).where(leaf, torch.zeros_like(cx))
    o, d = ray[:, 0:3], ray[:, 3:6]
    n = take(n_flat, 0, pix_flat)
    nd = (n * d).sum(-1)
    t_star = ((take(points, 0, pix_flat) - o) * n).sum(-1) / torch.where(nd < 0, nd, -torch.ones_like(nd))
    x = o + t_star.clamp(min=0).unsqueeze(-1) * d
    q, _ = project(torch.cat([x[:, :2], x[:, 2:].clamp(max=-NEAR)], -1), fov_x, H, W)
    dd = st[:, 2:4]
    s_star = ((q - st[:, 0:2]) * dd).sum(-1) / (dd * dd).sum(-1).clamp(min=1e-12)  # the crossing's s
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


_COMPILED: dict[str, object] = {}


def _step_kernel(compiled: bool):
    if not compiled:
        return _step
    if "step" not in _COMPILED:  # one fused kernel; the working set shrinks as rays finish: dynamic shapes
        _COMPILED["step"] = torch.compile(_step, dynamic=True)
    return _COMPILED["step"]


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
    depend on it. compiled=True runs each step as one fused torch.compile kernel (about 2.5x faster on
    CPU; the first call compiles for tens of seconds and needs a C++ compiler, or Triton on CUDA)."""
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

    # --- clip the 3-D ray: in front of the near plane, within a far distance beyond every surface ----
    finite = clean[torch.isfinite(clean)]
    far = 4.0 * (float(finite.max()) if finite.numel() else 10.0) + float(o.norm(dim=-1).max()) if N else 1.0
    t_end = torch.full((N,), far, dtype=dt, device=dev)
    toward = d[:, 2] > 0  # moving towards the camera plane: stop at z = -NEAR
    t_near = (-NEAR - o[:, 2]) / torch.where(toward, d[:, 2], torch.ones_like(d[:, 2]))
    t_end = torch.where(toward, torch.minimum(t_end, t_near), t_end)
    ok = (o[:, 2] < -NEAR) & (t_end > 0)
    e = o + t_end.unsqueeze(-1) * d

    def proj(p):  # rays that start behind the near plane are dropped by `ok`; keep their numbers finite
        return project(torch.cat([p[:, :2], p[:, 2:].clamp(max=-NEAR)], -1), fov_x, H, W)

    P0, z0 = proj(o)
    P1, z1 = proj(e)
    D = P1 - P0
    # --- clip the 2-D segment to the image rectangle [0, W] x [0, H] ----------------------------------
    lo, hi = torch.zeros(N, dtype=dt, device=dev), torch.ones(N, dtype=dt, device=dev)
    for axis, size in ((0, W), (1, H)):
        dd = D[:, axis]
        safe = torch.where(dd.abs() > 1e-12, dd, torch.ones_like(dd))
        a, b = (0 - P0[:, axis]) / safe, (size - P0[:, axis]) / safe
        s_min, s_max = torch.minimum(a, b), torch.maximum(a, b)
        inside = (P0[:, axis] >= 0) & (P0[:, axis] <= size)
        lo = torch.where(dd.abs() > 1e-12, torch.maximum(lo, s_min), lo)
        hi = torch.where(dd.abs() > 1e-12, torch.minimum(hi, s_max), hi)
        ok &= (dd.abs() > 1e-12) | inside
    ok &= lo < hi
    # re-parametrise over the clipped part: a near-plane clip can put P1 ~1e6 px away, where float32 could
    # no longer resolve one pixel step; within the image every quantity stays well conditioned
    inv0, inv1 = 1.0 / z0, 1.0 / z1
    lo_c, hi_c = lo.clamp(0, 1), hi.clamp(0, 1)
    inv0, inv1 = (1 - lo_c) * inv0 + lo_c * inv1, (1 - hi_c) * inv0 + hi_c * inv1
    P0, P1 = P0 + lo_c.unsqueeze(-1) * D, P0 + hi_c.unsqueeze(-1) * D
    D = P1 - P0
    starts_inside = lo <= 0

    pixel = torch.full((N, 2), -1, dtype=torch.long, device=dev)
    hit = torch.zeros(N, dtype=torch.bool, device=dev)
    gap = torch.zeros(N, dtype=dt, device=dev)

    # Working set: one packed float state per ray plus its ray id and level, compacted as rays finish.
    # Depths are compared as inverse depths (1/z is affine along the screen segment), against a pyramid
    # of max(1/z) = 1/min(z), so a step needs no division.
    inv_levels = torch.cat([(1.0 / lv).reshape(-1) for lv in levels])  # inf -> 0: never "behind"
    # per level: rows, cols, offset into inv_levels, 2^level -- one gather per step instead of four
    level_table = torch.cat([sizes, offsets[:, None], (2 ** torch.arange(len(levels), device=dev))[:, None]], 1).int()
    small = D.abs() <= 1e-12
    inv_d = 1.0 / torch.where(small, torch.ones_like(D), D)
    ids = torch.nonzero(ok).squeeze(-1)
    # per-ray constants, columns: P0x P0y Dx Dy 1/Dx 1/Dy inv0 (inv1 - inv0); the position s is separate
    st = torch.cat([P0, D, inv_d, inv0[:, None], (inv1 - inv0)[:, None]], 1)[ids]
    flat_small = small[ids]
    lvl = torch.zeros(len(ids), dtype=torch.int32, device=dev)

    # start just past the origin's own pixel (its surface is the ray's origin, not a hit); a ray whose
    # origin projects outside the image starts where it enters it
    _, s_first = _step_geometry(
        st, torch.zeros(len(ids), dtype=dt, device=dev), flat_small, torch.ones(len(ids), dtype=dt, device=dev)
    )
    s = torch.where(starts_inside[ids], s_first, torch.zeros_like(s_first))
    b_of = bidx[ids].int()
    live = s < 1
    ray = torch.cat([o, d], 1)[ids]
    # per working ray: hit row, col (-1 = none yet) and gap, written out when the ray leaves the working set
    res = torch.cat(
        [torch.full((len(ids), 2), -1.0, dtype=dt, device=dev), torch.zeros(len(ids), 1, dtype=dt, device=dev)], 1
    )
    scene = (level_table, level_table[:, 3].to(dt), inv_levels, n_flat, points, H, W)
    step = _step_kernel(compiled)

    def write_out(rows):
        k, r = ids[rows], res[rows]
        pixel[k], hit[k], gap[k] = r[:, :2].long(), r[:, 0] >= 0, r[:, 2]

    take = torch.index_select
    for it in range(max_steps):
        # reading the live count waits for the device and (compiled) re-enters Python guards: do it every
        # few steps only; steps on finished rays change nothing
        if it % SYNC_EVERY == 0:
            n_live = int(live.sum())
            if n_live == 0:
                break
            if n_live < 0.75 * live.numel():  # compact by one shared index once enough rays have finished
                write_out(~live)
                keep = torch.nonzero(live).squeeze(-1)
                ids, st, s, flat_small, ray, lvl, b_of, live, res = (
                    take(x, 0, keep) for x in (ids, st, s, flat_small, ray, lvl, b_of, live, res)
                )
        s, lvl, live, res = step(st, s, flat_small, lvl, ray, b_of, live, res, scene, top, fov_x)
    write_out(torch.ones_like(live))
    return pixel, hit, gap
