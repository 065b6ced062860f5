"""LightNet's `roombox` out-of-view branch: what it returns on an analytic room, units, gradients, every
mode, export and configuration errors."""

import pytest
import torch
from torch.nn import functional as F

from pipeline.bench.scenes import BoxRoom
from pipeline.models.light_net import LightNet, out_of_view_branch
from pipeline.models.light_net.roombox import RoomBoxBranch, box_radiance, normals_from_depth
from pipeline.ops.camera import backproject
from tests.models.test_light_net import _scene

BARE = torch.tensor([[-2.0, -1.4, -5.5], [2.0, 1.4, 0.5]])
ROOMBOX = {"kind": "roombox", "roombox": {"texture_size": 8, "channels": 8, "code_dim": 16}}


def glowing_room(H=60, W=80, fov=90.0):
    """A bare box room seen by a level camera at its origin whose six faces glow in six colours:
    image (1, 3, H, W), depth (1, H, W), normals (1, 3, H, W), the colours (6, 3) by face index."""
    room = BoxRoom(BARE.double(), torch.zeros(0, 2, 3, dtype=torch.float64))
    depth, normal = room.render(H, W, fov)
    n = normal[0].permute(1, 2, 0)
    face = torch.zeros(H, W, dtype=torch.long)
    for k in range(6):
        axis, side = divmod(k, 2)
        face[n[..., axis] == (-1.0 if side else 1.0)] = k
    colours = torch.tensor(
        [[1.0, 0.5, 0.2], [0.2, 1.0, 0.4], [0.6, 0.6, 0.6], [8.0, 7.0, 5.0], [0.3, 0.3, 1.0], [2.0, 2.0, 2.0]]
    )
    image = colours[face].permute(2, 0, 1)[None]
    return image, depth.float(), normal.float(), colours


def test_seen_faces_return_what_the_camera_saw_with_the_true_layout():
    # full coverage weight and an opaque, decoded-to-one texture: a ray towards a seen face returns that
    # face's colour exactly (in the image's own units), whatever the image's exposure
    image, depth, normal, colours = glowing_room()
    branch = RoomBoxBranch(texture_size=8, channels=8, code_dim=16, layout="gt", coverage_pixels=1e-4, far_field=False)
    with torch.no_grad():
        branch.refine[-1].weight.zero_()
        branch.refine[-1].bias.copy_(torch.tensor([0.0, 0.0, 0.0, 50.0]))
    box = (torch.eye(3)[None], BARE[:1], BARE[1:])
    unit = image.mean().view(1)
    room = branch.encode(image, unit, depth, 90.0, normal, box=box)
    # rays from the camera towards the centres of the left, right, floor, ceiling and front faces
    targets = torch.tensor([[-2.0, 0.0, -3.0], [2.0, 0.0, -3.0], [0.0, -1.4, -3.0], [0.0, 1.4, -3.0], [0.0, 0.0, -5.5]])
    wi = F.normalize(targets, dim=-1)
    b = torch.zeros(5, dtype=torch.long)
    out = branch.query(room, unit, b, torch.zeros(5, 3), wi)
    torch.testing.assert_close(out, colours[:5], rtol=1e-5, atol=1e-5)
    # the face behind the camera was not seen: there the decoded texture (one image mean) answers
    behind = branch.query(room, unit, b[:1], torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]]))
    torch.testing.assert_close(behind, unit.expand(1, 3), rtol=1e-5, atol=1e-6)


def test_predicted_layout_finds_the_bare_rooms_box():
    image, depth, normal, _ = glowing_room(96, 128, 100.0)
    branch = RoomBoxBranch(texture_size=8, channels=8, code_dim=16)
    room = branch.encode(image, image.mean().view(1), depth, 100.0, normal)
    torch.testing.assert_close(room["rotation"][0], torch.eye(3), atol=1e-4, rtol=0)
    torch.testing.assert_close(room["lo"][0], BARE[0], atol=0.05, rtol=0)
    torch.testing.assert_close(room["hi"][0, :2], BARE[1, :2], atol=0.05, rtol=0)


def test_learnt_unseen_faces_move_only_the_unseen_faces_and_learn_from_the_light():
    # the bare room seen by a level camera: the face behind it is unseen; a scale of e^0.5 on it moves
    # it alone, and a loss on rays that leave through it reaches the scale's head
    image, depth, normal, _ = glowing_room(96, 128, 100.0)
    branch = RoomBoxBranch(texture_size=8, channels=8, code_dim=16, unseen="learnt")
    unit = image.mean().view(1)
    prior = branch.encode(image, unit, depth, 100.0, normal)
    with torch.no_grad():
        branch.unseen_scale.bias[5] = 0.5  # face 5: the hi side of z, behind the camera
    room = branch.encode(image, unit, depth, 100.0, normal)
    torch.testing.assert_close(room["lo"], prior["lo"])
    torch.testing.assert_close(room["hi"][0, :2], prior["hi"][0, :2])
    assert room["hi"][0, 2].item() == pytest.approx(prior["hi"][0, 2].item() * float(torch.exp(torch.tensor(0.5))))
    wi = F.normalize(torch.tensor([[0.3, 0.2, 1.0], [-0.2, -0.1, 1.0]]), dim=-1)
    out = branch.query(room, unit, torch.zeros(2, dtype=torch.long), torch.zeros(2, 3), wi)
    out.sum().backward()
    assert branch.unseen_scale.bias.grad[5].abs() > 0
    with pytest.raises(ValueError, match="roombox.unseen='guess'"):
        RoomBoxBranch(unseen="guess")


def test_normals_from_depth_match_the_analytic_ones_inside_faces():
    image, depth, normal, _ = glowing_room()
    est = normals_from_depth(backproject(depth, 90.0))
    agree = (est * normal).sum(1)[0, 2:-2, 2:-2]
    assert (agree > 0.999).float().mean() > 0.9  # all but the pixels that straddle an edge


def test_box_radiance_gradcheck_in_textures():
    g = torch.Generator().manual_seed(0)
    tex = torch.rand(2, 6, 4, 4, 4, dtype=torch.float64, generator=g).requires_grad_(True)
    room = {
        "rotation": torch.eye(3, dtype=torch.float64).expand(2, 3, 3),
        "lo": BARE[:1].double().expand(2, 3),
        "hi": BARE[1:].double().expand(2, 3),
    }
    wi = F.normalize(torch.randn(9, 3, dtype=torch.float64, generator=g), dim=-1)
    o = torch.rand(9, 3, dtype=torch.float64, generator=g) * 0.5
    b = torch.randint(0, 2, (9,), generator=g)
    far = torch.rand(9, 3, dtype=torch.float64, generator=g)
    assert torch.autograd.gradcheck(lambda t: box_radiance({**room, "textures": t}, b, o, wi, far), (tex,))


@pytest.mark.parametrize("mode", ("mixed", "out_of_view_only"))
def test_lightnet_with_the_roombox_gives_finite_light_and_trains_every_part(mode):
    torch.manual_seed(0)
    im, gb, fov, origin, wi, bidx = _scene()
    net = LightNet(mode=mode, out_of_view=ROOMBOX)
    assert isinstance(net.out_of_view, RoomBoxBranch)
    out = net(net.encode(im, gb["depth"], fov, normal=gb["normal"]), gb, fov, origin, wi, bidx)
    L = out["radiance"]
    assert torch.isfinite(L).all() and (L >= 0).all() and out["out_queries"] == len(wi)
    L.sum().backward()
    ov = net.out_of_view
    for p in (ov.encoder.stages[0][0][0].weight, ov.seed.weight, ov.refine[0].weight, ov.far[0].weight):
        assert p.grad is not None and p.grad.abs().sum() > 0
    # without normals it derives them from the depth: the same frame within about a degree on this
    # 24 x 32 map (a fifth of its pixels border a depth edge)
    ctx = net.encode(im, gb["depth"], fov)
    ref = net.encode(im, gb["depth"], fov, normal=gb["normal"])
    torch.testing.assert_close(ctx["room"]["rotation"], ref["room"]["rotation"], atol=0.02, rtol=0)


def test_roombox_radiance_scales_with_exposure():
    torch.manual_seed(0)
    im, gb, fov, origin, wi, bidx = _scene()
    net = LightNet(mode="out_of_view_only", out_of_view=ROOMBOX).eval()
    with torch.no_grad():
        one = net(net.encode(im, gb["depth"], fov, normal=gb["normal"]), gb, fov, origin, wi, bidx)["radiance"]
        two = net(net.encode(2 * im, gb["depth"], fov, normal=gb["normal"]), gb, fov, origin, wi, bidx)["radiance"]
    torch.testing.assert_close(two, 2 * one, rtol=1e-4, atol=1e-6)


def test_roombox_export_round_trip(tmp_path):
    from pipeline.models.export import save_light_export
    from pipeline.models.light_net import load_light_export

    torch.manual_seed(0)
    im, gb, fov, origin, wi, bidx = _scene(B=1)
    bidx = torch.zeros(len(wi) // 2, dtype=torch.long)
    origin, wi = origin[: len(bidx)], wi[: len(bidx)]
    kwargs = {"mode": "mixed", "out_of_view": ROOMBOX}
    net = LightNet(**kwargs).eval()
    save_light_export(tmp_path / "light.pt", kwargs, net)
    back, blob = load_light_export(tmp_path / "light.pt")
    assert blob["light_net"]["out_of_view"]["kind"] == "roombox"
    with torch.no_grad():
        a = net(net.encode(im, gb["depth"], fov, normal=gb["normal"]), gb, fov, origin, wi, bidx)["radiance"]
        b = back(back.encode(im, gb["depth"], fov, normal=gb["normal"]), gb, fov, origin, wi, bidx)["radiance"]
    torch.testing.assert_close(a, b)


def test_bad_roombox_configs_name_the_key():
    with pytest.raises(ValueError, match="out_of_view.kind='voxels'"):
        out_of_view_branch({"kind": "voxels"})
    with pytest.raises(ValueError, match="roombox.layout='guess'"):
        out_of_view_branch({"kind": "roombox", "roombox": {"layout": "guess"}})
    with pytest.raises(ValueError, match="roombox.texture_size=6"):
        out_of_view_branch({"kind": "roombox", "roombox": {"texture_size": 6}})
    with pytest.raises(ValueError, match="layout=gt: encode needs box"):
        b = RoomBoxBranch(texture_size=4, channels=4, code_dim=8, layout="gt")
        image, depth, normal, _ = glowing_room(12, 16)
        b.encode(image, image.mean().view(1), depth, 90.0, normal)
    # the nerf keys are the NeRF's alone: the roombox block is dropped for kind nerf
    assert (
        type(out_of_view_branch({"kind": "nerf", "samples": 4, "roombox": {"texture_size": 8}})).__name__
        == "OutOfViewBranch"
    )


def test_the_profiles_roombox_block_builds():
    from omegaconf import OmegaConf

    from tests.conftest import compose_cfg

    cfg = compose_cfg("train_lighting", ["model.light_net.out_of_view.kind=roombox"])
    net = LightNet(**OmegaConf.to_container(cfg.model.light_net, resolve=True))
    assert isinstance(net.out_of_view, RoomBoxBranch) and net.out_of_view.texture_size == 32
