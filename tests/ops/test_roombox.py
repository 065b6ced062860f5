"""The room box (ops.roombox): canonical frames, Manhattan rotation, extents, ray exits, texel lookups,
and what the camera saw of each face, on analytic box rooms (bench.scenes.BoxRoom) seen by tilted cameras."""

import itertools
import math

import pytest
import torch
from torch.nn import functional as F

from pipeline.bench.scenes import BoxRoom
from pipeline.ops.camera import backproject, pixel_directions
from pipeline.ops.roombox import (
    box_from_room,
    canonical_frame,
    exit_face,
    extents_from_points,
    observed_textures,
    rotation_from_normals,
    texel_lookup,
)
from pipeline.ops.volume import ray_box


def rotation(pitch_deg: float, yaw_deg: float) -> torch.Tensor:
    """Room-from-view rotation of a camera pitched (about x) then turned (about y), float64."""
    p, y = math.radians(pitch_deg), math.radians(yaw_deg)
    rx = torch.tensor([[1, 0, 0], [0, math.cos(p), -math.sin(p)], [0, math.sin(p), math.cos(p)]], dtype=torch.float64)
    ry = torch.tensor([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]], dtype=torch.float64)
    return ry @ rx


def tilted_view(room: BoxRoom, room_from_view: torch.Tensor, H=48, W=64, fov=80.0):
    """Exact z-depth (1, H, W) and view-space normals (1, 3, H, W) of `room` (room frame, camera at its
    origin) seen by a camera whose axes are room_from_view's columns."""
    dirs = pixel_directions(H, W, fov, dtype=torch.float64).reshape(-1, 3)
    unit = F.normalize(dirs, dim=-1)
    t, n_room = room.cast(torch.zeros_like(unit), unit @ room_from_view.T)
    z = t * -unit[:, 2]
    n_view = n_room @ room_from_view
    return z.reshape(1, H, W), n_view.reshape(H, W, 3).permute(2, 0, 1)[None]


def test_canonical_frame_is_the_proper_relabelling_closest_to_the_identity():
    torch.manual_seed(0)
    for _ in range(20):
        q, _r = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64))
        out = canonical_frame(q[None])[0]
        assert torch.linalg.det(out) == pytest.approx(1.0)
        # every proper signed permutation of q's columns: none has a larger trace
        best = max(
            float(torch.trace(q[:, list(p)] * torch.tensor(s, dtype=torch.float64)))
            for p in itertools.permutations(range(3))
            for s in itertools.product((-1.0, 1.0), repeat=3)
            if torch.linalg.det(q[:, list(p)] * torch.tensor(s, dtype=torch.float64)) > 0
        )
        assert float(torch.trace(out)) == pytest.approx(best)
        # its columns are q's, up to order and sign
        assert torch.allclose((out.T @ q).abs().amax(1), torch.ones(3, dtype=torch.float64))


@pytest.mark.parametrize("pitch,yaw", [(0.0, 0.0), (-20.0, 30.0), (5.0, -40.0), (-25.0, 12.0)])
def test_rotation_from_normals_recovers_a_tilted_camera(pitch, yaw):
    # a furnished box room seen by a pitched and turned camera: the room's axes from its normals
    room = BoxRoom.default()
    truth = rotation(pitch, yaw)
    depth, normal = tilted_view(room, truth)
    valid = torch.isfinite(depth) & (depth > 0)
    noisy = F.normalize(
        normal + 0.02 * torch.randn(normal.shape, generator=torch.Generator().manual_seed(1), dtype=normal.dtype), dim=1
    )
    est = rotation_from_normals(noisy, valid)[0]
    expect = canonical_frame(truth.T[None])[0]  # room axes in view space, canonically labelled
    angle = math.degrees(math.acos(float(((torch.trace(est.T @ expect) - 1) / 2).clamp(-1, 1))))
    assert angle < 0.5


def test_extents_find_the_seen_walls_and_put_the_unseen_one_behind_by_the_prior():
    # a bare box room (no furniture), camera level: walls, floor, ceiling and front wall are seen at their
    # exact distances; the wall behind the camera is unseen and goes to 0.25 x the front wall's distance
    room = BoxRoom(
        torch.tensor([[-2.0, -1.4, -5.5], [2.0, 1.4, 0.5]], dtype=torch.float64),
        torch.zeros(0, 2, 3, dtype=torch.float64),
    )
    depth, normal = tilted_view(room, torch.eye(3, dtype=torch.float64), H=96, W=128, fov=100.0)
    valid = torch.isfinite(depth) & (depth > 0)
    pts = backproject(depth, 100.0)
    rot = rotation_from_normals(normal, valid)
    lo, hi = extents_from_points(pts, valid, rot, normal, quantile=1.0)
    torch.testing.assert_close(lo[0], torch.tensor([-2.0, -1.4, -5.5], dtype=torch.float64), atol=1e-6, rtol=0)
    torch.testing.assert_close(hi[0, :2], torch.tensor([2.0, 1.4], dtype=torch.float64), atol=1e-6, rtol=0)
    assert hi[0, 2].item() == pytest.approx(0.25 * 5.5)


def test_exit_face_lands_on_the_box_where_the_slab_method_says():
    g = torch.Generator().manual_seed(0)
    lo, hi = torch.tensor([[-2.0, -1.0, -3.0]]), torch.tensor([[1.0, 2.0, 0.5]])
    q = lo + (hi - lo) * torch.rand(500, 3, generator=g)
    d = F.normalize(torch.randn(500, 3, generator=g), dim=-1)
    face, st, t = exit_face(q, d, lo.expand(500, 3), hi.expand(500, 3))
    _t0, t_far = ray_box(q, d, lo, hi)
    # origins are first nudged 1e-4 of the box's size inside it: distances agree to that
    torch.testing.assert_close(t, t_far, atol=1e-3, rtol=0)
    point = q + t[:, None] * d
    axis, side = face // 2, face % 2
    plane = torch.where(side.bool(), hi[0][axis], lo[0][axis])
    torch.testing.assert_close(point.gather(1, axis[:, None])[:, 0], plane, atol=1e-4, rtol=0)
    assert (st.abs() <= 1).all()
    # st runs along the other two axes, -1 at lo and +1 at hi
    others = {0: (1, 2), 1: (0, 2), 2: (0, 1)}
    for i in range(0, 500, 37):
        a, b = others[int(axis[i])]
        expect = 2 * (point[i, [a, b]] - lo[0, [a, b]]) / (hi[0, [a, b]] - lo[0, [a, b]]) - 1
        torch.testing.assert_close(st[i], expect, atol=1e-4, rtol=0)


def test_texel_lookup_is_grid_sample_with_border_clamping():
    g = torch.Generator().manual_seed(0)
    tex = torch.rand(5, 4, 8, 8, generator=g, dtype=torch.float64)
    index = torch.randint(0, 5, (300,), generator=g)
    st = torch.rand(300, 2, generator=g, dtype=torch.float64) * 2.2 - 1.1
    got = texel_lookup(tex, index, st.clamp(-1, 1))
    ref = torch.stack(
        [
            F.grid_sample(
                tex[k : k + 1], st[i].clamp(-1, 1).view(1, 1, 1, 2), align_corners=False, padding_mode="border"
            )[0, :, 0, 0]
            for i, k in enumerate(index.tolist())
        ]
    )
    torch.testing.assert_close(got, ref, atol=1e-12, rtol=0)
    # texel centres return the texel
    centre = torch.tensor([[(2 + 0.5) / 8 * 2 - 1, (5 + 0.5) / 8 * 2 - 1]], dtype=torch.float64)
    torch.testing.assert_close(texel_lookup(tex, torch.tensor([3]), centre)[0], tex[3, :, 5, 2])


def test_texel_lookup_gradcheck():
    tex = torch.rand(2, 3, 4, 4, dtype=torch.float64, requires_grad=True)
    st = torch.rand(7, 2, dtype=torch.float64) * 1.6 - 0.8
    index = torch.tensor([0, 1, 1, 0, 1, 0, 0])
    assert torch.autograd.gradcheck(lambda t: texel_lookup(t, index, st), (tex,))


def test_observed_textures_put_each_faces_colour_on_that_face_and_lamps_on_the_ceiling():
    # a bare room whose faces glow in six colours; ceiling pixels carry no depth (a lamp panel): they must
    # still land on the ceiling through their camera ray. Nothing lands on the face behind the camera.
    room = BoxRoom(
        torch.tensor([[-2.0, -1.4, -5.5], [2.0, 1.4, 0.5]], dtype=torch.float64),
        torch.zeros(0, 2, 3, dtype=torch.float64),
    )
    H, W, fov = 60, 80, 90.0
    depth, normal = tilted_view(room, torch.eye(3, dtype=torch.float64), H, W, fov)
    n = normal[0].permute(1, 2, 0)
    face = torch.zeros(H, W, dtype=torch.long)
    for k in range(6):
        axis, side = divmod(k, 2)
        face[n[..., axis] == (-1.0 if side else 1.0)] = k
    colours = torch.arange(1, 19, dtype=torch.float64).view(6, 3)
    image = colours[face].permute(2, 0, 1)[None]
    ceiling = face == 3
    depth = torch.where(ceiling[None], torch.zeros_like(depth), depth)
    rot = torch.eye(3, dtype=torch.float64)[None]
    lo, hi = room.room[:1], room.room[1:]
    mean, count = observed_textures(image, depth, fov, rot, lo, hi, 8, normal)
    for k in range(5):
        seen = count[0, k, 0] > 0
        assert seen.any(), k
        expect = colours[k].view(3, 1).expand(3, int(seen.sum()))
        torch.testing.assert_close(mean[0, k][:, seen], expect)
    assert count[0, 5].sum() == 0
    assert count.sum() == H * W  # every pixel counted once


def test_box_from_room_matches_the_generators_camera_convention():
    # a camera at (1, 1.5, 2) looking down -z, level: the box in its frame is the room shifted
    size = (4.0, 3.0, 6.0)
    m = torch.eye(4, dtype=torch.float64)
    m[:3, 3] = torch.tensor([1.0, 1.5, 2.0])
    rot, lo, hi = box_from_room(size, m.tolist())
    torch.testing.assert_close(rot, torch.eye(3, dtype=torch.float64))
    torch.testing.assert_close(lo, torch.tensor([-3.0, -1.5, -5.0], dtype=torch.float64))
    torch.testing.assert_close(hi, torch.tensor([1.0, 1.5, 1.0], dtype=torch.float64))
