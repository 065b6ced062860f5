"""Analytic test scenes with exact ray casting: a box room with box furniture, in view space.

Used to render exact depth/normal maps and exact first hits, against which screen-space ray tracing is
scored. The camera sits at the origin looking down -z (OpenGL view space, docs/design.md, section 3).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.ops.camera import pixel_directions


@dataclass
class BoxRoom:
    """room: (2, 3) min/max corners of the room (rays start inside); boxes: (K, 2, 3) furniture AABBs."""

    room: torch.Tensor
    boxes: torch.Tensor

    @staticmethod
    def default(dtype=torch.float64) -> BoxRoom:
        room = torch.tensor([[-2.0, -1.4, -5.5], [2.0, 1.4, 0.5]], dtype=dtype)
        boxes = torch.tensor(
            [
                [[-1.6, -1.4, -4.0], [-0.6, -0.65, -3.0]],  # table-height block
                [[0.8, -1.4, -5.5], [1.9, 0.6, -4.9]],  # cabinet against the back wall
                [[-0.3, -1.4, -2.4], [0.3, -1.0, -1.8]],  # low box in the foreground
                [[1.2, -1.4, -2.8], [1.9, -0.9, -1.6]],  # sofa-like block by the right wall
                [[-1.95, -0.2, -2.5], [-1.7, 0.8, -1.5]],  # shelf on the left wall
            ],
            dtype=dtype,
        )
        return BoxRoom(room, boxes)

    def cast(self, origin: torch.Tensor, direction: torch.Tensor, eps: float = 1e-9):
        """Exact first hit of rays (N, 3) from inside the room: t (N,), unit normal facing the ray (N, 3)."""
        d = torch.nn.functional.normalize(direction, dim=-1)
        inv = 1.0 / torch.where(d.abs() > 1e-15, d, torch.full_like(d, 1e-15))
        # room: the ray leaves through the nearest far slab
        t_far = torch.maximum((self.room[0] - origin) * inv, (self.room[1] - origin) * inv)
        t_best, axis = t_far.min(-1)
        normal = torch.zeros_like(d)
        normal.scatter_(1, axis[:, None], -torch.sign(d.gather(1, axis[:, None])))
        for box in self.boxes:
            t1, t2 = (box[0] - origin) * inv, (box[1] - origin) * inv
            tn, tf = torch.minimum(t1, t2), torch.maximum(t1, t2)
            t_in, ax = tn.max(-1)
            enter = (t_in <= tf.min(-1).values) & (t_in > eps) & (t_in < t_best)
            n_box = torch.zeros_like(d)
            n_box.scatter_(1, ax[:, None], -torch.sign(d.gather(1, ax[:, None])))
            t_best = torch.where(enter, t_in, t_best)
            normal = torch.where(enter[:, None], n_box, normal)
        return t_best, normal

    def render(self, height: int, width: int, fov_x: float):
        """Exact z-depth (1, H, W) and normals (1, 3, H, W) at pixel centres."""
        dirs = pixel_directions(height, width, fov_x, dtype=self.room.dtype).reshape(-1, 3)
        unit = torch.nn.functional.normalize(dirs, dim=-1)
        t, n = self.cast(torch.zeros_like(unit), unit)
        z = t * -unit[:, 2]
        return z.reshape(1, height, width), n.reshape(height, width, 3).permute(2, 0, 1)[None]


def ssrt_rays(depth: torch.Tensor, normal: torch.Tensor, fov_x: float, rays_per_pixel: int, generator: torch.Generator):
    """Cosine-distributed rays (origin, direction, normal at origin) from every valid pixel's surface point."""
    from pipeline.ops.camera import backproject
    from pipeline.ops.sampling import sample_cosine

    pts = backproject(depth, fov_x)[0].reshape(-1, 3)
    nrm = normal[0].permute(1, 2, 0).reshape(-1, 3)
    ok = torch.isfinite(pts).all(-1) & (depth[0].reshape(-1) > 0)
    pts, nrm = pts[ok], nrm[ok]
    o = (pts + 1e-4 * nrm).repeat_interleave(rays_per_pixel, 0)
    n = nrm.repeat_interleave(rays_per_pixel, 0)
    wi, _ = sample_cosine(torch.rand(len(o), 3, generator=generator, dtype=depth.dtype), n)
    return o, wi


def score_ssrt(
    scene: BoxRoom,
    depth,
    normal,
    fov_x: float,
    origin,
    direction,
    pixel,
    hit,
    gap,
    k: float = 10.0,
    tolerance_px: int = 2,
) -> dict[str, float]:
    """Score screen-space hits against exact first hits (docs/design.md, section 5 / the render-core benchmark):
    recall over rays whose true hit is visible on screen (same plane as the pixel that shows it);
    precision over reported hits (correct = within `tolerance_px` of the true hit pixel), also among
    confident hits u = tanh(k gap) < 0.5; and how many wrong hits that screen space cannot avoid (true
    target hidden or off screen) carry u >= 0.5."""
    from pipeline.ops.camera import backproject, project

    _, H, W = depth.shape
    o, d = origin.to(torch.float64), torch.nn.functional.normalize(direction.to(torch.float64), dim=-1)
    t, tn = scene.cast(o, d)
    p_true = o + t[:, None] * d
    uv, z = project(p_true, fov_x, H, W)
    col, row = uv[:, 0].floor().long(), uv[:, 1].floor().long()
    onscreen = (col >= 0) & (col < W) & (row >= 0) & (row < H) & (z > 1e-3)
    rr, cc = row.clamp(0, H - 1), col.clamp(0, W - 1)
    shown = backproject(depth.to(torch.float64), fov_x)[0][rr, cc]
    same_plane = ((normal[0].to(torch.float64)[:, rr, cc].T * tn).sum(-1) > 0.999) & (
        ((p_true - shown) * tn).sum(-1).abs() < 1e-6 + 1e-6 * z
    )
    visible = onscreen & same_plane
    dist = torch.maximum((pixel[:, 0] - row).abs(), (pixel[:, 1] - col).abs())
    correct = hit & onscreen & (dist <= tolerance_px)
    u = torch.tanh(k * gap.to(torch.float64))
    confident = hit & (u < 0.5)
    wrong = hit & ~correct
    unavoidable = wrong & ~visible
    mean = lambda x: float(x.float().mean()) if x.numel() else float("nan")  # noqa: E731
    return {
        "rays": float(len(o)),
        "visible_fraction": mean(visible),
        "hit_fraction": mean(hit),
        "recall": mean(correct[visible]),
        "precision": mean(correct[hit]),
        "precision_confident": mean(correct[confident]),
        "confident_fraction": mean(confident[hit]),
        "unavoidable_wrong_flagged": mean(u[unavoidable] >= 0.5),
        "false_positive_rate": mean(~correct[hit]),
    }
