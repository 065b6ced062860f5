"""`python -m pipeline.bench.shading_placement`: does the photo's own shading place the ceiling lamps?

`bench.lamp_placement` found that a CNN trained on the training rooms places the lamps barely better
than the rooms' mean placement (surface nMSE 0.85 against 0.87; the true placement 0.46). That network
sees the photo only as a picture. The lamps also light what the camera sees: a wall under a lamp is
brighter than one far from it, with the falloff and cosines of a known geometry. This bench asks how
much of the placement that shading determines, with no learning: per test view, on its ground-truth
G-buffers (an upper bound for predicted ones), the ceiling of the true box
(`bench.roombox_floor.true_box`) is cut into `--grid` x `--grid` cells as in `bench.lamp_placement`,
and each visible pixel's radiance is explained as a Lambertian surface lit by every cell at its own
unknown radiance, by the walls and floor, and by one ambient term:

    L_p = albedo_p / pi * (sum_c w_c E_pc + K_p + u U_p) + albedo_p * b,    w_c, u, b >= 0 (per RGB channel)

where E_pc is the irradiance (W m^-2 per unit radiance) the cell would cast on the pixel's point and
normal (`irradiance_matrix`: the cell cut into `--sub` x `--sub` patches, each a small area light with
both cosines and the inverse square; occlusion ignored), K_p the light of the wall and floor texels the
camera saw, at what it saw there, and U_p the transfer from the unseen ones, at one unknown radiance u
(`bounce_terms`, `--no-bounce` leaves both out): the true lamps' direct light is a minority of what the
fitted pixels show (the report's `true_lamps_direct_share`). The
weights are solved by non-negative least squares (`fit_view`) on up to `--pixels` pixels (metallic ones,
dark albedo and the ceiling itself, which no ceiling lamp lights, left out), refitted once without the
`--trim` share of pixels the model explains worst (specular highlights of glossy surfaces, shadows of
furniture). With `--material` the fit reads a trained MaterialNet's albedo, normals, material and depth
(times its export's `depth_scale`) instead, as a deployed fit would (`--predicted` takes only some of
them, to find which map's error costs the fit). The ceiling's cells are on the room file's box, or with
`--box estimated` on the box `ops.roombox` finds from the fit's own depth and normals, which the
placements and the complete source below then use too: what a deployed fit could do. `--depth-noise E`
multiplies the depth the fit reads (true or predicted) by 1 + E f, f a smooth standard-normal field per
view (`noisy_depth`): how large a smooth depth error the fit tolerates.

A least-squares fit is a point estimate, and the light's squared error punishes a lamp put in the wrong
cell twice; the placement used is the fit's shrunk towards the training rooms' mean placement, the
fit's weight (0 to 1 by 0.1) the one whose light error is lowest on the validation views, and the fit's
energy is scaled by the median ratio of true to fitted lamp energy on those views (the fit also lends
the lamps bounced light the model leaves out). Nothing of the test views but their photo and G-buffers
enters a fit.

Scored as `bench.lamp_placement` scores its placements (tiny's blend with the image's pixel as the local
source, ceiling directions at the placement's cell plus the photo's mean, the rest at the photo's mean):
the fit's own placement and the shrunk one with the true lamp energy spread by them (placement scored
alone, comparable with that bench's CNN), the fit's own radiances, and the shrunk placement at the
calibrated energy. Then the whole out-of-view light with nothing true but the box (`CompleteSources`: the
texels the camera saw, the calibrated lamps on the unseen ceiling, the image's mean elsewhere), with and
without the lamps, and with `--light-net` a trained LightNet's branch on the same directions
(`blend_floor.network_sources`); every row paired by test view against the training rooms' mean
placement and the branch, with bootstrap intervals. With `--learned-seeds N`, `bench.lamp_placement`'s
network is trained on the training views (whose fits are made alike) from the photo alone and from the
photo and the fit's placement, N seeds each: can a network learn when to trust the fit? Writes
reports/bench/shading_placement.json (or `--name`) and a PNG of the light errors and the first views'
true and fitted ceilings.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure
from tqdm import tqdm

from pipeline.bench.blend_floor import network_sources, network_system
from pipeline.bench.common import add_threads_option, apply_threads, publish
from pipeline.bench.lamp_placement import (
    CEILING,
    ceiling_lamps,
    distribution,
    light_bars,
    light_scores,
    luminance,
    paired_differences,
    photo_input,
    placement_scores,
    placement_summary,
    train,
)
from pipeline.bench.roombox_floor import estimated_box, true_box
from pipeline.bench.visible_light import TEXTURE_SIZE, box_texels, observed, room_lamps, seen_lookup
from pipeline.ops.camera import backproject_views
from pipeline.ops.roombox import OTHER_AXES

CEILING_CLEARANCE_M = 0.05  # points this close below the ceiling are the ceiling (no ceiling lamp lights them)
MIN_ALBEDO = 0.02  # darker pixels carry almost no shading signal
MAX_METALLIC = 0.5  # metals reflect, they do not shade


def ceiling_patches(box, grid: int, sub: int) -> tuple[torch.Tensor, float]:
    """Centres (grid * grid, sub * sub, 3) of the patches of each ceiling cell, box frame (cells row-major:
    rows along the box's z, columns along its x, as `lamp_placement.ceiling_lamps`), and one patch's area
    (m^2), float64."""
    _, lo, hi = (t.double() for t in box)
    n = grid * sub
    x = lo[0] + (torch.arange(n, dtype=torch.float64) + 0.5) / n * (hi[0] - lo[0])
    z = lo[2] + (torch.arange(n, dtype=torch.float64) + 0.5) / n * (hi[2] - lo[2])
    zz, xx = torch.meshgrid(z, x, indexing="ij")
    q = torch.stack([xx, torch.full_like(xx, float(hi[1])), zz], -1)  # (n, n, 3)
    q = q.view(grid, sub, grid, sub, 3).permute(0, 2, 1, 3, 4).reshape(grid * grid, sub * sub, 3)
    area = float((hi[0] - lo[0]) * (hi[2] - lo[2])) / (n * n)
    return q, area


def irradiance_matrix(points: torch.Tensor, normals: torch.Tensor, box, grid: int, sub: int) -> torch.Tensor:
    """(P, grid * grid) irradiance (W m^-2) at points (P, 3) with unit normals (P, 3), both in the box
    frame, from each ceiling cell emitting unit radiance downwards: the sum over its patches of
    A cos(theta_surface) cos(theta_lamp) / r^2 (each patch a small area light; no occlusion), float64."""
    centres, area = ceiling_patches(box, grid, sub)
    d = centres[None] - points[:, None, None]  # (P, C, S, 3) towards the patch
    r2 = (d**2).sum(-1).clamp(min=1e-6)
    r = r2.sqrt()
    cos_surface = ((d * normals[:, None, None]).sum(-1) / r).clamp(min=0)
    cos_lamp = (d[..., 1] / r).clamp(min=0)  # the patch faces -y (down): cos = (y_lamp - y_point) / r
    return (area * cos_surface * cos_lamp / r2).sum(-1)


BOUNCE_TEXELS = 16  # texels a side of each box face whose seen radiance is a known bounce in the fit


def box_texel_geometry(box, size: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Centres (6 size^2, 3), inward unit normals (6 size^2, 3) and areas (6 size^2,) m^2 of the texels of
    the box's faces, box frame, float64, in `ops.roombox`'s flat order (face, t, s; face 2 axis + side,
    side 1 the axis's high wall; s and t along the axis's `OTHER_AXES`)."""
    _, lo, hi = (t.double() for t in box)
    centres, normals, areas = [], [], []
    steps = (torch.arange(size, dtype=torch.float64) + 0.5) / size
    for face in range(6):
        axis, side = divmod(face, 2)
        a_s, a_t = OTHER_AXES[axis]
        tt, ss = torch.meshgrid(
            lo[a_t] + steps * (hi[a_t] - lo[a_t]), lo[a_s] + steps * (hi[a_s] - lo[a_s]), indexing="ij"
        )
        c = torch.zeros(size, size, 3, dtype=torch.float64)
        c[..., a_s], c[..., a_t], c[..., axis] = ss, tt, (hi if side else lo)[axis]
        n = torch.zeros(size * size, 3, dtype=torch.float64)
        n[:, axis] = -1.0 if side else 1.0
        centres.append(c.reshape(-1, 3))
        normals.append(n)
        areas.append(torch.full((size * size,), float((hi[a_s] - lo[a_s]) * (hi[a_t] - lo[a_t])) / size**2))
    return torch.cat(centres), torch.cat(normals), torch.cat(areas).double()


def texel_transfer(points: torch.Tensor, normals: torch.Tensor, box, size: int) -> torch.Tensor:
    """(P, 6 size^2) irradiance (W m^-2) at points (P, 3) with unit normals (P, 3), box frame, from each
    texel of `box_texel_geometry` at unit radiance: A cos cos / r^2 at the texel's centre, the distance
    held at least one texel side (a point beside a face does not meet a singular texel), float64."""
    centres, tnormals, areas = box_texel_geometry(box, size)
    side = float((box[2] - box[1]).max()) / size
    d = centres[None] - points[:, None]  # (P, K, 3) towards the texel
    r2 = (d**2).sum(-1).clamp(min=side**2)
    r = r2.sqrt()
    cos_surface = ((d * normals[:, None]).sum(-1) / r).clamp(min=0)
    cos_texel = (-(d * tnormals[None]).sum(-1) / r).clamp(min=0)
    return areas[None] * cos_surface * cos_texel / r2


def bounce_terms(batch: dict, gb: dict, box, px: dict) -> dict:
    """The light the fitted pixels px get from the box's walls and floor (not the ceiling, whose cells are
    fitted): from the texels the camera saw, at what it saw there (`visible_light.observed` of the one-view
    `batch`'s photo on its G-buffers gb), as a known irradiance (P, 3); from the unseen ones, their summed
    transfer (P,) for one unknown radiance."""
    seen_radiance, count = observed(batch, gb, box, BOUNCE_TEXELS)
    face = torch.arange(len(count)) // BOUNCE_TEXELS**2
    walls = face != CEILING
    transfer = texel_transfer(px["point"], px["normal"], box, BOUNCE_TEXELS)
    seen = walls & (count > 0)
    return {
        "known": transfer[:, seen] @ seen_radiance[seen].double(),
        "unseen": transfer[:, walls & (count == 0)].sum(1),
    }


def shading_pixels(item: dict, box, pixels: int, seed: int) -> dict:
    """The pixels a view's fit uses (module docstring) with their box-frame point and normal (P, 3),
    albedo and radiance (P, 3), float64; at most `pixels`, drawn without replacement by `seed`."""
    rot = box[0].double()
    depth = item["depth"][0].double()
    valid = item["mask"][0].bool() & (depth > 0)
    points = backproject_views(torch.where(valid, depth, torch.zeros_like(depth))[None], float(item["fov_x_deg"]))[0]
    q = points.reshape(-1, 3) @ rot
    n = item["normal"].double().permute(1, 2, 0).reshape(-1, 3) @ rot
    albedo = item["albedo"].double().permute(1, 2, 0).reshape(-1, 3)
    radiance = item["im"].double().clamp(min=0).permute(1, 2, 0).reshape(-1, 3)
    metallic = item["material"][1].double().reshape(-1)
    keep = (
        valid.reshape(-1)
        & (metallic < MAX_METALLIC)
        & (luminance(albedo) > MIN_ALBEDO)
        & (q[:, 1] < float(box[2][1]) - CEILING_CLEARANCE_M)
    )
    index = torch.nonzero(keep).squeeze(-1)
    if len(index) > pixels:
        g = torch.Generator().manual_seed(seed)
        index = index[torch.randperm(len(index), generator=g)[:pixels]]
    return {"point": q[index], "normal": n[index], "albedo": albedo[index], "radiance": radiance[index]}


def _nnls(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    from scipy.optimize import nnls

    scale = np.linalg.norm(a, axis=0)
    scale[scale == 0] = 1.0
    x, _ = nnls(a / scale, b, maxiter=50 * a.shape[1])
    return x / scale


def fit_view(px: dict, box, grid: int, sub: int, trim: float, bounce: dict | None = None) -> dict:
    """Per-cell radiance (grid * grid, 3) and ambient radiance b (3,) explaining the pixels `px` (module
    docstring), each RGB channel its own non-negative least squares; refitted once without the `trim`
    share of pixels with the largest absolute residual. With `bounce` (`bounce_terms`) the seen walls'
    light is subtracted as known and the unseen walls get one more non-negative radiance. Also the
    relative residual of the kept pixels. A view without pixels to fit gets no lamp and no ambient light
    (a uniform placement), counted by `run`."""
    if len(px["point"]) == 0:
        zeros = torch.zeros(grid * grid, 3, dtype=torch.float64)
        return {"cells": zeros, "ambient": zeros[0], "relative_residual": math.nan, "pixels": 0}
    E = irradiance_matrix(px["point"], px["normal"], box, grid, sub).numpy()  # (P, C)
    albedo, radiance = px["albedo"].numpy(), px["radiance"].numpy()
    known = np.zeros_like(radiance) if bounce is None else bounce["known"].numpy()
    cells = np.zeros((E.shape[1], 3))
    ambient = np.zeros(3)
    keep = np.ones(len(E), bool)
    for attempt in range(2 if trim > 0 else 1):
        residual = np.zeros_like(radiance)
        for c in range(3):
            k = albedo[:, c : c + 1] / math.pi
            columns = [k * E] + ([k * bounce["unseen"].numpy()[:, None]] if bounce is not None else [])
            a = np.concatenate([*columns, albedo[:, c : c + 1]], 1)
            target = radiance[:, c] - k[:, 0] * known[:, c]
            x = _nnls(a[keep], target[keep])
            cells[:, c], ambient[c] = x[: E.shape[1]], x[-1]
            residual[:, c] = a @ x - target
        if attempt == 0 and trim > 0:
            err = np.abs(residual).sum(1)
            keep = err <= np.quantile(err, 1 - trim)
    rel = float(np.sqrt((residual[keep] ** 2).sum() / max((radiance[keep] ** 2).sum(), 1e-30)))
    return {
        "cells": torch.from_numpy(cells),
        "ambient": torch.from_numpy(ambient),
        "relative_residual": rel,
        "pixels": int(keep.sum()),
    }


PREDICTABLE = ("albedo", "normal", "material", "depth")  # the maps --predicted can take from MaterialNet


def predicted_maps(item: dict, material_net, depth_scale: float, keys=PREDICTABLE) -> dict:
    """`item` with the maps in `keys` (of albedo, normal, material and depth: metres, 0 outside the mask)
    replaced by a trained MaterialNet's prediction from its photo; the others stay the truth."""
    with torch.no_grad():
        pred = material_net(item["im"][None])
    out = {**item, **{k: pred[k][0] for k in ("albedo", "normal", "material") if k in keys}}
    if "depth" in keys:
        depth = pred["depth"][0] * depth_scale
        out["depth"] = torch.where(item["mask"], depth, torch.zeros_like(depth))
    return out


DEPTH_NOISE_KNOTS = (3, 4)  # rows x columns of the random field --depth-noise multiplies a view's depth by


def noisy_depth(maps: dict, noise: float, seed: int) -> dict:
    """`maps` with its depth times (1 + noise * f), f a smooth random field (`DEPTH_NOISE_KNOTS` standard
    normal knots, bicubic over the image) drawn from `seed`: a depth whose error is smooth and of a known
    size, to find how much error the fit tolerates. noise 0 leaves the maps as they are."""
    if noise == 0:
        return maps
    g = torch.Generator().manual_seed(seed)
    knots = torch.randn(1, 1, *DEPTH_NOISE_KNOTS, generator=g, dtype=torch.float64)
    depth = maps["depth"]
    field = torch.nn.functional.interpolate(knots, size=depth.shape[-2:], mode="bicubic", align_corners=True)[0]
    return {**maps, "depth": (depth.double() * (1 + noise * field)).clamp(min=0).to(depth.dtype)}


def training_mean_placement(data_dir: Path, source_root: Path, grid: int) -> torch.Tensor:
    """(1, grid * grid) mean lamp placement (`lamp_placement.distribution`) over the training views, from
    their room files and cameras alone."""
    from pipeline.data.datasets import read_manifest

    ids = read_manifest(data_dir)["splits"]["train"]["views"]
    if not ids:
        raise ValueError(f"{data_dir}/manifest.json: the train split is empty")
    cells = torch.stack(
        [ceiling_lamps(room_lamps(source_root, i), true_box(source_root, i), grid) for i in tqdm(ids, desc="train")]
    )
    return distribution(cells).mean(0, keepdim=True)


SEEN_ONLY = "seen texels, the rest at the image mean"
SEEN_AND_FIT = "seen texels, shading-fit lamps, the rest at the image mean"
NETWORK = "trained out-of-view branch"
BOX_KINDS = ("true", "estimated")
LEARNED_INPUT_HEIGHT = 60  # photo rows a placement network sees (as `bench.lamp_placement`'s default)
WEIGHTS = tuple(k / 10 for k in range(11))  # the fit's weights against the mean placement tried on validation


class CompleteSources:
    """The out-of-view light with nothing true but what the fit saw (`lamp_placement.light_scores`' extra
    sources): each direction that leaves the view's box (`boxes`, per view) through a texel the camera saw
    takes what it saw there (`seen`, per view: `visible_light.observed` on the fit's own depth and normals,
    `visible_light.TEXTURE_SIZE` texels a side); an unseen one through the ceiling its cell's radiance in
    `lamps` (N, grid * grid, 3) plus the image's mean; any other the image's mean. Beside it the same
    without the lamps, and a trained LightNet's branch on its own G-buffers when `system` is given."""

    def __init__(self, grid: int, lamps: torch.Tensor, boxes: list, seen: list, system=None):
        self.grid, self.lamps, self.boxes, self.seen, self.system = grid, lamps, boxes, seen, system
        self.names = (SEEN_ONLY, SEEN_AND_FIT) + ((NETWORK,) if system is not None else ())

    def __call__(self, i: int, batch: dict, gb: dict, r: dict) -> dict:
        box = self.boxes[i]
        values, was_seen = seen_lookup(self.seen[i], box, r["origin"], r["direction"], TEXTURE_SIZE)
        index = box_texels(box, r["origin"], r["direction"], self.grid)
        ceiling = (index // (self.grid * self.grid)) == CEILING
        image_mean = batch["im"][0].double().clamp(min=0).mean((1, 2)).expand(len(index), 3)
        lamps = torch.where(ceiling[:, None], self.lamps[i].double()[index % (self.grid * self.grid)], 0.0)
        out = {
            SEEN_ONLY: torch.where(was_seen[:, None], values, image_mean),
            SEEN_AND_FIT: torch.where(was_seen[:, None], values, image_mean + lamps),
        }
        if self.system is not None:
            out[NETWORK] = network_sources(self.system, batch, self.system.gbuffers(batch), r)["out"]
        return out


def _finite_stat(stat, values: list[float]) -> float | None:
    """stat over the finite values (a view without pixels has none), None when there are none."""
    finite = [v for v in values if math.isfinite(v)]
    return float(stat(finite)) if finite else None


def view_box(kind: str, source_root: Path, maps: dict):
    """The box a view's fit and scoring use: the room file's (`true`) or the one `ops.roombox` finds from
    the fit's own depth and normals (`estimated`, `roombox_floor.estimated_box`)."""
    if kind == "true":
        return true_box(source_root, maps["id"])
    return estimated_box(maps)


def fit_split(data, source_root: Path, grid: int, options: dict, material=None) -> dict:
    """Every view of `data` fitted (`fit_view`; `options`: sub, pixels, trim, seed, bounce, box, depth_noise): the true
    and fitted cell radiance (N, grid * grid, 3) on each view's box, the boxes, what the camera saw of
    each (`visible_light.observed`, `TEXTURE_SIZE` texels a side) and the fit's statistics. `material`:
    (MaterialNet, depth scale, the maps it replaces) whose maps replace the truth in the fit."""
    from pipeline.bench.blend_floor import ground_truth_gbuffers
    from pipeline.data.datasets import collate_views

    true_cells, fitted, residuals, used, direct_share, boxes, seen = [], [], [], [], [], [], []
    for i in tqdm(range(len(data)), desc="shading fit"):
        item = data[i]
        maps = item if material is None else predicted_maps(item, *material)
        maps = noisy_depth(maps, options["depth_noise"], options["seed"] + 7919 * i)
        box = view_box(options["box"], source_root, maps)
        boxes.append(box)
        true_cells.append(ceiling_lamps(room_lamps(source_root, item["id"]), box, grid).reshape(-1, 3))
        batch = collate_views([{k: v for k, v in maps.items() if k != "light"}])
        gb = ground_truth_gbuffers(batch)  # the fit's own maps as G-buffers (predicted ones with `material`)
        seen.append(observed(batch, gb, box, TEXTURE_SIZE))
        px = shading_pixels(maps, box, options["pixels"], options["seed"] + i)
        bounce = bounce_terms(batch, gb, box, px) if options["bounce"] and len(px["point"]) else None
        fit = fit_view(px, box, grid, options["sub"], options["trim"], bounce)
        if len(px["point"]):  # how much of what the pixels show the true lamps light directly
            direct = (
                px["albedo"] / math.pi * (irradiance_matrix(px["point"], px["normal"], box, grid, 1) @ true_cells[-1])
            )
            direct_share.append(float(luminance(direct).sum() / luminance(px["radiance"]).sum().clamp(min=1e-12)))
        fitted.append(fit["cells"])
        residuals.append(fit["relative_residual"])
        used.append(fit["pixels"])
    return {
        "true": torch.stack(true_cells),
        "fitted": torch.stack(fitted),
        "residuals": residuals,
        "used": used,
        "direct_share": direct_share,
        "boxes": boxes,
        "seen": seen,
    }


def shrunk(fitted: torch.Tensor, prior: torch.Tensor, weight: float, grid: int) -> torch.Tensor:
    """weight * the fit's placement + (1 - weight) * the prior placement (1, grid * grid), (N, grid * grid)."""
    return weight * distribution(fitted.view(-1, grid, grid, 3)) + (1 - weight) * prior


def energy_scale(fits: dict) -> float:
    """Median over views with lamps of the true lamp luminance over the fitted one: the fit's energy
    calibrated on other views (1 where none has both)."""
    true, fit = luminance(fits["true"]).sum(1), luminance(fits["fitted"]).sum(1)
    both = (true > 0) & (fit > 0)
    return float(torch.median(true[both] / fit[both])) if both.any() else 1.0


def fit_features(fits: dict, grid: int) -> torch.Tensor:
    """(N, 2 grid^2) a placement network's extra input per view: the fit's placement and its log."""
    share = distribution(fits["fitted"].view(-1, grid, grid, 3)).float()
    return torch.cat([share, torch.log(share + 1e-3)], 1)


def learned_placements(splits: dict, fits: dict, grid: int, seeds: int, epochs: int, height: int) -> tuple:
    """Per seed, `lamp_placement.PlacementNet` trained on the training views from the photo alone and from
    the photo and the fit (`fit_features`), the epoch of lowest validation cross-entropy kept: their test
    placements {name: (N, grid^2)} and each run's kept epoch."""
    inputs = {
        name: torch.stack([photo_input(data[i]["im"], height) for i in range(len(data))])
        for name, data in splits.items()
    }
    targets = {name: distribution(f["true"].view(-1, grid, grid, 3)).float() for name, f in fits.items()}
    extra = {name: fit_features(f, grid) for name, f in fits.items()}
    out, kept = {}, {}
    for seed in range(seeds):
        for label, use_fit in (("from the photo", False), ("from the photo and the fit", True)):
            net, curve = train(
                inputs["train"],
                targets["train"],
                inputs["val"],
                targets["val"],
                grid,
                epochs,
                seed,
                extra["train"] if use_fit else None,
                extra["val"] if use_fit else None,
            )
            with torch.no_grad():
                logits = net(inputs["test"], extra["test"] if use_fit else None)
            out[f"{label}, seed {seed}"] = torch.softmax(logits, -1).double()
            kept[f"{label}, seed {seed}"] = int(np.argmin(curve)) + 1
    return out, kept


def run(
    data_dir="outputs/preprocess",
    grid=8,
    sub=4,
    pixels=4000,
    trim=0.02,
    seed=0,
    views=None,
    material=None,
    light_net=None,
    bounce=True,
    predicted=PREDICTABLE,
    box="true",
    learned_seeds=0,
    epochs=60,
    depth_noise=0.0,
) -> dict:
    from torch.utils.data import Subset

    from pipeline.data.datasets import ShardDataset

    data_dir = Path(data_dir)
    manifest = json.loads((data_dir / "manifest.json").read_text())
    source_root = Path(manifest["source_root"])
    if not source_root.is_dir():
        raise FileNotFoundError(f"{data_dir}/manifest.json: source_root {source_root} (the room files) is missing")
    if grid < 1 or sub < 1 or pixels < grid * grid + 1 or not 0 <= trim < 0.5:
        raise ValueError(
            f"--grid {grid}, --sub {sub}, --pixels {pixels}, --trim {trim}: need grid >= 1, sub >= 1, "
            "pixels > grid^2 and 0 <= trim < 0.5"
        )
    if learned_seeds < 0 or epochs < 1:
        raise ValueError(f"--learned-seeds {learned_seeds}, --epochs {epochs}: need seeds >= 0 and epochs >= 1")
    if box not in BOX_KINDS:
        raise ValueError(f"--box {box}: choose one of {', '.join(BOX_KINDS)}")
    if not predicted or any(k not in PREDICTABLE for k in predicted):
        raise ValueError(f"--predicted {','.join(predicted)}: choose some of {','.join(PREDICTABLE)}")
    test, val = ShardDataset(data_dir, "test", lighting=True), ShardDataset(data_dir, "val", lighting=True)
    if views is not None:
        test, val = (Subset(d, list(range(min(views, len(d))))) for d in (test, val))
    for name, d in (("test", test), ("val", val)):
        if len(d) == 0:
            raise ValueError(f"{data_dir}: the {name} split holds no view")
    prior = training_mean_placement(data_dir, source_root, grid)
    maps = None
    if material is not None:
        from pipeline.models.material_net import load_material_export

        net, blob = load_material_export(material)
        maps = (net, float(blob["depth_scale"]), tuple(predicted))
    if not 0 <= depth_noise < 1:
        raise ValueError(f"--depth-noise {depth_noise}: give a relative error in [0, 1)")
    options = {
        "sub": sub,
        "pixels": pixels,
        "trim": trim,
        "seed": seed,
        "bounce": bool(bounce),
        "box": box,
        "depth_noise": float(depth_noise),
    }
    # the fit's weight against the mean placement and its energy scale, both chosen on the validation views
    fits_val = fit_split(val, source_root, grid, options, maps)
    tried = {f"{w:.1f}": shrunk(fits_val["fitted"], prior, w, grid) for w in WEIGHTS}
    val_light, _ = light_scores(val, source_root, grid, tried, boxes=fits_val["boxes"])
    val_error = {w: 0.5 * (row["surf"]["nmse"] + row["free"]["nmse"]) for w, row in val_light.items() if w in tried}
    weight = float(min(val_error, key=val_error.get))
    scale = energy_scale(fits_val)

    fits = fit_split(test, source_root, grid, options, maps)
    fitted = fits["fitted"]
    learned, kept = {}, {}
    if learned_seeds > 0:  # placement networks trained on the training views, with and without the fit
        train_set = ShardDataset(data_dir, "train", lighting=False)
        fits_train = fit_split(train_set, source_root, grid, options, maps)
        learned, kept = learned_placements(
            {"train": train_set, "val": val, "test": test},
            {"train": fits_train, "val": fits_val, "test": fits},
            grid,
            learned_seeds,
            epochs,
            LEARNED_INPUT_HEIGHT,
        )
    target = distribution(fits["true"].view(-1, grid, grid, 3))
    placed = shrunk(fitted, prior, weight, grid)
    lamps = placed[..., None] * (scale * fitted.sum(1, keepdim=True))  # the calibrated energy, placed
    placements = {
        "uniform over the ceiling": torch.full_like(target, 1 / target.shape[1]),
        "training rooms' mean": prior.expand_as(target),
        "shading fit (placement, true energy)": distribution(fitted.view(-1, grid, grid, 3)),
        "shading fit shrunk to the mean (placement, true energy)": placed,
        "shading fit (its own radiance)": fitted,
        "shading fit shrunk, calibrated energy": lamps,
        **learned,
    }
    true_energy = luminance(fits["true"]).sum(1)
    has_lamps = true_energy > 0
    ratio = luminance(fitted).sum(1)[has_lamps] / true_energy[has_lamps]
    report = {
        "data_dir": str(data_dir),
        "grid": grid,
        **options,
        "bounce_texels": BOUNCE_TEXELS if bounce else None,
        "gbuffers": (
            "ground truth"
            if material is None
            else f"MaterialNet {material}"
            + ("" if set(predicted) == set(PREDICTABLE) else f" ({', '.join(predicted)}; the rest true)")
        )
        + (f", depth x (1 + {depth_noise:g} smooth field)" if depth_noise else ""),
        "test_views": len(test),
        "val_views": len(val),
        "views_with_lamps": int(has_lamps.sum()),
        "pixels_used": {"median": float(np.median(fits["used"])), "min": int(min(fits["used"]))},
        "views_without_pixels": int(sum(u == 0 for u in fits["used"])),
        "relative_residual": {
            "median": _finite_stat(np.median, fits["residuals"]),
            "max": _finite_stat(np.max, fits["residuals"]),
        },
        "fitted_over_true_lamp_energy": {"median": float(torch.median(ratio)) if has_lamps.any() else None},
        "true_lamps_direct_share": {
            "median": _finite_stat(np.median, fits["direct_share"]),
            "definition": "the true lamps' direct light (on the ceiling's cells, no occlusion) over the fitted pixels' "
            "radiance, luminance",
        },
        "learned": {"seeds": learned_seeds, "epochs": epochs, "kept_epoch": kept} if learned_seeds else None,
        "validation": {
            "mean nMSE (surface and free) by the fit's weight": val_error,
            "chosen weight": weight,
            "energy scale (true over fitted, median)": scale,
        },
        "placement": {
            name: placement_scores(p if p.dim() == 2 else distribution(p.view(-1, grid, grid, 3)), target)
            for name, p in placements.items()
        },
    }
    system = None if light_net is None else network_system(light_net, material)
    complete = CompleteSources(grid, lamps, fits["boxes"], fits["seen"], system)
    report["light_net"] = None if light_net is None else str(light_net)
    report["light"], per_view = light_scores(
        test, source_root, grid, placements, complete.names, complete, fits["boxes"]
    )
    report["differences"] = paired_differences(per_view, "training rooms' mean")
    if system is not None:
        report["differences"].update(paired_differences(per_view, NETWORK))
    report["summary"] = placement_summary(report, "nMSE differences, paired by test view (95 % bootstrap)")
    report["examples"] = {
        "target": target[:4].view(-1, grid, grid).tolist(),
        "shading fit": distribution(fitted[:4].view(-1, grid, grid, 3)).view(-1, grid, grid).tolist(),
    }
    return report


def plot(report: dict, path) -> None:
    fig = Figure(figsize=(11, 6))
    grid_spec = fig.add_gridspec(2, 8, height_ratios=[1.5, 1])
    light_bars(
        fig.add_subplot(grid_spec[0, :]),
        report["light"],
        f"light on {report['test_views']} test views, lamps placed from the visible shading\n"
        f"{report['grid']} x {report['grid']} cells on the {report.get('box', 'true')} box's ceiling; "
        f"G-buffers: {report['gbuffers']}",
    )
    ex = report["examples"]
    for i in range(min(4, len(ex["target"]))):
        for j, key in enumerate(("target", "shading fit")):
            a = fig.add_subplot(grid_spec[1, 2 * i + j])
            a.imshow(np.array(ex[key][i]), cmap="magma")
            a.set_xticks([])
            a.set_yticks([])
            a.set_title(f"test view {i}\n" + ("true lamps" if j == 0 else "shading fit"), fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data-dir", default="outputs/preprocess")
    p.add_argument("--grid", type=int, default=8, help="ceiling cells per side")
    p.add_argument("--sub", type=int, default=4, help="patches per cell side in the irradiance integral")
    p.add_argument("--pixels", type=int, default=4000, help="pixels per view in the fit (at most)")
    p.add_argument("--trim", type=float, default=0.02, help="share of worst-explained pixels dropped in the refit")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--views", type=int, default=None, help="the first N test and validation views (default: all)")
    p.add_argument("--material", default=None, help="a MaterialNet export: fit on its G-buffers (default: the truth)")
    p.add_argument("--light-net", default=None, help="a LightNet export: its out-of-view branch as one more row")
    p.add_argument(
        "--predicted",
        default=",".join(PREDICTABLE),
        help="with --material, the maps taken from it (the rest stay true): which error costs the fit",
    )
    p.add_argument(
        "--box", default="true", choices=BOX_KINDS, help="the room's box: its file's, or found from the fit's maps"
    )
    p.add_argument(
        "--learned-seeds",
        type=int,
        default=0,
        help="also train placement networks from the photo, and from the photo and the fit (seeds each)",
    )
    p.add_argument("--epochs", type=int, default=60, help="the placement networks' epochs")
    p.add_argument("--no-bounce", action="store_true", help="leave the walls' bounce light out of the fit")
    p.add_argument(
        "--depth-noise",
        type=float,
        default=0.0,
        help="multiply the fit's depth by 1 + this times a smooth random field (the error the fit tolerates)",
    )
    p.add_argument("--name", default="shading_placement")
    add_threads_option(p)
    a = p.parse_args(argv)
    apply_threads(a.threads)
    report = run(
        a.data_dir,
        grid=a.grid,
        sub=a.sub,
        pixels=a.pixels,
        trim=a.trim,
        seed=a.seed,
        views=a.views,
        material=a.material,
        light_net=a.light_net,
        bounce=not a.no_bounce,
        predicted=tuple(a.predicted.split(",")),
        box=a.box,
        learned_seeds=a.learned_seeds,
        epochs=a.epochs,
        depth_noise=a.depth_noise,
    )
    print(publish(a.name, report, plot))


if __name__ == "__main__":
    main()
