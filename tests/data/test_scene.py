"""The procedural generator: determinism, non-interpenetration, cameras in free space, material coverage."""

import itertools

import numpy as np
import pytest

from pipeline.data.synth.materials import Material, pattern_levels
from pipeline.data.synth.scene import Footprint, Room, generate_room

SEEDS = range(40)


def _rooms():
    return [generate_room(s, views=5)[0] for s in SEEDS]


@pytest.fixture(scope="module")
def rooms():
    return _rooms()


def _world_aabb(shape):
    """Axis-aligned bounds (2, 3) of a cube or sphere shape in world space."""
    m = np.asarray(shape.to_world)
    corners = np.array(list(itertools.product([-1, 1], repeat=3)), float)
    pts = corners @ m[:3, :3].T + m[:3, 3]
    return np.stack([pts.min(0), pts.max(0)])


def test_same_seed_same_room_and_json_roundtrip():
    a, b = generate_room(7, 3)[0], generate_room(7, 3)[0]
    assert a.to_json() == b.to_json()
    assert Room.from_json(a.to_json()).to_json() == a.to_json()
    assert generate_room(8, 3)[0].to_json() != a.to_json()


def test_footprint_separating_axis():
    a = Footprint(np.array([0.0, 0.0]), np.array([1.0, 0.5]), 0.0)
    assert a.overlaps(Footprint(np.array([1.9, 0.0]), np.array([1.0, 0.5]), 0.0))
    assert not a.overlaps(Footprint(np.array([2.1, 0.0]), np.array([1.0, 0.5]), 0.0))
    # a rotated square whose corner pokes into a is caught; a rotated one just clear of it is not
    assert a.overlaps(Footprint(np.array([1.6, 0.0]), np.array([0.5, 0.5]), np.pi / 4))
    assert not a.overlaps(Footprint(np.array([1.75, 0.0]), np.array([0.5, 0.5]), np.pi / 4))
    assert a.overlaps(Footprint(np.array([1.9, 0.0]), np.array([1.0, 0.5]), 0.0), gap=0.0)


def test_pieces_stay_inside_the_room_and_do_not_interpenetrate(rooms):
    for room in rooms:
        W, H, D = room.size
        lo, hi = np.array([-W / 2, 0, -D / 2]), np.array([W / 2, H, D / 2])
        solids = [s for s in room.shapes if s.kind in ("cube", "sphere")]
        boxes = [_world_aabb(s) for s in solids]
        for s, b in zip(solids, boxes, strict=True):
            assert np.all(b[0] >= lo - 1e-6) and np.all(b[1] <= hi + 1e-6), (
                f"seed {room.seed}: {s.role} leaves the room"
            )
        # small objects: footprint circles (xz) of objects standing at the same height must be disjoint
        objects = []
        for s in solids:
            if s.role != "object":
                continue
            m = np.asarray(s.to_world)
            radius = (
                m[0, 0] if s.kind == "sphere" else np.linalg.norm([np.linalg.norm(m[:3, 0]), np.linalg.norm(m[:3, 2])])
            )
            objects.append((m[:3, 3], radius, _world_aabb(s)[0, 1]))
        for (c1, r1, y1), (c2, r2, y2) in itertools.combinations(objects, 2):
            if abs(y1 - y2) < 1e-6:
                assert np.linalg.norm(c1[[0, 2]] - c2[[0, 2]]) >= r1 + r2 - 1e-9, f"seed {room.seed}: objects overlap"
    for room in rooms:
        assert room.size[1] >= 2.4


def test_furniture_footprints_are_disjoint():
    for seed in SEEDS:
        _, footprints, _ = generate_room(seed, 1)
        for a, b in itertools.combinations(footprints, 2):
            assert not a.overlaps(b, gap=0.04), f"seed {seed}: furniture footprints overlap"


def test_cameras_stand_in_free_space_at_eye_height():
    for seed in SEEDS:
        room, footprints, _ = generate_room(seed, 5)
        W, H, D = room.size
        for cam in room.cameras:
            o = np.asarray(cam.origin)
            assert abs(o[0]) < W / 2 and abs(o[2]) < D / 2 and 1.0 <= o[1] <= 1.8
            assert not any(fp.contains(o[[0, 2]], margin=0.25) for fp in footprints)
            fwd = np.asarray(cam.target) - o
            pitch = np.degrees(np.arcsin(fwd[1] / np.linalg.norm(fwd)))
            assert -26 <= pitch <= 6


def test_material_coverage_over_many_rooms(rooms):
    mats = [m for r in rooms for m in r.materials if m.role != "lamp"]
    rough = np.array([m.roughness for m in mats])
    metal = np.array([m.metallic for m in mats])
    assert rough.min() <= 0.05 and rough.max() >= 0.95, "mirror-like to matte"
    assert (metal == 0).any() and (metal == 1).any() and ((metal > 0) & (metal < 1)).any()
    assert any(m.texture for m in mats) and any(m.roughness_map() is not None for m in mats)
    assert any(r.sky is not None for r in rooms) and any(s.role == "mirror" for r in rooms for s in r.shapes)
    assert all(any(s.role == "lamp" for s in r.shapes) or r.windows for r in rooms), "every room is lit"
    for m in mats:
        assert all(0 <= c <= 1 for c in m.albedo) and 0 < m.roughness <= 1 and 0 <= m.metallic <= 1


def test_textures_are_deterministic_discrete_and_in_range():
    spec = {"pattern": "planks", "repeat": 4, "seed": 3, "albedo2": [0.1, 0.2, 0.3], "roughness2": 0.9}
    np.testing.assert_array_equal(pattern_levels(spec), pattern_levels(spec))
    m = Material("floor", [0.5, 0.4, 0.3], 0.1, 0.0, spec)
    assert m.albedo_map().shape == (64, 64, 3) and m.roughness_map().shape == (64, 64)
    assert len(np.unique(pattern_levels(spec))) <= 5
    with pytest.raises(ValueError, match="pattern"):
        pattern_levels({**spec, "pattern": "zebra"})


def test_pictures_hang_flat_on_walls_without_overlapping(rooms):
    pictures = 0
    for room in rooms:
        hung = [s for s in room.shapes if s.role in ("picture", "mirror")]
        pictures += sum(s.role == "picture" for s in hung)
        for s in hung:
            m = room.materials[s.material]
            assert m.metallic == (1.0 if s.role == "mirror" else 0.0)
            centre = np.asarray(s.to_world)[:3, 3]
            W, H, D = room.size
            # within a few millimetres of a wall plane, at eye height
            assert min(abs(abs(centre[0]) - W / 2), abs(abs(centre[2]) - D / 2)) < 0.005
            assert 1.0 < centre[1] < 2.0
        # spans on the same wall do not overlap (compare the centres' separation with the half extents)
        for i, a in enumerate(hung):
            for b in hung[i + 1 :]:
                ta, tb = np.asarray(a.to_world), np.asarray(b.to_world)
                if not np.allclose(ta[:3, 2], tb[:3, 2]):  # different walls
                    continue
                along = ta[:3, 0] / np.linalg.norm(ta[:3, 0])
                gap = abs(float(np.dot(ta[:3, 3] - tb[:3, 3], along)))
                assert gap >= np.linalg.norm(ta[:3, 0]) + np.linalg.norm(tb[:3, 0]) + 0.05
    assert pictures > len(rooms) // 2


def test_furniture_materials_follow_their_kind():
    from pipeline.data.synth.materials import FURNITURE_MIX, random_material
    from pipeline.data.synth.scene import FURNITURE_KINDS

    assert set(FURNITURE_MIX) == set(FURNITURE_KINDS)
    rng = np.random.default_rng(0)
    for kind, mix in FURNITURE_MIX.items():
        assert abs(sum(p for _, p in mix) - 1) < 1e-9
        metal = np.mean([random_material(rng, "furniture", kind).metallic == 1.0 for _ in range(400)])
        expect = dict(mix).get("metal", 0.0)
        assert abs(metal - expect) <= 4 * np.sqrt(max(expect * (1 - expect), 1e-4) / 400), kind
    with pytest.raises(ValueError, match="furniture kind"):
        random_material(rng, "furniture", "piano")


def test_the_out_of_distribution_style_draws_what_the_standard_rooms_never_do(rooms):
    """`synthesize`'s ood rooms (the shipped config) lie outside the standard rooms' ranges on layout,
    lights and materials: narrower, deeper and taller rooms, smaller lamps, saturated glossy walls,
    grey floors and mostly boxes; the standard rooms (`rooms`) never reach those values."""
    import colorsys

    from pipeline.runs.synthesize import ood_config
    from tests.conftest import compose_cfg

    cfg = ood_config(compose_cfg("synthesize", ["profile=tiny"]))
    assert cfg is not None and cfg.splits == {"train": 0.0, "val": 0.0, "test": 1.0}
    assert cfg.cases.enabled and tuple(cfg.cases.edits) == (0, 0)  # insertion cases only
    loft = [generate_room(s, views=1, cfg=cfg.room)[0] for s in SEEDS]

    def walls(room, key):
        return [m for m in room.materials if m.role == key]

    def lamp_halves(room):
        return [np.linalg.norm(np.asarray(s.to_world)[:3, 0]) for s in room.shapes if s.role == "lamp"]

    def saturation(rgb):
        return colorsys.rgb_to_hsv(*rgb)[1]

    for standard, other in ((rooms, False), (loft, True)):
        widths = [r.size[0] for r in standard]
        heights = [r.size[1] for r in standard]
        wall_sat = [saturation(m.albedo) for r in standard for m in walls(r, "wall")]
        wall_rough = [m.roughness for r in standard for m in walls(r, "wall")]
        floor_sat = [saturation(m.albedo) for r in standard for m in walls(r, "floor")]
        lamps = [h for r in standard for h in lamp_halves(r)]
        if other:
            assert max(widths) <= 3.2 and min(heights) >= 3.3 and max(lamps) <= 0.12 + 1e-9
            assert min(wall_sat) >= 0.45 - 1e-9 and max(wall_rough) <= 0.45 and max(floor_sat) <= 0.08 + 1e-9
        else:
            assert min(widths) >= 3.2 and max(heights) <= 3.2 and min(lamps) >= 0.15 - 1e-9
            assert max(wall_sat) <= 0.4 + 1e-9 and min(wall_rough) >= 0.5 and min(floor_sat) >= 0.2 - 1e-9
    objects = [s.kind for r in loft for s in r.shapes if s.role == "object"]
    assert objects and objects.count("cube") > 0.7 * len(objects)


def test_a_test_only_split_and_bad_fractions():
    from pipeline.data.synth.generate import assign_splits
    from pipeline.data.synth.materials import random_material

    only = assign_splits(5, {"train": 0.0, "val": 0.0, "test": 1.0}, 0)
    assert only["train"] == [] and only["val"] == [] and len(only["test"]) == 5
    with pytest.raises(ValueError, match="val and test must hold all"):
        assign_splits(5, {"train": 0.0, "val": 0.0, "test": 0.5}, 0)
    with pytest.raises(ValueError, match="fractions in"):
        assign_splits(5, {"train": 0.7, "val": 0.15, "tset": 0.15}, 0)
    with pytest.raises(ValueError, match="synth.room.palette='neon'"):
        random_material(np.random.default_rng(0), "wall", palette="neon")
