"""Rooms that are not boxes (`data.synth.room_shapes`): the geometry each shape promises, checked on the
room data and, through Mitsuba's ray casts, on the scene the renderer builds from it."""

import json

import numpy as np
import pytest

from pipeline.data.synth.room_shapes import SHAPES, ceiling_height, reshape_room, slope_angle_deg
from pipeline.data.synth.scene import RoomConfig, generate_room

SEEDS = range(12)


def shaped(seed: int, shape: str, views: int = 2):
    cfg = RoomConfig()
    room, footprints, rng = generate_room(seed, views, cfg)
    return reshape_room(room, footprints, rng, shape, cfg)


def blocks(room):
    """Floor-to-ceiling wall-material cubes: (centre xz, half xz) each."""
    wall = next(s.material for s in room.shapes if s.role == "wall" and s.kind == "rectangle")
    out = []
    for s in room.shapes:
        if s.kind == "cube" and s.role == "wall":
            m = np.asarray(s.to_world)
            assert s.material == wall
            assert m[1, 3] - m[1, 1] == pytest.approx(0.0) and m[1, 3] + m[1, 1] == pytest.approx(room.size[1])
            out.append((m[[0, 2], 3], np.abs(np.diag(m)[[0, 2]])))
    return out


def over(xz, block, margin=0.0) -> bool:
    centre, half = block
    return bool(np.all(np.abs(np.asarray(xz) - centre) < half + margin))


def test_box_is_the_generator_room_and_every_shape_repeats_from_its_seed():
    for shape in SHAPES:
        a, b = shaped(3, shape)[0], shaped(3, shape)[0]
        assert json.dumps(a.to_json()) == json.dumps(b.to_json())
    assert json.dumps(shaped(3, "box")[0].to_json()) == json.dumps(generate_room(3, 2, RoomConfig())[0].to_json())
    with pytest.raises(ValueError, match="room shape 'dome'"):
        shaped(3, "dome")


@pytest.mark.parametrize("shape", ["l_shaped", "alcove"])
def test_blocks_stand_clear_of_furniture_lamps_and_cameras(shape):
    """An L's corner block (35-50 % of each side, in a corner) and an alcove's two piers (against one wall, at
    its ends): nothing of the room stands in them, the cameras keep clear, and a light is left."""
    for seed in SEEDS:
        room, footprints = shaped(seed, shape)
        W, H, D = room.size
        found = blocks(room)
        if shape == "l_shaped":
            assert len(found) == 1
            ((centre, half),) = found
            assert (
                0.35 * W / 2 - 1e-9 <= half[0] <= 0.5 * W / 2 + 1e-9
                and 0.35 * D / 2 - 1e-9 <= half[1] <= 0.5 * D / 2 + 1e-9
            )
            assert np.allclose(np.abs(centre) + half, [W / 2, D / 2])  # in a corner
        else:
            assert len(found) == 2
            (c0, h0), (c1, h1) = found
            touching = [np.isclose(np.abs(c) + h, [W / 2, D / 2]) for c, h in found]
            axis = 1 if touching[0][1] and touching[1][1] and np.sign(c0[1]) == np.sign(c1[1]) else 0
            assert np.sign(c0[axis]) == np.sign(c1[axis])  # against the same wall
            along = 1 - axis
            assert np.isclose(abs(c0[along]) + h0[along], room.size[2 * along] / 2)  # at its two ends
            assert np.sign(c0[along]) == -np.sign(c1[along])
        for s in room.shapes:
            xz = np.asarray(s.to_world)[[0, 2], 3]
            if s.role in ("furniture", "object", "lamp"):
                assert not any(over(xz, b) for b in found), (seed, s.role)
        for cam in room.cameras:
            assert not any(over(np.asarray(cam.origin)[[0, 2]], b, margin=0.3) for b in found), seed
        assert any(s.role == "lamp" for s in room.shapes) or room.windows
        assert sum(fp.half.prod() > 0 for fp in footprints) >= len(found)


def test_the_sloped_ceiling_tilts_its_lamps_and_clears_furniture_and_cameras():
    for seed in SEEDS:
        room, _ = shaped(seed, "sloped")
        W, H, D = room.size
        corners = [ceiling_height(room, x, z) for x in (-W / 2, W / 2) for z in (-D / 2, D / 2)]
        assert max(corners) == pytest.approx(H)
        assert 2.0 - 1e-9 <= min(corners) <= H - 0.4 + 1e-9
        assert 3.0 < slope_angle_deg(room) < 25.0
        ceiling = next(s for s in room.shapes if s.role == "ceiling")
        normal = np.asarray(ceiling.to_world)[:3, 2]
        assert normal[1] < 0  # faces down, into the room
        m = np.asarray(ceiling.to_world)
        assert np.dot(np.cross(m[:3, 0], m[:3, 1]), normal) > 0  # a right-handed frame, as every shape's
        for s in room.shapes:
            t = np.asarray(s.to_world)
            if s.role == "lamp":
                assert np.allclose(t[:3, 2], normal)
                assert np.dot(normal, t[:3, 3] - m[:3, 3]) == pytest.approx(0.001)  # 1 mm below the ceiling
            if s.role == "furniture":
                top = t[1, 3] + abs(t[1, 1])
                assert top <= ceiling_height(room, t[0, 3], t[2, 3]) - 0.1 + 1e-9, seed
        for cam in room.cameras:
            assert cam.origin[1] < ceiling_height(room, cam.origin[0], cam.origin[2]) - 0.2


def test_the_renderer_sees_the_shapes(mitsuba_variant):
    """Mitsuba's ray casts from each camera: straight up meets the sloped ceiling at its plane's height; a ray
    towards an L's corner block stops at the block's face, not at the outer wall behind it."""
    from pipeline.data.synth import mitsuba_backend as mb

    for seed in range(4):
        room, _ = shaped(seed, "sloped")
        scene = mb.load_scene(room)
        o = np.array([c.origin for c in room.cameras], float)
        hit = mb.intersect(scene, o, np.tile([0.0, 1.0, 0.0], (len(o), 1)))
        heights = [ceiling_height(room, x, z) for x, _, z in o]
        lamp = hit["lamp"]
        assert np.allclose((o[:, 1] + hit["t"])[~lamp], np.array(heights)[~lamp], atol=2e-3)

        room, _ = shaped(seed, "l_shaped")
        scene = mb.load_scene(room)
        ((centre, half),) = blocks(room)
        o = np.array([c.origin for c in room.cameras], float)
        target = np.array([[centre[0], 1.0, centre[1]]] * len(o))
        d = target - o
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        hit = mb.intersect(scene, o, d)
        entry = []
        for oo, dd in zip(o, d, strict=True):  # where the ray enters the block's xz rectangle (slab test)
            lo, hi = centre - half, centre + half
            t = [((lo - oo[[0, 2]]) / dd[[0, 2]]), ((hi - oo[[0, 2]]) / dd[[0, 2]])]
            entry.append(np.max(np.minimum(*t)))
        assert np.all(hit["t"] <= np.array(entry) + 1e-3)
        assert np.all(hit["hit"])
