"""One view of a generated room: ground-truth maps at pixel centres, the beauty image, lighting probes.

All outputs follow docs/design.md, sections 3 and 4: view space is OpenGL (x right, y up, camera looks down -z),
depth is z-depth in millimetres (inf on misses), normals are unit view-space vectors.
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.data.synth import mitsuba_backend as mb
from pipeline.data.synth.scene import Camera
from pipeline.ops.envmap import hemisphere_directions, sphere_directions, stratified_square, texel_directions

PROBE_OFFSET_M = 2e-3  # probe rays start this far along the normal, clear of the surface they sit on


@dataclass
class LightingConfig:
    """Lighting ground truth per view (our extension, see docs/data.md)."""

    surface_stride: int = 20  # a surface probe every `stride` pixels (grid centred in the image)
    hemi_size: tuple[int, int] = (8, 16)  # (theta rows over [0, pi/2], phi columns over [0, 2 pi))
    free_points: int = 4
    sphere_size: tuple[int, int] = (16, 32)  # (theta rows over [0, pi], phi columns)
    spp: int = 64  # paths per texel, each along its own direction: a k x k stratified grid over the texel

    def __post_init__(self):
        k = math.isqrt(int(self.spp))
        if self.spp < 4 or k * k != self.spp or k % 2:
            raise ValueError(
                f"synth.lighting.spp={self.spp}: must be the square of an even number (4, 16, 64, 144, 256: "
                "k x k directions stratified over each texel, paired for the standard error)"
            )

    @property
    def strata(self) -> int:
        """k: each texel is sampled on a k x k grid of its (cos theta, phi) rectangle."""
        return math.isqrt(int(self.spp))


def gbuffer(scene, camera: Camera, width: int, height: int) -> dict[str, np.ndarray]:
    """InteriorVerse maps from one exact ray per pixel centre.

    Returns im-free maps: albedo (H,W,3), normal (H,W,3) view space, depth (H,W) mm (inf on misses, finite on
    lamps), material (H,W,2), mask (H,W) (hit and not a lamp), plus `t` (H,W) ray length in metres.
    """
    w2v = mb.world_from_view(camera)
    dirs_view = mb.view_rays(camera.fov_x_deg, width, height)
    dirs = dirs_view @ w2v[:3, :3].T
    hit = mb.intersect(scene, np.broadcast_to(w2v[:3, 3], dirs.shape), dirs)
    z = hit["t"] * -dirs_view[:, 2]  # z-depth = ray length x cos(angle to the optical axis)
    normal = hit["normal"] @ w2v[:3, :3]  # world -> view: rows of the rotation's transpose
    normal[~hit["hit"]] = 0.0
    mask = hit["hit"] & ~hit["lamp"]
    shape = (height, width)
    return {
        "albedo": hit["albedo"].reshape(*shape, 3),
        "normal": normal.reshape(*shape, 3).astype(np.float32),
        "depth": np.where(hit["hit"], z * 1000.0, np.inf).reshape(shape).astype(np.float32),
        "material": np.stack([hit["roughness"], hit["metallic"]], -1).reshape(*shape, 2),
        "mask": mask.reshape(shape).astype(np.float32),
        "t": hit["t"].reshape(shape),
    }


def lighting_probes(
    scene, camera: Camera, gb: dict, cfg: LightingConfig, rng: np.random.Generator, seed: int
) -> dict[str, np.ndarray]:
    """Incident radiance maps: hemispheres at a grid of valid surface pixels and full spheres at free
    points (between the camera and a visible surface, hence never inside furniture). Positions, normals
    and directions in view space; radiance is L_i(p, w) arriving at p from w (the ray p + t w)."""
    height, width = gb["mask"].shape
    w2v = mb.world_from_view(camera)
    rot, origin = w2v[:3, :3], w2v[:3, 3]
    s = cfg.surface_stride
    rows, cols = np.meshgrid(np.arange(s // 2, height, s), np.arange(s // 2, width, s), indexing="ij")
    rows, cols = rows.ravel(), cols.ravel()
    keep = gb["mask"][rows, cols] > 0
    pix = np.stack([rows[keep], cols[keep]], -1)
    dirs_view = mb.view_rays(camera.fov_x_deg, width, height).reshape(height, width, 3)
    t = gb["t"][pix[:, 0], pix[:, 1]]
    surf_pos = dirs_view[pix[:, 0], pix[:, 1]] * t[:, None]
    surf_n = gb["normal"][pix[:, 0], pix[:, 1]].astype(np.float64)
    surf_n /= np.linalg.norm(surf_n, axis=-1, keepdims=True)
    hemi = hemisphere_directions(surf_n, *cfg.hemi_size)

    # free points: a random fraction of the way to a random visible surface, >= 0.1 m in front of it
    valid = np.flatnonzero((gb["mask"] > 0).ravel() & (gb["t"].ravel() > 0.5))
    picks = rng.choice(valid, size=min(cfg.free_points, len(valid)), replace=False) if len(valid) else np.zeros(0, int)
    frac = rng.uniform(0.25, 0.75, size=len(picks))
    dist = np.minimum(frac * gb["t"].ravel()[picks], gb["t"].ravel()[picks] - 0.1)
    free_pos = dirs_view.reshape(-1, 3)[picks] * dist[:, None]
    sphere = np.broadcast_to(sphere_directions(*cfg.sphere_size), (len(picks), *cfg.sphere_size, 3))

    def query(pos_view, size, normals, key):
        """Texel averages (P, rows, cols, 3) and their standard errors for probes at pos_view (P, 3)."""
        rows, cols = size
        texels, k = rows * cols, cfg.strata
        gen = torch.Generator().manual_seed(int(seed) * 2 + key)  # the directions' jitter
        mean = np.zeros((len(pos_view), rows, cols, 3), np.float32)
        se = np.zeros_like(mean)
        per_chunk = max(1, (1 << 20) // (texels * k * k))  # probes per batch of rays
        for c, start in enumerate(range(0, len(pos_view), per_chunk)):
            sl = slice(start, min(len(pos_view), start + per_chunk))
            n = sl.stop - sl.start
            row = torch.arange(rows).repeat_interleave(cols).repeat(n)
            col = torch.arange(cols).repeat(rows * n)
            u = stratified_square(k, n * texels, gen)
            nrm = None if normals is None else torch.from_numpy(normals[sl]).repeat_interleave(texels, 0)
            d_view = texel_directions(row, col, u, rows, cols, nrm).numpy().reshape(-1, 3)
            o_view = pos_view[sl] + (normals[sl] * PROBE_OFFSET_M if normals is not None else 0.0)
            o = np.repeat(o_view @ rot.T + origin, texels * k * k, axis=0)
            L, _ = mb.radiance(scene, o, d_view @ rot.T, 1, seed=(seed * 2 + key) * 4099 + c)
            L = L.reshape(n, rows, cols, k * k, 3)
            mean[sl] = L.mean(3)
            se[sl] = stratified_stderr(L.reshape(n, rows, cols, k, k, 3))
        return mean, se

    surf_L, surf_se = query(surf_pos, cfg.hemi_size, surf_n, 0)
    free_L, free_se = query(free_pos, cfg.sphere_size, None, 1)
    return {
        "surf_pixel": pix.astype(np.int32),
        "surf_position": surf_pos.astype(np.float32),
        "surf_normal": surf_n.astype(np.float32),
        "surf_directions": hemi.astype(np.float32),
        "surf_radiance": surf_L,
        "surf_stderr": surf_se,
        "free_position": free_pos.astype(np.float32),
        "free_directions": np.array(sphere, np.float32),
        "free_radiance": free_L,
        "free_stderr": free_se,
        "probe_offset_m": np.float32(PROBE_OFFSET_M),
        "spp": np.int32(cfg.spp),
    }


def stratified_stderr(samples: np.ndarray) -> np.ndarray:
    """Standard error of the mean of one sample per cell of a k x k stratified grid, samples (..., k, k, C)
    with k even -> (..., C). Neighbouring cells are collapsed into pairs: with N = k^2 cells,
    Var(mean) ~ sum over pairs of (a - b)^2 / N^2, which is unbiased up to the (small, non-negative)
    squared difference of the two cells' own means; the plain sample spread would also count the
    variation between cells that stratification removes, overstating the error several-fold."""
    k = samples.shape[-2]
    if k % 2:
        raise ValueError(f"stratified_stderr: need an even grid, got {k} x {k} (synth.lighting.spp)")
    diff = samples[..., 0::2, :] - samples[..., 1::2, :]  # (..., k, k/2, C)
    return np.sqrt((diff**2).sum((-3, -2)) / k**4)


def camera_is_usable(scene, camera: Camera, min_valid: float = 0.6, min_median_depth_m: float = 1.0) -> bool:
    """Cheap 16x12-ray check that a proposed view sees mostly valid surfaces and not a wall at arm's length."""
    gb = gbuffer(scene, camera, 16, 12)
    valid = gb["mask"] > 0
    return bool(valid.mean() >= min_valid and np.median(gb["depth"][valid]) / 1000.0 >= min_median_depth_m)


class Timer:
    """Accumulates wall seconds per named phase: `with timer("render"): ...`."""

    def __init__(self):
        self.seconds: dict[str, float] = {}

    @contextlib.contextmanager
    def __call__(self, name: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0
