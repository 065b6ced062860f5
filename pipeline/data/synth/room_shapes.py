"""Rooms that are not boxes, made from the generator's box rooms (`scene.generate_room`).

Every room `scene.generate_room` draws is a box, and the `roombox` out-of-view branch assumes one. To see
where that assumption fails, `reshape_room` turns a drawn box room into one of `SHAPES`:

- `box`: unchanged;
- `l_shaped`: a corner of the floor plan (35-50 % of the width and of the depth) walled off by a
  floor-to-ceiling block of the wall material, so the room is an L;
- `alcove`: one wall gets a floor-to-ceiling pier of the wall material at each end (0.5-0.9 m deep,
  0.5-1.0 m wide), so its middle is a recess;
- `sloped`: the ceiling tilts across the room's shorter span, from the room's height on one side down by
  0.4-1.2 m, to no lower than 2 m, on the other (4-20 degrees; the lamps tilt with it); the walls keep
  their height, the parts above the slope being outside the room, behind the one-sided ceiling.

Furniture (with the objects on it) and lamps that would collide with the new geometry are removed, the
blocks join the floor-plan footprints so cameras keep clear of them, and the cameras are drawn anew from
the same random stream, so a reshaped room is a pure function of its seed and shape. The room's `size`
stays the bounding box: what a box model of the room would be told as its true layout.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.data.synth.scene import (
    Footprint,
    Room,
    RoomConfig,
    Shape,
    box_matrix,
    frame_matrix,
    propose_camera,
)

SHAPES = ("box", "l_shaped", "alcove", "sloped")
MIN_LOW_CEILING_M = 2.0  # a sloped ceiling's low side: above every camera (at most 1.7 m) and most furniture
MIN_SLOPE_DROP_M = 0.4
CLEARANCE_M = 0.1  # furniture this close below a sloped ceiling is removed


def reshape_room(room: Room, footprints: list[Footprint], rng, shape: str, cfg: RoomConfig) -> tuple[Room, list]:
    """`room` (drawn by `scene.generate_room` with `cfg`, its footprints and the generator's `rng`) made
    into `shape` (module docstring), in place; returns (room, footprints). The cameras are re-drawn for
    every shape but `box`."""
    if shape not in SHAPES:
        raise ValueError(f"room shape {shape!r}: choose one of {', '.join(SHAPES)}")
    if shape == "box":
        return room, footprints
    if shape == "l_shaped":
        blocks = [_corner_block(room, rng)]
    elif shape == "alcove":
        blocks = _alcove_piers(room, rng)
    else:
        blocks = []
        _slope_ceiling(room, rng)
    if blocks:
        wall_material = next(s.material for s in room.shapes if s.role == "wall")
        H = room.size[1]
        for fp in blocks:
            room.shapes.append(
                Shape(
                    "cube",
                    box_matrix([fp.centre[0], H / 2, fp.centre[1]], [fp.half[0], H / 2, fp.half[1]], 0.0),
                    wall_material,
                    "wall",
                )
            )
        footprints = _remove_colliding(room, footprints, blocks)
        footprints = footprints + blocks
    else:
        footprints = _remove_under_slope(room, footprints)
    room.cameras = [propose_camera(room, rng, cfg, footprints) for _ in room.cameras]
    return room, footprints


def ceiling_height(room: Room, x: float, z: float) -> float:
    """Height (metres) of the room's ceiling above the floor point (x, z): the `ceiling` shape's plane."""
    ceiling = next(s for s in room.shapes if s.role == "ceiling")
    m = np.asarray(ceiling.to_world)
    centre, normal = m[:3, 3], m[:3, 2]
    # the plane n . (p - c) = 0 solved for y at (x, z)
    return float(centre[1] - (normal[0] * (x - centre[0]) + normal[2] * (z - centre[2])) / normal[1])


def _corner_block(room: Room, rng) -> Footprint:
    W, _, D = room.size
    sx, sz = (1.0 if rng.uniform() < 0.5 else -1.0), (1.0 if rng.uniform() < 0.5 else -1.0)
    w, d = W * float(rng.uniform(0.35, 0.5)), D * float(rng.uniform(0.35, 0.5))
    return Footprint(np.array([sx * (W - w) / 2, sz * (D - d) / 2]), np.array([w / 2, d / 2]), 0.0)


def _alcove_piers(room: Room, rng) -> list[Footprint]:
    W, _, D = room.size
    along_x = rng.uniform() < 0.5  # the recessed wall: one of the two along x (z = +-D/2) or along z
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    length = W if along_x else D
    piers = []
    for end in (-1.0, 1.0):
        width, depth = float(rng.uniform(0.5, 1.0)), float(rng.uniform(0.5, 0.9))
        width = min(width, 0.3 * length)
        a = end * (length / 2 - width / 2)  # centre along the wall
        b = side * ((D if along_x else W) / 2 - depth / 2)  # centre across, against the wall
        centre, half = ([a, b], [width / 2, depth / 2]) if along_x else ([b, a], [depth / 2, width / 2])
        piers.append(Footprint(np.array(centre, float), np.array(half, float), 0.0))
    return piers


def _slope_ceiling(room: Room, rng) -> None:
    """Tilt the ceiling (and its lamps) along x or z: full height on one side, lower on the other."""
    W, H, D = room.size
    low = float(rng.uniform(max(MIN_LOW_CEILING_M, H - 1.2), max(MIN_LOW_CEILING_M, H - MIN_SLOPE_DROP_M)))
    along_x, down_at_plus = W <= D, rng.uniform() < 0.5  # across the shorter span: the steeper slope
    half = W / 2 if along_x else D / 2
    drop = (low - H) * (1.0 if down_at_plus else -1.0)  # y change over the axis from - to +
    slope = np.array([half, drop / 2, 0.0]) if along_x else np.array([0.0, drop / 2, half])
    across = np.array([0.0, 0.0, D / 2]) if along_x else np.array([W / 2, 0.0, 0.0])
    normal = np.cross(slope, across)
    normal /= np.linalg.norm(normal)
    if normal[1] > 0:  # the one-sided ceiling faces down, into the room (frames stay right-handed)
        normal, across = -normal, -across
    ceiling = next(s for s in room.shapes if s.role == "ceiling")
    ceiling.to_world = frame_matrix([0.0, (H + low) / 2, 0.0], slope, across, normal)
    slope_dir, across_dir = slope / np.linalg.norm(slope), across / np.linalg.norm(across)
    for s in room.shapes:
        if s.role == "lamp":  # a panel's half sizes along x and z (columns u and v) laid onto the slope
            m = np.asarray(s.to_world)
            hx, hz = np.linalg.norm(m[:3, 0]), np.linalg.norm(m[:3, 1])
            x, z = m[0, 3], m[2, 3]
            u, v = (slope_dir * hx, across_dir * hz) if along_x else (slope_dir * hz, across_dir * hx)
            centre = np.array([x, ceiling_height(room, x, z), z]) + 0.001 * normal
            s.to_world = frame_matrix(centre, u, v, normal)


def _remove_colliding(room: Room, footprints: list[Footprint], blocks: list[Footprint]) -> list[Footprint]:
    """Drop furniture pieces (and the objects standing on them) overlapping `blocks`; lamps over a block
    are removed too, unless the room would be left without a light it can see (`_relight`)."""
    gone = [k for k, fp in enumerate(footprints) if any(fp.overlaps(b, gap=0.05) for b in blocks)]
    kept = _drop_furniture(room, footprints, gone)
    removed_lamps = [s for s in room.shapes if s.role == "lamp" and _panel_overlaps(s, blocks)]
    room.shapes = [s for s in room.shapes if not any(s is lamp for lamp in removed_lamps)]
    _relight(room, blocks, removed_lamps)
    return kept


def _drop_furniture(room: Room, footprints: list[Footprint], gone: list[int]) -> list[Footprint]:
    """Remove the furniture pieces of the footprints indexed by `gone`, and the objects standing on them,
    from the room; returns the footprints kept."""
    areas = [footprints[k] for k in gone]
    room.shapes = [s for s in room.shapes if not (s.role in ("furniture", "object") and _stands_on(s, areas))]
    return [fp for k, fp in enumerate(footprints) if k not in gone]


def _stands_on(shape: Shape, areas: list[Footprint]) -> bool:
    """Whether the shape's centre lies over one of the floor-plan `areas`."""
    return _over(np.asarray(shape.to_world)[[0, 2], 3], areas)


def _over(xz, areas: list[Footprint]) -> bool:
    return any(a.contains(np.asarray(xz, float), margin=0.05) for a in areas)


def _panel_overlaps(shape: Shape, blocks: list[Footprint]) -> bool:
    m = np.asarray(shape.to_world)
    panel = Footprint(m[[0, 2], 3], np.array([np.linalg.norm(m[:3, 0]), np.linalg.norm(m[:3, 1])]), 0.0)
    return any(panel.overlaps(b, gap=0.1) for b in blocks)


def _relight(room: Room, blocks: list[Footprint], removed_lamps: list[Shape]) -> None:
    """A room left with no lamp and no window outside the blocks gets its first removed lamp back, moved
    (size and light kept) to the point of the free floor plan farthest from the blocks."""
    open_windows = [w for w in room.windows if not _over([w.centre[0], w.centre[2]], blocks)]
    if open_windows or any(s.role == "lamp" for s in room.shapes) or not removed_lamps:
        return
    W, H, D = room.size
    xs, zs = np.linspace(-W / 2 + 0.6, W / 2 - 0.6, 9), np.linspace(-D / 2 + 0.6, D / 2 - 0.6, 9)
    grid = [np.array([x, z]) for x in xs for z in zs]
    xz = max(grid, key=lambda p: min(float(np.max(np.abs(p - b.centre) - b.half)) for b in blocks))
    lamp = removed_lamps[0]
    m = np.array(lamp.to_world)
    m[0, 3], m[2, 3] = xz
    lamp.to_world = m.tolist()
    room.shapes.append(lamp)


def _remove_under_slope(room: Room, footprints: list[Footprint]) -> list[Footprint]:
    """Drop furniture pieces (and their objects) whose top comes within `CLEARANCE_M` of the sloped
    ceiling anywhere over their footprint."""
    gone = []
    for k, fp in enumerate(footprints):
        parts = [np.asarray(s.to_world) for s in room.shapes if s.role == "furniture" and _stands_on(s, [fp])]
        top = max((m[1, 3] + abs(m[1, 1]) for m in parts), default=0.0)  # a part's centre y + its half height
        if top > min(ceiling_height(room, *c) for c in fp.corners()) - CLEARANCE_M:
            gone.append(k)
    return _drop_furniture(room, footprints, gone)


def slope_angle_deg(room: Room) -> float:
    """The ceiling's tilt from horizontal, degrees (0 for a flat one)."""
    ceiling = next(s for s in room.shapes if s.role == "ceiling")
    n = np.asarray(ceiling.to_world)[:3, 2]
    return math.degrees(math.acos(min(1.0, abs(n[1]) / np.linalg.norm(n))))
