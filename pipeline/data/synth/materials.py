"""Materials of the paper's GGX metallic workflow as plain data: base colour (albedo), roughness, metallic.

A material is either uniform or textured. Textures are procedural 2-D patterns with a few discrete
levels (checker tiles, wood planks, stripes, blotches) that mix two colours and, optionally, two
roughness values; the renderer looks them up with nearest filtering, so every rendered ground-truth
value is exactly one texel of the pattern (which the tests rely on).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TEXTURE_RESOLUTION = 64
PATTERNS = ("checker", "planks", "stripes", "blotches")


@dataclass
class Material:
    """GGX metallic-workflow parameters. `texture` (optional) is a pattern spec, see `pattern_levels`."""

    role: str
    albedo: list[float]  # base colour, linear RGB in [0, 1]
    roughness: float  # GGX roughness (alpha = roughness^2)
    metallic: float
    texture: dict | None = None  # {"pattern", "repeat", "seed", "albedo2", "roughness2"}

    def albedo_map(self) -> np.ndarray | None:
        """(T, T, 3) float32 base-colour texture, or None for a uniform material."""
        if self.texture is None:
            return None
        t = pattern_levels(self.texture)[..., None]
        return ((1 - t) * np.asarray(self.albedo) + t * np.asarray(self.texture["albedo2"])).astype(np.float32)

    def roughness_map(self) -> np.ndarray | None:
        """(T, T) float32 roughness texture, or None when roughness is uniform."""
        if self.texture is None or self.texture.get("roughness2") is None:
            return None
        t = pattern_levels(self.texture)
        return ((1 - t) * self.roughness + t * self.texture["roughness2"]).astype(np.float32)


def pattern_levels(spec: dict) -> np.ndarray:
    """(T, T) float array of mixing levels in [0, 1] for a pattern spec (deterministic in spec['seed'])."""
    n = TEXTURE_RESOLUTION
    rep = int(spec["repeat"])
    rng = np.random.default_rng(int(spec["seed"]))
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    cell = max(n // rep, 1)
    kind = spec["pattern"]
    if kind == "checker":
        return (((i // cell) + (j // cell)) % 2).astype(np.float64)
    if kind == "planks":
        # rows of planks with staggered joints; each plank one of 4 shades
        row = i // cell
        shift = (row * 7) % 3 * cell
        plank = (j + shift) // (2 * cell)
        shades = rng.integers(0, 4, size=(rep + 1, n))
        out = shades[np.minimum(row, rep), plank % n] / 3.0
        out[(i % cell) == 0] = 1.0  # dark seam between rows
        return out
    if kind == "stripes":
        return (((j // max(cell // 2, 1)) % 3) / 2.0).astype(np.float64)
    if kind == "blotches":
        coarse = rng.integers(0, 4, size=(rep, rep)) / 3.0
        return coarse[np.minimum(i // cell, rep - 1), np.minimum(j // cell, rep - 1)]
    raise ValueError(f"unknown texture pattern {kind!r} (choose from {PATTERNS})")


def hsv_colour(rng, hue, sat, val) -> list[float]:
    """A linear RGB colour from hue/saturation/value ranges (value is the linear max channel)."""
    h, s, v = rng.uniform(*hue) % 1.0, rng.uniform(*sat), rng.uniform(*val)
    k = (np.array([5.0, 3.0, 1.0]) + h * 6) % 6
    rgb = v - v * s * np.clip(np.minimum(k, 4 - k), 0, 1)
    return np.clip(rgb, 0.0, 1.0).tolist()


def metal_colour(rng) -> list[float]:
    """Base colour (= normal-incidence reflectance F0) of a real metal: bright, as measured F0 of common
    metals lies between about 0.5 (iron) and 0.97 (silver); neutral (steel, aluminium, chrome) or warm
    (gold, copper, brass). A dark or saturated green 'metal' does not exist and only blurs the cue."""
    if rng.uniform() < 0.7:
        return hsv_colour(rng, (0.0, 1.0), (0.0, 0.12), (0.5, 0.97))
    return hsv_colour(rng, (0.03, 0.14), (0.25, 0.7), (0.6, 0.95))


def _texture(rng, albedo2, roughness2=None, patterns=PATTERNS) -> dict:
    return {
        "pattern": str(rng.choice(patterns)),
        "repeat": int(rng.choice([2, 4, 8])),
        "seed": int(rng.integers(2**31)),
        "albedo2": albedo2,
        "roughness2": roughness2,
    }


# Which materials each kind of furniture is made of, as (material, probability) in the order drawn. Real
# cabinets, tables and shelves come in steel; sofas and beds are upholstered. A metal sofa or bed does
# not exist, and a 2 m metal slab is most of a view's metal; keeping it out is a semantic cue real photos
# carry too.
FURNITURE_MIX = {
    "cabinet": (("wood", 0.35), ("metal", 0.3), ("lacquer", 0.15), ("painted", 0.2)),
    "table": (("wood", 0.4), ("metal", 0.3), ("lacquer", 0.15), ("painted", 0.15)),
    "shelf": (("wood", 0.45), ("metal", 0.35), ("painted", 0.2)),
    "sofa": (("fabric", 0.6), ("leather", 0.25), ("painted", 0.15)),
    "bed": (("fabric", 0.8), ("painted", 0.2)),
    "block": (("wood", 0.25), ("metal", 0.2), ("lacquer", 0.15), ("fabric", 0.2), ("painted", 0.2)),
}


def _furniture_material(rng, kind: str | None, u: float) -> Material:
    """One piece of furniture's material; `u` ~ U(0, 1) picks the kind of material from FURNITURE_MIX."""
    mix = FURNITURE_MIX.get(kind or "block")
    if mix is None:
        raise ValueError(f"unknown furniture kind {kind!r} (choose from {sorted(FURNITURE_MIX)})")
    names, probs = zip(*mix, strict=True)
    which = names[min(int(np.searchsorted(np.cumsum(probs), u, side="right")), len(names) - 1)]
    role = "furniture"
    if which == "wood":
        base = hsv_colour(rng, (0.05, 0.1), (0.4, 0.8), (0.1, 0.5))
        other = hsv_colour(rng, (0.04, 0.1), (0.4, 0.8), (0.05, 0.35))
        return Material(
            role, base, float(rng.uniform(0.3, 0.7)), 0.0, _texture(rng, other, None, ("planks", "stripes"))
        )
    if which == "metal":
        return Material(role, metal_colour(rng), float(rng.uniform(0.05, 0.5)), 1.0)
    if which == "lacquer":  # glossy plastic / lacquer
        return Material(role, hsv_colour(rng, (0.0, 1.0), (0.3, 0.9), (0.1, 0.8)), float(rng.uniform(0.05, 0.2)), 0.0)
    if which == "fabric":  # patterned upholstery
        base = hsv_colour(rng, (0.0, 1.0), (0.2, 0.8), (0.1, 0.7))
        other = hsv_colour(rng, (0.0, 1.0), (0.2, 0.8), (0.1, 0.7))
        return Material(
            role, base, float(rng.uniform(0.85, 1.0)), 0.0, _texture(rng, other, None, ("checker", "blotches"))
        )
    if which == "leather":
        return Material(role, hsv_colour(rng, (0.0, 0.12), (0.3, 0.8), (0.03, 0.4)), float(rng.uniform(0.3, 0.6)), 0.0)
    return Material(role, hsv_colour(rng, (0.0, 1.0), (0.0, 0.8), (0.05, 0.9)), float(rng.uniform(0.2, 1.0)), 0.0)


PALETTES = ("standard", "loft")


def _loft_material(rng, role: str, u: float) -> Material | None:
    """The `loft` palette, a style the standard rooms never show: grey concrete floors, saturated glossy
    paint on the walls, dark ceilings, and mostly metal or glossy plastic objects. None for the roles it
    leaves to the standard draws (furniture, mirrors, pictures, lamps)."""
    if role == "floor":
        base = hsv_colour(rng, (0.0, 1.0), (0.0, 0.08), (0.15, 0.45))
        rough = float(rng.uniform(0.3, 0.8))
        if u < 0.5:
            other = hsv_colour(rng, (0.0, 1.0), (0.0, 0.08), (0.05, 0.3))
            return Material(role, base, rough, 0.0, _texture(rng, other, None, ("checker",)))
        return Material(role, base, rough, 0.0)
    if role == "wall":
        return Material(
            role, hsv_colour(rng, (0.0, 1.0), (0.45, 0.9), (0.15, 0.6)), float(rng.uniform(0.15, 0.45)), 0.0
        )
    if role == "ceiling":
        return Material(role, [float(rng.uniform(0.15, 0.4))] * 3, float(rng.uniform(0.6, 1.0)), 0.0)
    if role == "object":
        if u < 0.55:
            return Material(role, metal_colour(rng), float(np.exp(rng.uniform(np.log(0.02), np.log(0.4)))), 1.0)
        rough = float(np.exp(rng.uniform(np.log(0.02), np.log(0.3))))
        return Material(role, hsv_colour(rng, (0.0, 1.0), (0.5, 1.0), (0.1, 0.9)), rough, 0.0)
    return None


def random_material(
    rng: np.random.Generator, role: str, kind: str | None = None, palette: str = "standard"
) -> Material:
    """Draw a material for a surface role: floor, wall, ceiling, furniture, object, mirror, picture, lamp.
    `kind` is the furniture kind (see scene.FURNITURE_KINDS), which decides which materials it can be made of.
    `palette` (`PALETTES`): `standard`, the training rooms' mix, or `loft` (`_loft_material`), another
    style for out-of-distribution tests.

    The mix covers mirror-like to matte roughness, metallic 0, 1 and in between, and textured albedo.
    """
    if palette not in PALETTES:
        raise ValueError(f"synth.room.palette={palette!r}: choose one of {PALETTES}")
    u = rng.uniform()
    if palette == "loft":
        loft = _loft_material(rng, role, u)
        if loft is not None:
            return loft
    if role == "floor":
        base = hsv_colour(rng, (0.05, 0.12), (0.3, 0.7), (0.15, 0.6))
        rough = float(rng.uniform(0.05, 0.5))  # glossy floors are common indoors
        if u < 0.65:
            other = hsv_colour(rng, (0.0, 0.15), (0.2, 0.6), (0.05, 0.5))
            rough2 = float(rng.uniform(0.4, 0.9)) if rng.uniform() < 0.4 else None
            return Material(role, base, rough, 0.0, _texture(rng, other, rough2, ("checker", "planks")))
        return Material(role, base, rough, 0.0)
    if role == "wall":
        base = hsv_colour(rng, (0.0, 1.0), (0.0, 0.35), (0.35, 0.85))
        if u < 0.2:
            other = hsv_colour(rng, (0.0, 1.0), (0.0, 0.4), (0.3, 0.8))
            return Material(role, base, float(rng.uniform(0.6, 1.0)), 0.0, _texture(rng, other, None, ("stripes",)))
        return Material(role, base, float(rng.uniform(0.5, 1.0)), 0.0)
    if role == "ceiling":
        return Material(role, [float(rng.uniform(0.7, 0.9))] * 3, float(rng.uniform(0.7, 1.0)), 0.0)
    if role == "mirror":
        return Material(role, [float(rng.uniform(0.88, 0.96))] * 3, 0.02, 1.0)
    if role == "picture":  # poster / painting: a high-contrast pattern of two unrelated colours
        base = hsv_colour(rng, (0.0, 1.0), (0.2, 0.9), (0.3, 0.9))
        other = hsv_colour(rng, (0.0, 1.0), (0.3, 1.0), (0.02, 0.4))
        return Material(
            role,
            base,
            float(rng.uniform(0.3, 0.9)),
            0.0,
            _texture(rng, other, None, ("checker", "stripes", "blotches")),
        )
    if role == "lamp":
        return Material(role, [0.9, 0.9, 0.9], 0.5, 0.0)
    if role == "furniture":
        return _furniture_material(rng, kind, u)
    if role == "object":
        if u < 0.35:  # solid metal
            return Material(role, metal_colour(rng), float(np.exp(rng.uniform(np.log(0.02), np.log(0.6)))), 1.0)
        rough = float(np.exp(rng.uniform(np.log(0.02), np.log(1.0))))  # log-uniform: many glossy ones
        metallic = float(rng.uniform(0.0, 1.0)) if u < 0.45 else 0.0  # a few painted/worn metal blends
        return Material(role, hsv_colour(rng, (0.0, 1.0), (0.0, 0.9), (0.05, 0.95)), rough, metallic)
    raise ValueError(f"unknown material role {role!r}")
