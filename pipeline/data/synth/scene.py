"""Procedural indoor scenes as plain data (numpy + JSON), independent of Mitsuba.

A room spans x in [-W/2, W/2], y in [0, H] (y up), z in [-D/2, D/2], world units metres. Every surface is
one of three primitives: `rectangle` (canonical [-1,1]^2 in the local xy plane, normal +z), `cube`
(canonical [-1,1]^3) or `sphere` (unit, at the origin), placed by a 4x4 world-from-local matrix.
Rectangles are one-sided, so every wall, floor and ceiling piece faces into the room.

Everything is drawn from one `numpy.random.Generator`, so a scene is a pure function of its seed.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from pipeline.data.synth.materials import Material, random_material

# ----------------------------------------------------------------------------------------------------
# Data


@dataclass
class Shape:
    """One primitive: kind in {rectangle, cube, sphere, mesh}, world-from-local 4x4, material index, role.
    A `mesh` (inserted objects only) carries its triangles in `mesh`: {"vertices": (V, 3) world metres,
    "faces": (F, 3) vertex indices, counter-clockwise seen from outside}, its `to_world` the identity."""

    kind: str
    to_world: list[list[float]]
    material: int
    role: str  # wall | floor | ceiling | furniture | object | mirror | picture | lamp | inserted
    emission: list[float] | None = None  # RGB radiance (W/m^2/sr) for lamps
    mesh: dict | None = None


@dataclass
class Window:
    """An opening in a wall onto the sky: centre, half-extent vectors u, v (metres) and inward normal."""

    centre: list[float]
    u: list[float]
    v: list[float]
    normal: list[float]


@dataclass
class Sky:
    """Sky seen through windows: zenith/horizon/ground RGB radiance and a sun disc."""

    zenith: list[float]
    horizon: list[float]
    ground: list[float]
    sun_direction: list[float]  # unit, world space, pointing towards the sun
    sun_radiance: list[float]
    sun_radius_deg: float


@dataclass
class Camera:
    """A pinhole camera: origin and look-at target in world space, horizontal field of view (degrees)."""

    origin: list[float]
    target: list[float]
    fov_x_deg: float


@dataclass
class Room:
    seed: int
    size: list[float]  # W (x), H (y), D (z) in metres
    materials: list[Material]
    shapes: list[Shape]
    windows: list[Window]
    sky: Sky | None
    cameras: list[Camera] = field(default_factory=list)

    def to_json(self) -> dict:
        d = asdict(self)
        for shape in d["shapes"]:  # only inserted objects are meshes: room files keep their primitives' keys
            if shape["mesh"] is None:
                del shape["mesh"]
        return d

    @staticmethod
    def from_json(d: dict) -> Room:
        return Room(
            seed=d["seed"],
            size=d["size"],
            materials=[Material(**m) for m in d["materials"]],
            shapes=[Shape(**s) for s in d["shapes"]],
            windows=[Window(**w) for w in d["windows"]],
            sky=Sky(**d["sky"]) if d["sky"] else None,
            cameras=[Camera(**c) for c in d["cameras"]],
        )


# ----------------------------------------------------------------------------------------------------
# Geometry helpers


def frame_matrix(centre, u, v, n) -> list[list[float]]:
    """World-from-local matrix whose local x, y, z axes map to u, v, n and origin to `centre`."""
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = u, v, n, centre
    return m.tolist()


def box_matrix(centre, half, yaw) -> list[list[float]]:
    """World-from-local matrix of a box with half extents `half` rotated by `yaw` radians about +y."""
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    m = np.eye(4)
    m[:3, :3] = rot @ np.diag(half)
    m[:3, 3] = centre
    return m.tolist()


def sphere_matrix(centre, radius) -> list[list[float]]:
    m = np.eye(4) * radius
    m[3, 3] = 1.0
    m[:3, 3] = centre
    return m.tolist()


@dataclass
class Footprint:
    """Oriented rectangle on the floor (xz plane): centre (2,), half extents (2,), yaw (radians)."""

    centre: np.ndarray
    half: np.ndarray
    yaw: float

    def axes(self) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        # local x maps to world (c, -s) in (x, z) and local z to (s, c), matching box_matrix's rotation.
        return np.array([[c, -s], [s, c]])

    def corners(self) -> np.ndarray:
        ax = self.axes()
        signs = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]])
        return self.centre + (signs * self.half) @ ax

    def overlaps(self, other: Footprint, gap: float = 0.0) -> bool:
        """Separating-axis test of the two rectangles, each grown by `gap`/2 on every side."""
        for axis in np.concatenate([self.axes(), other.axes()]):
            pa = self.corners() @ axis
            pb = other.corners() @ axis
            if pa.max() + gap <= pb.min() or pb.max() + gap <= pa.min():
                return False
        return True

    def contains(self, xz: np.ndarray, margin: float = 0.0) -> bool:
        local = self.axes() @ (np.asarray(xz) - self.centre)
        return bool(np.all(np.abs(local) <= self.half + margin))


# ----------------------------------------------------------------------------------------------------
# Furniture: composites of boxes in a local frame (x width, y up, z depth), resting on the floor.

# kind -> (width range, depth range, height range, against-wall probability)
FURNITURE_KINDS = {
    "cabinet": ((0.6, 1.4), (0.4, 0.6), (0.8, 2.0), 0.9),
    "table": ((0.8, 1.6), (0.6, 1.0), (0.68, 0.8), 0.2),
    "sofa": ((1.5, 2.2), (0.8, 0.95), (0.75, 0.9), 0.8),
    "bed": ((1.3, 1.8), (1.9, 2.1), (0.45, 0.6), 0.9),
    "shelf": ((0.6, 1.2), (0.3, 0.4), (1.4, 2.1), 1.0),
    "block": ((0.3, 0.7), (0.3, 0.7), (0.3, 1.0), 0.3),
}


def furniture_parts(kind: str, w: float, d: float, h: float) -> tuple[list[tuple], float | None]:
    """Boxes (centre (3,), half (3,)) in the local frame of one piece, and the height of its top surface
    where small objects may stand (None if none)."""
    if kind == "table":
        t, leg = 0.04, 0.03
        parts = [((0, h - t / 2, 0), (w / 2, t / 2, d / 2))]
        for sx in (-1, 1):
            for sz in (-1, 1):
                cx, cz = sx * (w / 2 - 2 * leg), sz * (d / 2 - 2 * leg)
                parts.append(((cx, (h - t) / 2, cz), (leg, (h - t) / 2, leg)))
        return parts, h
    if kind == "sofa":
        seat_h, back_t, arm_w = 0.42, 0.2, 0.15
        parts = [
            ((0, seat_h / 2, back_t / 2), (w / 2 - arm_w, seat_h / 2, d / 2 - back_t / 2)),
            ((0, h / 2, -d / 2 + back_t / 2), (w / 2, h / 2, back_t / 2)),
        ]
        for sx in (-1, 1):
            parts.append(((sx * (w / 2 - arm_w / 2), 0.3, back_t / 2), (arm_w / 2, 0.3, d / 2 - back_t / 2)))
        return parts, None
    if kind == "bed":
        head_t = 0.08
        return [
            ((0, h / 2, head_t / 2), (w / 2, h / 2, d / 2 - head_t / 2)),
            ((0, (h + 0.5) / 2, -d / 2 + head_t / 2), (w / 2, (h + 0.5) / 2, head_t / 2)),
        ], None
    if kind == "shelf":
        return [((0, h / 2, 0), (w / 2, h / 2, d / 2))], None
    return [((0, h / 2, 0), (w / 2, h / 2, d / 2))], (h if h < 1.3 else None)


# ----------------------------------------------------------------------------------------------------
# The generator


@dataclass
class RoomConfig:
    """Knobs of the generator (metres, degrees); the Hydra `synth` group maps onto this."""

    width: tuple[float, float] = (3.2, 6.0)
    depth: tuple[float, float] = (3.5, 7.0)
    height: tuple[float, float] = (2.4, 3.2)
    furniture: tuple[int, int] = (3, 7)
    objects: tuple[int, int] = (1, 5)
    lamps: tuple[int, int] = (1, 3)
    window_probability: float = 0.75
    mirror_probability: float = 0.4
    pictures: tuple[int, int] = (0, 2)  # framed patterns per wall without a window
    fov_x_deg: tuple[float, float] = (60.0, 85.0)
    camera_height: tuple[float, float] = (1.1, 1.7)
    camera_pitch_deg: tuple[float, float] = (-25.0, 5.0)
    # the style knobs an out-of-distribution split turns (the defaults draw the standard rooms)
    palette: str = "standard"  # materials.PALETTES: how floors, walls, ceilings and objects are drawn
    sphere_probability: float = 0.6  # objects that are spheres (the rest boxes)
    object_radius: tuple[float, float] = (0.05, 0.14)  # metres, the object's bounding radius
    lamp_half_size: tuple[float, float] = (0.15, 0.45)  # metres, half the side of a ceiling panel
    cool_lamp_probability: float = 0.3  # lamps with a cool (blue) rather than a warm tint


def generate_room(seed: int, views: int, cfg: RoomConfig | None = None):
    """Draw a furnished, lit room and `views` camera proposals from `seed` (deterministic).

    Returns (room, footprints, rng): the furniture footprints and the generator's state are handed on so
    the renderer can re-draw (`propose_camera`) a camera that looks at a wall from too close, still
    deterministically.
    """
    cfg = cfg or RoomConfig()
    rng = np.random.default_rng(seed)
    W, H, D = (float(rng.uniform(*r)) for r in (cfg.width, cfg.height, cfg.depth))
    room = Room(seed=seed, size=[W, H, D], materials=[], shapes=[], windows=[], sky=None)

    def add_material(role: str, kind: str | None = None) -> int:
        room.materials.append(random_material(rng, role, kind, cfg.palette))
        return len(room.materials) - 1

    _add_shell(room, rng, cfg, add_material)
    footprints = _add_furniture(room, rng, cfg, add_material)
    _add_lamps(room, rng, cfg, add_material)
    room.cameras = [propose_camera(room, rng, cfg, footprints) for _ in range(views)]
    return room, footprints, rng


def _add_shell(room: Room, rng, cfg: RoomConfig, add_material) -> None:
    W, H, D = room.size
    floor_m, ceil_m, wall_m = add_material("floor"), add_material("ceiling"), add_material("wall")
    hx, hz = W / 2, D / 2
    room.shapes.append(
        Shape("rectangle", frame_matrix([0, 0, 0], [hx, 0, 0], [0, 0, -hz], [0, 1, 0]), floor_m, "floor")
    )
    room.shapes.append(
        Shape("rectangle", frame_matrix([0, H, 0], [hx, 0, 0], [0, 0, hz], [0, -1, 0]), ceil_m, "ceiling")
    )
    # Walls: (centre of the wall, unit horizontal axis along it, half length, inward normal)
    walls = [
        (np.array([0, H / 2, -hz]), np.array([1.0, 0, 0]), hx, np.array([0, 0, 1.0])),
        (np.array([0, H / 2, hz]), np.array([-1.0, 0, 0]), hx, np.array([0, 0, -1.0])),
        (np.array([-hx, H / 2, 0]), np.array([0, 0, -1.0]), hz, np.array([1.0, 0, 0])),
        (np.array([hx, H / 2, 0]), np.array([0, 0, 1.0]), hz, np.array([-1.0, 0, 0])),
    ]
    window_walls: set[int] = set()
    if rng.uniform() < cfg.window_probability:
        window_walls = set(rng.choice(4, size=int(rng.integers(1, 3)), replace=False).tolist())
    mirror_wall = int(rng.integers(4)) if rng.uniform() < cfg.mirror_probability else -1
    up = np.array([0, 1.0, 0])
    for k, (c, along, half_len, n) in enumerate(walls):
        # local frame: x along the wall, y up, z = inward normal; right-handed: along x up = n
        if np.dot(np.cross(along, up), n) < 0:
            along = -along
        if k not in window_walls:
            room.shapes.append(Shape("rectangle", frame_matrix(c, along * half_len, up * H / 2, n), wall_m, "wall"))
        else:
            _add_wall_with_window(room, rng, c, along, half_len, n, wall_m)
        taken: list[tuple[float, float]] = []  # occupied spans along the wall (mirror, pictures)
        if k == mirror_wall and k not in window_walls:
            mw, mh = float(rng.uniform(0.4, min(1.0, half_len * 0.6))), float(rng.uniform(0.5, 0.9))
            off = float(rng.uniform(-(half_len - mw - 0.2), half_len - mw - 0.2))
            centre = c + n * 0.002 + up * (float(rng.uniform(1.2, 1.6)) - H / 2) + along * off
            room.shapes.append(
                Shape("rectangle", frame_matrix(centre, along * mw, up * mh, n), add_material("mirror"), "mirror")
            )
            taken.append((off - mw, off + mw))
        if k not in window_walls:
            _add_pictures(room, rng, cfg, c, along, half_len, n, taken, add_material)
    if window_walls:
        room.sky = _random_sky(rng)


def _add_pictures(room: Room, rng, cfg: RoomConfig, c, along, half_len, n, taken, add_material) -> None:
    """Up to `cfg.pictures` framed patterns (posters, paintings) hung on a wall at eye height, clear of
    the spans in `taken`. Real rooms are full of such structure, and it is what glossy and metal
    surfaces visibly reflect: in a room of plain walls a polished metal box looks like a grey one."""
    H = room.size[1]
    up = np.array([0, 1.0, 0])
    for _ in range(int(rng.integers(cfg.pictures[0], cfg.pictures[1] + 1))):
        pw, ph = float(rng.uniform(0.25, 0.7)), float(rng.uniform(0.2, 0.5))
        if half_len - pw - 0.15 <= 0:
            continue
        off = float(rng.uniform(-(half_len - pw - 0.15), half_len - pw - 0.15))
        if any(off - pw < b + 0.1 and off + pw > a - 0.1 for a, b in taken):
            continue  # would overlap the mirror or another picture: leave this one out
        taken.append((off - pw, off + pw))
        centre = c + n * 0.003 + up * (float(rng.uniform(1.3, 1.8)) - H / 2) + along * off
        room.shapes.append(
            Shape("rectangle", frame_matrix(centre, along * pw, up * ph, n), add_material("picture"), "picture")
        )


def _add_wall_with_window(room: Room, rng, c, along, half_len, n, wall_m) -> None:
    """A wall made of four rectangles around a rectangular hole; the hole is recorded as a Window."""
    H = room.size[1]
    up = np.array([0, 1.0, 0])
    ww = float(rng.uniform(0.4, min(1.2, half_len - 0.3)))  # half width
    y0, y1 = float(rng.uniform(0.6, 1.0)), float(rng.uniform(1.9, min(2.4, H - 0.2)))
    off = float(rng.uniform(-(half_len - ww - 0.2), half_len - ww - 0.2))
    base = c - up * H / 2  # wall centre at floor height
    # (u-range along the wall, y-range) of each piece
    pieces = [
        ((-half_len, off - ww), (0, H)),
        ((off + ww, half_len), (0, H)),
        ((off - ww, off + ww), (0, y0)),
        ((off - ww, off + ww), (y1, H)),
    ]
    for (a0, a1), (b0, b1) in pieces:
        centre = base + along * (a0 + a1) / 2 + up * (b0 + b1) / 2
        room.shapes.append(
            Shape("rectangle", frame_matrix(centre, along * (a1 - a0) / 2, up * (b1 - b0) / 2, n), wall_m, "wall")
        )
    centre = base + along * off + up * (y0 + y1) / 2
    room.windows.append(Window(centre.tolist(), (along * ww).tolist(), (up * (y1 - y0) / 2).tolist(), n.tolist()))


def _random_sky(rng) -> Sky:
    elevation = math.radians(float(rng.uniform(12, 55)))
    azimuth = float(rng.uniform(0, 2 * math.pi))
    sun = [math.cos(elevation) * math.sin(azimuth), math.sin(elevation), math.cos(elevation) * math.cos(azimuth)]
    scale = float(rng.uniform(0.6, 2.0))
    zenith = (np.array([0.25, 0.45, 1.0]) * scale).tolist()
    horizon = (np.array([0.85, 0.9, 1.0]) * scale * 1.3).tolist()
    ground = (np.array([0.35, 0.3, 0.25]) * scale * 0.6).tolist()
    warm = np.array([1.0, float(rng.uniform(0.85, 0.95)), float(rng.uniform(0.7, 0.85))])
    return Sky(
        zenith, horizon, ground, sun, (warm * float(rng.uniform(150, 500))).tolist(), float(rng.uniform(2.5, 4.0))
    )


def _add_furniture(room: Room, rng, cfg: RoomConfig, add_material) -> list[Footprint]:
    W, _, D = room.size
    footprints: list[Footprint] = []
    tops: list[tuple[Footprint, float]] = []
    kinds = list(FURNITURE_KINDS)
    for _ in range(int(rng.integers(cfg.furniture[0], cfg.furniture[1] + 1))):
        kind = kinds[int(rng.integers(len(kinds)))]
        (w0, w1), (d0, d1), (h0, h1), wall_p = FURNITURE_KINDS[kind]
        w, d, h = float(rng.uniform(w0, w1)), float(rng.uniform(d0, d1)), float(rng.uniform(h0, h1))
        if h >= room.size[1] - 0.3:
            h = room.size[1] - 0.3
        for _attempt in range(30):
            fp = _draw_footprint(rng, W, D, w, d, rng.uniform() < wall_p)
            if fp is not None and not any(fp.overlaps(o, gap=0.05) for o in footprints):
                break
        else:
            continue  # no free spot for this piece: the room is full enough
        footprints.append(fp)
        mat = add_material("furniture", kind)
        parts, top = furniture_parts(kind, w, d, h)
        xz = fp.centre
        for centre, half in parts:
            c, s = math.cos(fp.yaw), math.sin(fp.yaw)
            world = np.array([xz[0] + c * centre[0] + s * centre[2], centre[1], xz[1] - s * centre[0] + c * centre[2]])
            room.shapes.append(Shape("cube", box_matrix(world, half, fp.yaw), mat, "furniture"))
        if top is not None:
            tops.append((fp, top))
    _add_objects(room, rng, cfg, add_material, tops)
    return footprints


def _draw_footprint(rng, W, D, w, d, against_wall: bool) -> Footprint | None:
    half = np.array([w / 2, d / 2])
    if against_wall:
        wall = int(rng.integers(4))
        yaw = [0.0, math.pi, math.pi / 2, -math.pi / 2][wall]  # local +z (front) faces into the room
        fp = Footprint(np.zeros(2), half, yaw)
        ext = np.abs(fp.axes().T) @ half  # world half extents of the rotated rectangle (x, z)
        if wall < 2:
            x = rng.uniform(-W / 2 + ext[0] + 0.05, W / 2 - ext[0] - 0.05) if W / 2 > ext[0] + 0.05 else None
            z = (-D / 2 + ext[1] + 0.01) * (1 if wall == 0 else -1)
        else:
            z = rng.uniform(-D / 2 + ext[1] + 0.05, D / 2 - ext[1] - 0.05) if D / 2 > ext[1] + 0.05 else None
            x = (-W / 2 + ext[0] + 0.01) * (1 if wall == 2 else -1)
        if x is None or z is None:
            return None
        fp.centre = np.array([x, z], dtype=float)
        return fp
    yaw = float(rng.uniform(0, 2 * math.pi))
    fp = Footprint(np.zeros(2), half, yaw)
    ext = np.abs(fp.axes().T) @ half
    if W / 2 <= ext[0] + 0.1 or D / 2 <= ext[1] + 0.1:
        return None
    fp.centre = np.array(
        [
            rng.uniform(-W / 2 + ext[0] + 0.1, W / 2 - ext[0] - 0.1),
            rng.uniform(-D / 2 + ext[1] + 0.1, D / 2 - ext[1] - 0.1),
        ]
    )
    return fp


def _add_objects(room: Room, rng, cfg: RoomConfig, add_material, tops) -> None:
    """Spheres and small boxes standing on table/cabinet tops, never overlapping each other."""
    if not tops:
        return
    placed: list[tuple[int, np.ndarray, float]] = []  # (top index, xz, bounding radius)
    for _ in range(int(rng.integers(cfg.objects[0], cfg.objects[1] + 1))):
        k = int(rng.integers(len(tops)))
        fp, top_y = tops[k]
        r = float(rng.uniform(*cfg.object_radius))
        if np.any(fp.half < r + 0.02):
            continue
        local = rng.uniform(-(fp.half - r - 0.02), fp.half - r - 0.02)
        xz = fp.centre + local @ fp.axes()
        if any(j == k and np.linalg.norm(xz - p) < r + q + 0.02 for j, p, q in placed):
            continue
        placed.append((k, xz, r))
        mat = add_material("object")
        if rng.uniform() < cfg.sphere_probability:
            room.shapes.append(Shape("sphere", sphere_matrix([xz[0], top_y + r, xz[1]], r), mat, "object"))
        else:
            half = r / math.sqrt(2) * np.array([1.0, float(rng.uniform(0.6, 1.4)), 1.0])
            yaw = float(rng.uniform(0, 2 * math.pi))
            room.shapes.append(Shape("cube", box_matrix([xz[0], top_y + half[1], xz[1]], half, yaw), mat, "object"))


def _add_lamps(room: Room, rng, cfg: RoomConfig, add_material) -> None:
    """Ceiling panels (one-sided rectangles facing down, 1 mm below the ceiling) with area emitters."""
    W, H, D = room.size
    n = int(rng.integers(cfg.lamps[0], cfg.lamps[1] + 1))
    if not room.windows:
        n = max(n, 1)
    lamp_m = add_material("lamp")
    boxes: list[Footprint] = []
    for _ in range(n):
        half = np.array([float(rng.uniform(*cfg.lamp_half_size)), float(rng.uniform(*cfg.lamp_half_size))])
        fp = Footprint(
            np.array([rng.uniform(-W / 2 + 0.6, W / 2 - 0.6), rng.uniform(-D / 2 + 0.6, D / 2 - 0.6)]), half, 0.0
        )
        if any(fp.overlaps(b, gap=0.2) for b in boxes):
            continue
        boxes.append(fp)
        kelvin_tint = np.array([1.0, float(rng.uniform(0.8, 0.95)), float(rng.uniform(0.6, 0.9))])
        if rng.uniform() < cfg.cool_lamp_probability:
            kelvin_tint = kelvin_tint[::-1].copy()  # a cool lamp now and then
        power = float(rng.uniform(6.0, 30.0)) * (0.1 / (half[0] * half[1])) ** 0.5
        centre = [fp.centre[0], H - 0.001, fp.centre[1]]
        room.shapes.append(
            Shape(
                "rectangle",
                frame_matrix(centre, [half[0], 0, 0], [0, 0, half[1]], [0, -1, 0]),
                lamp_m,
                "lamp",
                (kelvin_tint * power).tolist(),
            )
        )


def propose_camera(room: Room, rng, cfg: RoomConfig, footprints: list[Footprint]) -> Camera:
    """A camera standing in free floor space (0.3 m clear of furniture, 0.35 m from walls), at eye height,
    looking into the room with a small pitch."""
    W, H, D = room.size
    for _ in range(200):
        xz = np.array([rng.uniform(-W / 2 + 0.35, W / 2 - 0.35), rng.uniform(-D / 2 + 0.35, D / 2 - 0.35)])
        if not any(fp.contains(xz, margin=0.3) for fp in footprints):
            break
    height = float(rng.uniform(*cfg.camera_height))
    # look towards the room's far side: aim roughly at the centre, then perturb yaw
    to_centre = -xz if np.linalg.norm(xz) > 0.3 else rng.normal(size=2)
    yaw = math.atan2(to_centre[0], to_centre[1]) + float(rng.uniform(-0.6, 0.6))
    pitch = math.radians(float(rng.uniform(*cfg.camera_pitch_deg)))
    fwd = np.array([math.cos(pitch) * math.sin(yaw), math.sin(pitch), math.cos(pitch) * math.cos(yaw)])
    origin = np.array([xz[0], height, xz[1]])
    return Camera(origin.tolist(), (origin + fwd).tolist(), float(rng.uniform(*cfg.fov_x_deg)))
