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
in tensor operations; finished rays are masked out and leave the working set once a quarter of it has
finished (no per-ray Python, little work on finished rays). Results equal a pixel-by-pixel march with
the same hit rule. No gradients flow (the outputs are indices, a flag and a gap used as a confidence).
"""

from __future__ import annotations

import math

import torch

from pipeline.ops.camera import backproject, project

NEAR = 1e-3  # metres: rays are clipped to z-depth >= NEAR


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
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """March rays across depth maps.

    depth (B, H, W) z-depth in metres (0 or non-finite = no surface, e.g. sky); normal (B, 3, H, W) view
    space; fov_x degrees; origin, direction (N, 3) view space; batch_index (N,) long (None = image 0).
    Returns pixel (N, 2) long (row, col) of the hit (-1 on misses), hit (N,) bool and gap (N,) metres
    (ray depth minus surface depth on entering the hit pixel, >= 0; 0 on misses). Rays that leave the
    image, reach the near plane or never pass behind a facing surface are misses. max_level caps the
    pyramid level a ray may skip at (0 = a plain pixel-by-pixel march, for comparison); the hits do not
    depend on it."""
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
    level_table = torch.cat([sizes, offsets[:, None], (2 ** torch.arange(len(levels), device=dev))[:, None]], 1)
    small = D.abs() <= 1e-12
    inv_d = 1.0 / torch.where(small, torch.ones_like(D), D)
    ids = torch.nonzero(ok).squeeze(-1)
    # columns: P0x P0y Dx Dy 1/Dx 1/Dy inv0 (inv1 - inv0) s
    st = torch.cat([P0, D, inv_d, inv0[:, None], (inv1 - inv0)[:, None], torch.zeros(N, 1, dtype=dt, device=dev)], 1)[
        ids
    ]
    flat_small = small[ids]
    lvl = torch.zeros(len(ids), dtype=torch.long, device=dev)

    def step_geometry(st, flat_small, scale):
        """Cell (A, 2) entered at level lvl from the position at s, and the s where the ray leaves it. On a
        boundary the cell ahead is taken per axis (floor moving +, ceil - 1 moving -): a forward nudge would
        vanish below float32 resolution on the slow axis and stall the ray. Every exit lies at least 1e-6
        ahead, so the march always progresses."""
        scale = scale.unsqueeze(-1)
        p0, dd, idd, s = st[:, 0:2], st[:, 2:4], st[:, 4:6], st[:, 8]
        q = torch.addcmul(p0, s.unsqueeze(-1), dd) / scale
        neg = dd < 0
        cell = torch.where(neg, torch.ceil(q) - 1, torch.floor(q))
        t_axis = ((cell + (~neg).to(dt)) * scale - p0) * idd
        t_axis = t_axis.masked_fill(flat_small, math.inf)
        return cell.long(), torch.maximum(t_axis.amin(-1), s + 1e-6).clamp(max=1.0)

    # start just past the origin's own pixel (its surface is the ray's origin, not a hit); a ray whose
    # origin projects outside the image starts where it enters it
    _, s_first = step_geometry(st, flat_small, torch.ones(len(ids), dtype=dt, device=dev))
    st[:, 8] = torch.where(starts_inside[ids], s_first, torch.zeros_like(s_first))
    b_of = bidx[ids]
    live = st[:, 8] < 1
    level_scale = level_table[:, 3].to(dt)
    take = torch.index_select  # plain row gathers: leaner than advanced indexing on CPU
    for _ in range(max_steps):
        n_live = int(live.sum())
        if n_live == 0:
            break
        if n_live < 0.75 * live.numel():  # compact by one shared index, only once enough rays have finished
            keep = torch.nonzero(live).squeeze(-1)
            ids, st, flat_small = take(ids, 0, keep), take(st, 0, keep), take(flat_small, 0, keep)
            lvl, b_of, live = take(lvl, 0, keep), take(b_of, 0, keep), take(live, 0, keep)
        tab = take(level_table, 0, lvl)
        rows, cols = tab[:, 0], tab[:, 1]
        cell, s_out = step_geometry(st, flat_small, take(level_scale, 0, lvl))
        cx = torch.minimum(cell[:, 0].clamp(min=0), cols - 1)
        cy = torch.minimum(cell[:, 1].clamp(min=0), rows - 1)
        iz_cell = take(inv_levels, 0, tab[:, 2] + (b_of * rows + cy) * cols + cx)
        iz_in = torch.addcmul(st[:, 6], st[:, 8], st[:, 7])
        iz_out = torch.addcmul(st[:, 6], s_out, st[:, 7])
        behind = torch.minimum(iz_in, iz_out) <= iz_cell  # the ray's far end reaches the nearest surface
        leaf = behind & (lvl == 0) & live
        li = torch.nonzero(leaf).squeeze(-1)
        done = torch.zeros_like(leaf)
        if li.numel():
            cy_l, cx_l = take(cy, 0, li), take(cx, 0, li)
            pix_flat = (take(b_of, 0, li) * H + cy_l) * W + cx_l
            rid = take(ids, 0, li)
            n_l, d_l = take(n_flat, 0, pix_flat), take(d, 0, rid)
            nd = (n_l * d_l).sum(-1)
            # Where does the ray cross the pixel's facet (the plane through its centre point, with its
            # normal)? Ahead of this pixel: the ray only grazes the depth map's staircase and goes on.
            o_l = take(o, 0, rid)
            t_star = ((take(points, 0, pix_flat) - o_l) * n_l).sum(-1) / torch.where(nd < 0, nd, -torch.ones_like(nd))
            q_star, _ = proj(o_l + t_star.clamp(min=0).unsqueeze(-1) * d_l)
            st_l = take(st, 0, li)
            len2 = (st_l[:, 2:4] * st_l[:, 2:4]).sum(-1).clamp(min=1e-12)
            s_star = ((q_star - st_l[:, 0:2]) * st_l[:, 2:4]).sum(-1) / len2  # crossing's segment parameter
            beyond = (t_star > 0) & (s_star > take(s_out, 0, li))
            crossing = (t_star > 0) & ~beyond & (s_star >= st_l[:, 8])
            facing = (nd < 0) & ~beyond
            fi = li[facing]
            done[fi] = True
            k = ids[fi]
            hit[k] = True
            pixel[k, 0], pixel[k, 1] = cy_l[facing], cx_l[facing]
            behind_gap = (1.0 / torch.maximum(iz_in[fi], iz_out[fi]) - 1.0 / iz_cell[fi]).clamp(min=0)
            gap[k] = torch.where(crossing[facing], torch.zeros_like(behind_gap), behind_gap)
        advance = ~behind | (leaf & ~done)
        st[:, 8] = torch.where(advance, s_out, st[:, 8])
        # clear: one level up (to skip more next time); blocked above the pixel level: one level down
        lvl = (lvl + (~behind).long() - (behind & (lvl > 0)).long()).clamp(max=top)
        live = live & ~done & (st[:, 8] < 1)
    return pixel, hit, gap
