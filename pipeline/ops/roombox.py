"""An indoor room as a box seen from the camera (docs/design.md, section 5, the `roombox` out-of-view branch).

A box is (rotation, lo, hi): rotation (B, 3, 3) whose columns are the box's axes in view space, lo and hi
(B, 3) its faces in box coordinates q = rotation^T x (metres; x a view-space point, so the camera sits at
q = 0 inside the box). The frame is canonical: the box axis closest to each view axis (x right, y up,
z backwards) is that axis, so face k means the same side of the room seen from the camera in every view
(`FACES`); a room's box is symmetric under those relabellings, so nothing is lost.

Face textures are (T, T) maps over each face; a face's texel coordinates (s, t) in [-1, 1]^2 run along the
two other axes in increasing order (face x: (y, z), face y: (x, z), face z: (x, y)), -1 at lo, +1 at hi.
"""

from __future__ import annotations

import itertools

import torch

from pipeline.ops.camera import backproject_views, pixel_directions

# face index = 2 * axis + (0: the lo side, 1: the hi side); as seen from the camera, for a level view
FACES = ("left", "right", "floor", "ceiling", "front", "behind")
OTHER_AXES = ((1, 2), (0, 2), (0, 1))  # the texel axes (s, t) of the faces of each axis
_PERMUTATIONS = torch.tensor(list(itertools.permutations(range(3))))
_SIGNS = torch.tensor(list(itertools.product((-1.0, 1.0), repeat=3)))


def canonical_frame(rotation: torch.Tensor) -> torch.Tensor:
    """Relabel and flip the columns of rotations (B, 3, 3) (a room's three axes, in any order and sign)
    so the result is the proper rotation closest to the identity (largest trace): the canonical frame."""
    perms = _PERMUTATIONS.to(rotation.device)
    signs = _SIGNS.to(rotation.device, rotation.dtype)
    cand = rotation[:, :, perms]  # (B, 3, 6, 3): columns permuted
    cand = cand.unsqueeze(3) * signs.view(1, 1, 1, 8, 3)  # (B, 3, 6, 8, 3)
    cand = cand.permute(0, 2, 3, 1, 4).reshape(rotation.shape[0], 48, 3, 3)
    proper = torch.linalg.det(cand) > 0
    trace = cand.diagonal(dim1=-2, dim2=-1).sum(-1)
    best = torch.where(proper, trace, torch.full_like(trace, -10.0)).argmax(1)
    return cand[torch.arange(len(best)), best]


def rotation_from_normals(normal: torch.Tensor, valid: torch.Tensor, iterations: int = 6, min_cos: float = 0.9):
    """The room's frame (B, 3, 3) from view-space normals (B, 3, H, W) at valid pixels (B, H, W).

    Manhattan alignment: each normal is assigned to the nearest signed axis of the current frame, and the
    frame is refitted to those pairs (the orthogonal Procrustes solution, by SVD), starting from the
    camera's own frame; normals further than acos(min_cos) from every axis (curved objects) do not vote.
    A view with no usable normal keeps the camera frame."""
    B = normal.shape[0]
    n = normal.permute(0, 2, 3, 1).reshape(B, -1, 3)
    n = n / n.norm(dim=-1, keepdim=True).clamp(min=1e-6)
    w0 = (valid.reshape(B, -1) & torch.isfinite(n).all(-1)).to(n.dtype)
    n = torch.nan_to_num(n)
    eye = torch.eye(3, dtype=n.dtype, device=n.device)
    rot = eye.expand(B, 3, 3).clone()
    for it in range(iterations):
        c = n @ rot  # (B, P, 3): normals in box coordinates
        best = c.abs().argmax(-1)
        cos = c.abs().gather(-1, best[..., None])[..., 0]
        sign = torch.sign(c.gather(-1, best[..., None]))[..., 0]
        w = w0 * (cos >= (min_cos if it > 0 else 0.5)).to(n.dtype)
        target = eye[best] * sign[..., None]  # (B, P, 3): the box-frame axis each normal votes for
        m = (w[..., None, None] * n[..., :, None] * target[..., None, :]).sum(1)  # (B, 3, 3) = sum n a^T
        u, _s, vh = torch.linalg.svd(m)
        d = torch.sign(torch.linalg.det(u @ vh))
        fix = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
        fitted = u @ fix @ vh
        enough = (w.sum(1) >= 3)[:, None, None]
        rot = canonical_frame(torch.where(enough, fitted, rot))
    return rot


def extents_from_points(
    points: torch.Tensor,
    valid: torch.Tensor,
    rotation: torch.Tensor,
    normal: torch.Tensor,
    quantile: float = 0.98,
    unseen_fraction=(0.6, 1.0, 0.25),
    seen_share: float = 0.01,
    margin: float = 0.3,
    min_cos: float = 0.9,
    return_seen: bool = False,
):
    """Box faces lo, hi (B, 3) in box coordinates from view-space points (B, H, W, 3) and normals
    (B, 3, H, W) at valid pixels (B, H, W).

    Walls are the outermost surfaces: a face sits at the `quantile` of the points' coordinates towards it
    (a few stray depths ignored), if it is seen there: at least `seen_share` of the points lie within
    0.25 m of that position with normals facing into the room (within acos(min_cos)). An unseen face (the
    wall behind the camera, always; a side wall outside the field of view) is put at `unseen_fraction`
    (per axis x, y, z) of the opposite face's distance from the camera, never nearer than the furthest
    point towards it nor than `margin` metres (the camera is inside the room). The default fractions are
    the generator's rooms' medians (`bench.roombox_floor`): side walls 0.6, ceiling 1.0, behind 0.25.
    return_seen: also return which faces were seen, (B, 3) booleans for lo and for hi."""
    B = points.shape[0]
    q = points.reshape(B, -1, 3) @ rotation  # (B, P, 3)
    n = normal.permute(0, 2, 3, 1).reshape(B, -1, 3).to(q.dtype) @ rotation
    v = valid.reshape(B, -1) & torch.isfinite(q).all(-1) & torch.isfinite(n).all(-1)
    frac = torch.as_tensor(unseen_fraction, dtype=q.dtype, device=q.device).expand(3)
    lo, hi, seen_lo, seen_hi = [], [], [], []
    for b in range(B):
        qb, nb = q[b][v[b]], n[b][v[b]]
        if len(qb) < 8:
            lo.append(torch.full((3,), -3.0, dtype=q.dtype, device=q.device))
            hi.append(torch.full((3,), 3.0, dtype=q.dtype, device=q.device))
            seen_lo.append(torch.zeros(3, dtype=torch.bool, device=q.device))
            seen_hi.append(torch.zeros(3, dtype=torch.bool, device=q.device))
            continue
        lo_b = torch.quantile(qb, 1 - quantile, dim=0).clamp(max=-margin)
        hi_b = torch.quantile(qb, quantile, dim=0).clamp(min=margin)
        # seen: enough points at the extreme whose normals face into the room (+axis on the lo face)
        share_lo = (((qb - lo_b).abs() < 0.25) & (nb >= min_cos)).to(q.dtype).mean(0)
        share_hi = (((qb - hi_b).abs() < 0.25) & (nb <= -min_cos)).to(q.dtype).mean(0)
        far_lo = torch.minimum(lo_b, -frac * hi_b)
        far_hi = torch.maximum(hi_b, -frac * lo_b)
        seen_lo.append(share_lo >= seen_share)
        seen_hi.append(share_hi >= seen_share)
        lo.append(torch.where(seen_lo[-1], lo_b, far_lo))
        hi.append(torch.where(seen_hi[-1], hi_b, far_hi))
    if return_seen:
        return torch.stack(lo), torch.stack(hi), torch.stack(seen_lo), torch.stack(seen_hi)
    return torch.stack(lo), torch.stack(hi)


def exit_face(q: torch.Tensor, d: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor):
    """Where rays q + t d (N, 3) in box coordinates, started inside the box lo, hi (N, 3), leave it:
    (face index (N,) long, texel coordinates (N, 2) in [-1, 1], distance t (N,)). Origins outside the box
    are first moved onto its nearest inside point."""
    span = (hi - lo).clamp(min=1e-4)
    q = torch.minimum(torch.maximum(q, lo + 1e-4 * span), hi - 1e-4 * span)
    safe = torch.where(d.abs() > 1e-9, d, torch.full_like(d, 1e-9))
    t_axis = (torch.where(safe > 0, hi, lo) - q) / safe  # (N, 3) distance to each axis's far wall
    t, axis = t_axis.min(-1)
    face = 2 * axis + (safe.gather(-1, axis[:, None])[:, 0] > 0).long()
    point = q + t[:, None] * d
    other = torch.tensor(OTHER_AXES, device=q.device)[axis]  # (N, 2)
    lo_st, span_st = lo.gather(-1, other), span.gather(-1, other)
    st = (2 * (point.gather(-1, other) - lo_st) / span_st - 1).clamp(-1, 1)
    return face, st, t


def texel_lookup(textures: torch.Tensor, index: torch.Tensor, st: torch.Tensor) -> torch.Tensor:
    """Bilinear values (N, C) of maps textures (K, C, T, T) (row = t, column = s) at map index (N,) and
    coordinates st (N, 2) in [-1, 1] (texel centres at (i + 0.5) / T * 2 - 1, clamped at the borders)."""
    K, C, T, _ = textures.shape
    x = ((st + 1) * (T / 2) - 0.5).clamp(0, T - 1)  # continuous texel coordinates (s, t)
    x0 = x.floor().clamp(max=T - 2).long() if T > 1 else x.floor().long()
    f = x - x0.to(x.dtype)
    x1 = (x0 + 1).clamp(max=T - 1)
    flat = textures.permute(0, 2, 3, 1).reshape(K * T * T, C)
    base = index * T * T

    def at(s, t):
        return flat[base + t * T + s]

    fs, ft = f[:, :1], f[:, 1:]
    top = at(x0[:, 0], x0[:, 1]) * (1 - fs) + at(x1[:, 0], x0[:, 1]) * fs
    bottom = at(x0[:, 0], x1[:, 1]) * (1 - fs) + at(x1[:, 0], x1[:, 1]) * fs
    return top * (1 - ft) + bottom * ft


def observed_textures(
    image: torch.Tensor,
    depth: torch.Tensor,
    fov_x,
    rotation: torch.Tensor,
    lo: torch.Tensor,
    hi: torch.Tensor,
    size: int,
    normal: torch.Tensor | None = None,
    plane_tolerance: float = 0.15,
    min_cos: float = 0.7,
):
    """What the camera saw of each face: image (B, 3, H, W) splatted onto the six faces' (size, size)
    texels -> (mean radiance (B, 6, 3, size, size), pixel count (B, 6, 1, size, size)).

    A pixel with a depth lands on a face when its point lies within `plane_tolerance` metres of the
    face's plane and (normal given) its normal faces into the room within acos(min_cos) (furniture in
    front of a wall does not); a pixel without a depth (0 or non-finite: a lamp, a window, the sky) is
    followed along its camera ray to the face it leaves the box through. Each pixel counts once, in its
    nearest texel."""
    B, _, H, W = image.shape
    dt = image.dtype
    has_depth = torch.isfinite(depth) & (depth > 0)
    pts = backproject_views(torch.where(has_depth, depth, torch.ones_like(depth)), fov_x)  # (B, H, W, 3)
    if torch.is_tensor(fov_x) and fov_x.ndim > 0:
        dirs = torch.stack([pixel_directions(H, W, float(f), image.device, dt) for f in fov_x])
    else:
        dirs = pixel_directions(H, W, float(fov_x), image.device, dt).expand(B, H, W, 3)
    rot = rotation.to(dt)
    q = pts.reshape(B, -1, 3).to(dt) @ rot  # (B, P, 3)
    d = dirs.reshape(B, -1, 3) @ rot
    P = q.shape[1]
    lo_p, hi_p = lo[:, None].expand(B, P, 3).to(dt), hi[:, None].expand(B, P, 3).to(dt)
    # pixels without depth: where the camera ray (from the origin) leaves the box
    face_r, st_r, _ = exit_face(
        torch.zeros_like(d).reshape(-1, 3), d.reshape(-1, 3), lo_p.reshape(-1, 3), hi_p.reshape(-1, 3)
    )
    # pixels with depth: the face whose plane the point is on (nearest plane within the tolerance)
    dist = torch.cat([(q - lo_p).abs(), (hi_p - q).abs()], -1)[..., [0, 3, 1, 4, 2, 5]]  # (B, P, 6) by face
    if normal is not None:
        n = normal.permute(0, 2, 3, 1).reshape(B, -1, 3).to(dt) @ rot
        inward = torch.stack([n[..., 0], -n[..., 0], n[..., 1], -n[..., 1], n[..., 2], -n[..., 2]], -1)
        dist = torch.where(inward >= min_cos, dist, torch.full_like(dist, float("inf")))
    near, face_d = dist.min(-1)
    on_plane = has_depth.reshape(B, -1) & (near <= plane_tolerance)
    axis = face_d // 2
    other = torch.tensor(OTHER_AXES, device=q.device)[axis]  # (B, P, 2)
    span = (hi_p - lo_p).clamp(min=1e-4)
    st_d = (2 * (q.gather(-1, other) - lo_p.gather(-1, other)) / span.gather(-1, other) - 1).clamp(-1, 1)
    no_depth = ~has_depth.reshape(B, -1)
    face = torch.where(no_depth, face_r.view(B, P), face_d)
    st = torch.where(no_depth[..., None], st_r.view(B, P, 2), st_d)
    use = (no_depth | on_plane) & torch.isfinite(image).all(1).reshape(B, -1)
    texel = ((st + 1) * (size / 2)).long().clamp(0, size - 1)
    flat = (torch.arange(B, device=q.device)[:, None] * 6 + face) * size * size + texel[..., 1] * size + texel[..., 0]
    flat, use = flat.reshape(-1), use.reshape(-1)
    values = image.permute(0, 2, 3, 1).reshape(-1, 3)
    total = image.new_zeros(B * 6 * size * size, 3).index_add_(0, flat[use], values[use])
    count = image.new_zeros(B * 6 * size * size).index_add_(0, flat[use], torch.ones_like(flat[use], dtype=dt))
    mean = total / count.clamp(min=1)[:, None]
    mean = mean.view(B, 6, size, size, 3).permute(0, 1, 4, 2, 3)
    return mean, count.view(B, 6, 1, size, size)


def box_from_room(size, world_from_view) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The true box of a generated room (`size` W, H, D metres: x in [-W/2, W/2], y in [0, H], z in
    [-D/2, D/2]) seen by a camera with 4x4 `world_from_view`, in the canonical frame: (rotation (3, 3),
    lo (3,), hi (3,)), float64."""
    m = torch.as_tensor(world_from_view, dtype=torch.float64)
    view_from_world = m[:3, :3].T
    rot = canonical_frame(view_from_world[None])[0]  # columns: room axes in view space
    w, h, d = (float(v) for v in size)
    corners = torch.tensor(list(itertools.product((-w / 2, w / 2), (0.0, h), (-d / 2, d / 2))), dtype=torch.float64)
    q = ((corners - m[:3, 3]) @ view_from_world.T) @ rot  # corners in box coordinates
    return rot, q.amin(0), q.amax(0)
