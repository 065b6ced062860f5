"""The insertion and editing scoring of the `edit` stage, shared by `edit`, `ablate` (each LightNet preset
is scored on the same cases) and the benches: the per-view context, every row's render of every case,
the summary with paired bootstrap intervals, and the figure panels. What the stage writes with them:
`pipeline.runs.edit`.

Rows are scored at converged Monte Carlo noise (noise lowers the PSNR of a sharp light more than a blurred
one): each row renders the same pixels at its own samples per pixel (`row_spp`: `scoring.spp`, or more
for the sharp rows whose light is cheap to query), every pixel's samples a randomly shifted scrambled
Sobol sequence (`scoring.layer: converged`, `models.scoring_layer`), and the sharp rows also sample the
nearest probe's map as a light guide (`scoring.guide`, `ops.guide`); `bench.scoring_convergence`
measures each row's change at 4x its samples. One seed per case (its own per view; rows on the same
shading G-buffers at the same count draw the same directions: the LightNet and constant rows of an
object case):
- `lightnet`: LightNet on the photo and the frozen MaterialNet's G-buffers (the method);
- `lightnet_gt_gbuffers`: LightNet on the ground-truth G-buffers (what a perfect MaterialNet would give);
- `constant`, `scaled_constant`: the content-blind lights of `train_lighting` (mean training radiance,
  and the same at the photo's exposure);
- `nearest_probe`: the ground-truth free-point probe nearest to the case as a distant environment map
  (the best a single environment map can do, given the true light at one point);
- `oracle`: Mitsuba's incident radiance for every sample ray (`data.synth.oracle`, `oracle.paths` path
  samples each), on the ground-truth G-buffers: validates the evaluation itself. Its light is itself a
  Monte Carlo estimate (Mitsuba's paths), so its noise does not fall with the directions as the other
  rows' does. With `oracle.psnr: extrapolated` it renders four independent quarters of its samples and
  its PSNR is the converged render's: each half's tone-mapped render extrapolated to infinite samples
  from its two quarters, and the product of the two halves' errors (`metrics.insertion.psnr_extrapolated`;
  `psnr_decorrelated` keeps the product of the halves' plain means, which `oracle.psnr: decorrelated`
  renders alone); its other scores and its figure use the parts' mean, and `psnr_with_noise` keeps the
  plain PSNR of that mean.
Objects bring their own exact G-buffers in every row; edits apply the new material to the predicted
G-buffers (rows on predictions) or the ground truth (`lightnet_gt_gbuffers`, `oracle`). Objects are
placed where they truly are (their ground-truth G-buffers) in every row, so the LightNet row measures the
light at that point as the method sees the scene: its SSRT marches the predicted depth (metres through
the export's depth scale; zero outside the view's valid mask, as in `train_lighting`).
"""

from __future__ import annotations

import json
import time
import zlib
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import DataLoader
from tqdm import tqdm

from pipeline.data import cases as case_io
from pipeline.data import interiorverse as iv
from pipeline.data.datasets import ShardDataset, collate_views
from pipeline.data.lighting import ViewLighting
from pipeline.data.synth import mitsuba_backend as mb
from pipeline.data.synth.cases import InsertedObject, MaterialEdit
from pipeline.data.synth.oracle import MitsubaOracle
from pipeline.data.synth.scene import Room
from pipeline.metrics.bootstrap import paired_bootstrap
from pipeline.metrics.insertion import (
    HIGHER_IS_BETTER,
    SCORES,
    case_scores,
    noise_floor_psnr,
    psnr_decorrelated,
    psnr_extrapolated,
)
from pipeline.models.insertion import (
    composite_gbuffer,
    composite_image,
    edited_gbuffer,
    light_net_radiance,
    prepare_view,
    render_case,
)
from pipeline.models.light_net import load_light_export
from pipeline.models.material_net import load_material_export
from pipeline.models.render_layer import MCRenderLayer
from pipeline.models.scoring_layer import ScoringLayer
from pipeline.ops.camera import backproject
from pipeline.ops.envmap import sphere_lookup
from pipeline.ops.guide import SphereGuide
from pipeline.systems.lighting_baselines import constant_light, mean_training_radiance, scaled_constant_light
from pipeline.systems.ring_scoring import RING_ROWS, ring_change, ring_scores, view_shape

ROWS = ("lightnet", "lightnet_gt_gbuffers", "constant", "scaled_constant", "nearest_probe", "oracle")
GUIDED = ("nearest_probe", "oracle")  # rows whose light is sharp and cheap to query: sampled with a light guide
FIGURE_ROWS = ("lightnet", "lightnet_gt_gbuffers", "scaled_constant", "nearest_probe", "oracle")
NOISY_LIGHT = ("oracle",)  # rows whose light is itself a Monte Carlo estimate
ORACLE_PSNR = {"extrapolated": 4, "decorrelated": 2, "plain": 1}  # the independent renders each scores from
PSNR_VARIANTS = ("psnr_with_noise", "psnr_decorrelated")  # the other PSNRs of a row scored in parts
RING_SEED_OFFSET = 5  # the ring's renders: a seed apart from the case's (and its parts', +0..+3)


def parts(cfg: DictConfig, row: str) -> int:
    """Independent renders a row's samples are split into: for a noisy-light row, 4 under the
    extrapolated PSNR and 2 under the decorrelated one (`oracle.psnr`); else 1."""
    kind = str(cfg.oracle.get("psnr", "plain"))
    if kind not in ORACLE_PSNR:
        raise ValueError(f"oracle.psnr={kind!r}: choose one of {list(ORACLE_PSNR)}")
    return ORACLE_PSNR[kind] if row in NOISY_LIGHT else 1


def case_centre(case: case_io.Case, gt: dict, fov: float, w2v: np.ndarray) -> torch.Tensor:
    """(3,) view-space centre of a case: the object's bounding centre, or the mean point of the edit."""
    if case.kind == "object":
        world = np.asarray(case.description["spheres"])[:, :3].mean(0)
        return torch.from_numpy((world - w2v[:3, 3]) @ w2v[:3, :3]).float()
    pts = backproject(gt["depth"], fov)[0].reshape(-1, 3)[case.pixel]
    return pts.mean(0)


def case_seed(view_seed: int, index: int) -> int:
    """The render seed of the `index`-th case of a view whose seed is `view_seed` (`view_seed`): every row
    of a case draws from it, so rows on the same shading G-buffers see the same directions."""
    return int(view_seed) + 7919 * int(index)


def score_view(
    ctx: dict, cases: list[case_io.Case], cfg: DictConfig, rows: tuple = ROWS, ring: bool = False
) -> list[dict]:
    """`rows` (all by default) of every case of one view:
    [{"case", "rows": {row: scores}, "renders": {row: (M, 3)}, "seconds": {row: s}}]. With `ring`, object
    cases are also scored on the room around them (`systems.ring_scoring`): the composite without
    differential rendering and, for each of `rows` in `RING_ROWS`, with it (`ring_<row>` in "rows", the
    changes in "ring", their time in "seconds" as `ring`), at `ctx["ring_layer"]`'s samples."""
    view = ctx["view"]
    fov, gt, pred, photo, scale = view.fov, view.gt, view.pred, view.photo, view.scale
    constants, free = ctx["constants"], ctx["light"].free
    net, seed = view.net, int(ctx["seed"])
    lights = {
        "lightnet": light_net_radiance(net, view.ctx_pred, pred, fov, seed),
        "lightnet_gt_gbuffers": light_net_radiance(net, view.ctx_gt, gt, fov, seed),
        "constant": constant_light(constants),
        "scaled_constant": scaled_constant_light(constants, scale),
    }
    out = []
    for case in cases:
        if case.kind == "object":
            obj = {"albedo": case.albedo, "material": case.material, "normal": case.normal, "depth": case.depth}
            shade_pred = composite_gbuffer(pred, case.pixel, **obj)
            shade_gt = composite_gbuffer(gt, case.pixel, **obj)
            oracle = ctx["oracle"].for_object(InsertedObject(**case.description)) if "oracle" in rows else None
        else:
            d = case.description
            shade_pred = edited_gbuffer(pred, case.pixel, d["albedo"], d["roughness"], d["metallic"])
            shade_gt = composite_gbuffer(gt, case.pixel, albedo=case.albedo, material=case.material)
            oracle = ctx["oracle"].for_edit(MaterialEdit(**case.description)) if "oracle" in rows else None
        centre = case_centre(case, gt, fov, ctx["w2v"])
        probe = int(torch.argmin((free.position - centre).norm(dim=-1)))
        probe_map = free.radiance[probe : probe + 1]
        guide = probe_guide(probe_map, cfg)
        rows_light = {
            **lights,
            "nearest_probe": lambda idx, o, wi, b, m=probe_map: sphere_lookup(m, torch.zeros_like(b), wi),
            "oracle": oracle,
        }
        renders, scores, seconds = {}, {}, {}
        seed_of_case = case_seed(seed, len(out))
        for row in rows:
            shading = shade_gt if row in ("lightnet_gt_gbuffers", "oracle") else shade_pred
            layer = ctx["layers"][row]  # at the row's samples over its number of parts
            t0 = time.perf_counter()
            with torch.no_grad():  # the parts' seeds: the case's, then the next ones (no other case's)
                renders_k = [
                    render_case(
                        layer,
                        shading,
                        fov,
                        case.pixel,
                        rows_light[row],
                        seed_of_case + k,
                        guide if row in GUIDED else None,
                    )
                    for k in range(parts(cfg, row))
                ]
            renders[row] = torch.stack(renders_k).mean(0)
            seconds[row] = time.perf_counter() - t0
            scores[row] = case_scores(renders[row], case.radiance, photo, case.pixel, float(scale))
            scores[row].update(parted_psnr(renders_k, case.radiance, float(scale), scores[row]["psnr"]))
        scores["ground_truth"] = {"noise_floor_psnr": noise_floor_psnr(case.radiance, case.stderr, float(scale))}
        result = {"case": case, "rows": scores, "renders": renders, "seconds": seconds}
        if ring and case.kind == "object":
            t0 = time.perf_counter()
            shape = view_shape(case.description, ctx["w2v"])
            # the proxy where the room truly is, as the object is placed where it truly is; its materials
            # (and every row's light) the predictions
            proxy = {**pred, "depth": gt["depth"], "normal": gt["normal"]}
            changes = {
                row: ring_change(
                    ctx["ring_layer"],
                    proxy,
                    fov,
                    case.ring_pixel,
                    rows_light[row],
                    shape,
                    renders[row].mean(0),  # the object's radiance towards the room, as `invrender insert`
                    seed_of_case + RING_SEED_OFFSET,
                    guide if row in GUIDED else None,
                )
                for row in rows
                if row in RING_ROWS
            }
            scores.update(ring_scores(photo, case, changes, float(scale)))
            result["ring"], seconds["ring"] = changes, time.perf_counter() - t0
        out.append(result)
    return out


def parted_psnr(renders: list[torch.Tensor], target: torch.Tensor, scale: float, plain: float) -> dict:
    """The PSNR scores of a row rendered in independent parts (each (M, 3)): {} for one part; else
    `psnr` from the parts without their noise (`metrics.insertion`: decorrelated from 2, extrapolated from
    4, which also keeps `psnr_decorrelated`), and `psnr_with_noise`, the `plain` PSNR of their mean."""
    if len(renders) == 1:
        return {}
    if len(renders) == 2:
        return {"psnr": psnr_decorrelated(*renders, target, scale), "psnr_with_noise": plain}
    extrapolated, decorrelated = psnr_extrapolated(renders, target, scale)
    return {"psnr": extrapolated, "psnr_decorrelated": decorrelated, "psnr_with_noise": plain}


def probe_guide(probe_map: torch.Tensor, cfg: DictConfig) -> SphereGuide | None:
    """The light guide of the sharp rows: a distant map (1, rows, cols, 3), for the stage the nearest
    ground-truth probe's (the nearest-probe row's own light, and close to the oracle's light at the case);
    None if the map holds no energy or the scoring takes no guide (`scoring.guide`, `scoring.layer`)."""
    if not (cfg.scoring.guide and cfg.scoring.layer == "converged"):
        return None
    return SphereGuide(probe_map) if float(probe_map.sum()) > 0 else None


def case_group(kind: str, label: str) -> str:
    """The group a case is summarised in: `insert/<material class>` for objects, `edit/<kind>` for edits."""
    return f"insert/{label}" if kind == "object" else f"edit/{label}"


def summarise(records: list[dict], resamples: int, seed: int, rows: tuple = ROWS) -> dict[str, float]:
    """Means per group (material class of objects, kind of edits, and all of each; and the objects' shape,
    `insert/<shape>`, for records with a `shape`) and paired bootstrap intervals of LightNet minus every
    other row of `rows` (whose first is `lightnet`)."""
    metrics: dict[str, float] = {}
    groups: dict[str, list[dict]] = {}
    for r in records:
        group = case_group(r["kind"], r["label"])
        groups.setdefault(group, []).append(r)
        groups.setdefault(f"{group.split('/')[0]}/all", []).append(r)
        if r["kind"] == "object" and r.get("shape"):
            groups.setdefault(f"insert/{r['shape']}", []).append(r)
    for group, rs in sorted(groups.items()):
        metrics[f"{group}/cases"] = float(len(rs))
        for row in rows:
            for s in SCORES:
                metrics[f"{group}/{row}/{s}"] = float(np.mean([r[f"{row}/{s}"] for r in rs]))
            for variant in PSNR_VARIANTS:  # a row scored in parts: its other PSNRs beside
                if f"{row}/{variant}" in rs[0]:
                    metrics[f"{group}/{row}/{variant}"] = float(np.mean([r[f"{row}/{variant}"] for r in rs]))
        # what an exact render would score against this ground truth, given the truth's own noise
        metrics[f"{group}/ground_truth/noise_floor_psnr"] = float(
            np.mean([r["ground_truth/noise_floor_psnr"] for r in rs])
        )
        for row in rows[1:]:
            for s in SCORES:
                diff = [r[f"lightnet/{s}"] - r[f"{row}/{s}"] for r in rs]
                ci = paired_bootstrap(diff, resamples, seed, groups=[r["view"] for r in rs])
                metrics[f"{group}/lightnet_minus_{row}/{s}_diff"] = ci["diff"]
                if not np.isfinite(ci["lo"]):  # one view: no interval, and no verdict either way
                    metrics[f"{group}/lightnet_minus_{row}/{s}_verdict"] = 0.0
                    continue
                metrics[f"{group}/lightnet_minus_{row}/{s}_lo"] = ci["lo"]
                metrics[f"{group}/lightnet_minus_{row}/{s}_hi"] = ci["hi"]
                better = ci["lo"] > 0 if HIGHER_IS_BETTER[s] else ci["hi"] < 0
                worse = ci["hi"] < 0 if HIGHER_IS_BETTER[s] else ci["lo"] > 0
                metrics[f"{group}/lightnet_minus_{row}/{s}_verdict"] = 1.0 if better else (-1.0 if worse else 0.0)
    return metrics


def case_panel(res: dict, photo: torch.Tensor, scale: float, view_id: str, rows: tuple = FIGURE_ROWS) -> dict:
    """One `insertion_grid` panel of a scored case (`score_view`'s result `res`): the photo, Mitsuba's
    ground truth and each of `rows` composited into the photo, with each row's PSNR."""
    case = res["case"]
    return {
        "label": f"{view_id} {case.name} {case.label}",
        "photo": photo.numpy(),
        "scale": float(scale),
        "pixels": case.pixel.numpy(),
        "gt": composite_image(photo, case.pixel, case.radiance).numpy(),
        "rows": {row: composite_image(photo, case.pixel, res["renders"][row]).numpy() for row in rows},
        "psnr": {row: res["rows"][row]["psnr"] for row in rows},
    }


def ring_panel(res: dict, photo: torch.Tensor, scale: float, view_id: str) -> dict:
    """One `insertion_grid` panel of a case scored with its ring (`score_view(..., ring=True)`): Mitsuba's
    render (the object and its change to the room), LightNet's object with the shadow and bounce light
    of differential rendering and without them, each with its PSNR on the ring."""
    case = res["case"]
    ring, base = case.ring_pixel, photo.reshape(-1, 3)[case.ring_pixel]
    with_object = composite_image(photo, case.pixel, res["renders"]["lightnet"])
    shadowed = (base + res["ring"]["lightnet"].to(base.dtype)).clamp(min=0)
    truth = composite_image(photo, ring, (base + case.ring_delta.to(base.dtype)).clamp(min=0))
    return {
        "label": f"{view_id} {case.name} {case.label}",
        "photo": photo.numpy(),
        "scale": float(scale),
        "pixels": torch.cat([case.pixel, ring]).numpy(),
        "gt": composite_image(truth, case.pixel, case.radiance).numpy(),
        "rows": {
            "lightnet_shadows": composite_image(with_object, ring, shadowed).numpy(),
            "no_shadows": with_object.numpy(),
        },
        "psnr": {
            name: res["rows"][f"ring_{row}"]["psnr"]
            for name, row in (("lightnet_shadows", "lightnet"), ("no_shadows", "no_shadows"))
        },
    }


def ring_panels(results: list[dict], photo_of: dict, n: int) -> list[dict]:
    """The first `n` object cases scored with a ring that has changed pixels, as `ring_panel`s."""
    picked = [r for r in results if "ring" in r and np.isfinite(r["rows"]["ring_no_shadows"]["psnr"])][:n]
    return [ring_panel(res, *photo_of[res["view"]]) for res in picked]


def figure_panels(results: list[dict], photo_of: dict, kind: str, n: int, rows: tuple = FIGURE_ROWS) -> list[dict]:
    """The first `n` scored cases of `kind` (`object` or `edit`) as figure panels (`case_panel`) of `rows`;
    photo_of: view id -> (photo, scale, view id)."""
    picked = [res for res in results if res["case"].kind == kind][:n]
    return [case_panel(res, *photo_of[res["view"]], rows) for res in picked]


def _dataset_record(root: Path) -> dict:
    path = root / "dataset.json"
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise iv.DatasetError(f"{path}: cannot read the generator's record ({exc})") from exc


def view_seed(seed: int, view_id: str) -> int:
    """A seed of its own for every view (and so every case), stable across runs: Monte Carlo errors of
    different views are independent, as the bootstrap over views assumes."""
    return (int(seed) * 1_000_003 + zlib.crc32(view_id.encode())) & 0x7FFFFFFF


def row_spp(cfg: DictConfig, row: str) -> int:
    """Samples per pixel of `row`: its entry in `scoring.row_spp` (the rows whose light is sharp and cheap
    to query converge only at more samples), else `scoring.spp`. The oracle traces each sample ray with
    `oracle.paths` Mitsuba paths."""
    extra = OmegaConf.to_container(cfg.scoring.get("row_spp") or {}, resolve=True)
    unknown = sorted(set(extra) - set(ROWS))
    if unknown:
        raise ValueError(f"scoring.row_spp: unknown rows {unknown}; the rows are {ROWS}")
    key = f"scoring.row_spp.{row}" if row in extra else "scoring.spp"
    n = int(extra.get(row, cfg.scoring.spp))
    if n < 1:
        raise ValueError(f"{key}={n}: at least 1 sample per pixel")
    return n


def ring_spp(cfg: DictConfig) -> int:
    """Samples per pixel of the ring's differential renders (`scoring.ring.spp`), or 0 when the stage
    scores no ring (`scoring.ring.enabled` false, or no `scoring.ring`)."""
    ring = cfg.scoring.get("ring")
    if ring is None or not ring.get("enabled", False):
        return 0
    n = int(ring.spp)
    if n < 1:
        raise ValueError(f"scoring.ring.spp={n}: at least 1 sample per pixel")
    return n


LAYERS = ("converged", "render")


def scoring_layer(cfg: DictConfig, spp: int | None = None) -> MCRenderLayer | ScoringLayer:
    """A render layer for scoring at `scoring.spp` (or `spp`) samples per pixel: `scoring.layer` converged
    (`ScoringLayer`: Sobol samples and the light guide, BRDF importance sampling) or render (the
    configured `MCRenderLayer`, independent samples: how an estimator other than importance is scored)."""
    n = int(cfg.scoring.spp if spp is None else spp)
    if n < 1:
        raise ValueError(f"scoring.spp={n}: at least 1 sample per pixel")
    kind = str(cfg.scoring.layer)
    if kind not in LAYERS:
        raise ValueError(f"scoring.layer={kind!r}: choose one of {LAYERS}")
    render = OmegaConf.to_container(cfg.render, resolve=True)
    if kind == "converged":
        if render["estimator"] != "importance":
            raise ValueError(
                f"scoring.layer=converged samples the BRDF by importance; render.estimator={render['estimator']!r} "
                "is scored with scoring.layer=render"
            )
        return ScoringLayer(n, int(render.get("chunk", 1 << 16)))
    return MCRenderLayer.from_config({**render, "spp": n})


def scoring_layers(cfg: DictConfig, scale: int = 1) -> dict[str, MCRenderLayer]:
    """Every row's render layer ({row: layer}), at `row_spp` x `scale` samples per pixel over the row's
    `parts` (each part renders its share)."""
    layers = {}
    for row in ROWS:
        n, k = row_spp(cfg, row) * int(scale), parts(cfg, row)
        if n % k:
            raise ValueError(
                f"scoring.row_spp.{row}={row_spp(cfg, row)}: oracle.psnr={cfg.oracle.psnr} renders {k} "
                f"independent parts; give a multiple of {k}"
            )
        layers[row] = scoring_layer(cfg, n // k)
    return layers


def stage_setup(cfg: DictConfig) -> dict:
    """What every view shares: both networks, the constant lights, the render layers, the view list and
    the views' `max_depth` (the oracle traces as the views were rendered). Sets the Mitsuba variant."""
    from pipeline.systems.lighting import SSRT_DEPTHS

    if cfg.ssrt_depth not in SSRT_DEPTHS:
        raise ValueError(f"ssrt_depth={cfg.ssrt_depth!r}: choose one of {SSRT_DEPTHS}")
    root = Path(cfg.data_root)
    material_net, material_meta = load_material_export(cfg.material_path)
    net, _ = load_light_export(cfg.light_path)
    train = ShardDataset(cfg.data_dir, "train", lighting=True)
    views = case_io.case_views(root, str(cfg.split))
    mb.init_mitsuba(mb.choose_variant("auto"))
    return {
        "root": root,
        "material": (material_net, material_meta),
        "net": net.eval(),
        "constants": mean_training_radiance(DataLoader(train, batch_size=16, collate_fn=collate_views)),
        "layers": scoring_layers(cfg),
        "ring_layer": scoring_layer(cfg, ring_spp(cfg)) if ring_spp(cfg) else None,
        "views": views,
        "max_depth": int(_dataset_record(root)["config"]["max_depth"]),
    }


def with_views(shared: dict, root: str | Path, split: str) -> dict:
    """`shared` (`stage_setup`'s) for the cases of another dataset root's `split`, the networks, constant
    lights and layers kept: its root, view list and `max_depth` replaced (refused, naming the root, when no
    view of the split has cases)."""
    root = Path(root)
    views = case_io.case_views(root, split)
    return {**shared, "root": root, "views": views, "max_depth": int(_dataset_record(root)["config"]["max_depth"])}


def view_context(
    shared: dict, scene: str, view: str, cfg: DictConfig, oracle: bool = True
) -> tuple[dict, list[case_io.Case]]:
    """One view read and checked, prepared (`prepare_view`: its G-buffers predicted, LightNet's contexts
    of them and of the ground truth) and the oracle built: (the context `score_view` takes, the view's
    cases)."""
    root = shared["root"]
    maps, cases, camera = case_io.read_case_view(root, scene, view, str(cfg.split))
    light_file = iv.light_path(root, scene, view)
    light = ViewLighting.from_arrays(iv.read_light(light_file))
    if not len(light.free):
        raise iv.DatasetError(f"{light_file}: no free-point probe (the nearest-probe row needs one)")
    room = Room.from_json(json.loads((root / scene / "scene.json").read_text()))
    # predicted depth is zeroed outside the view's valid mask too, as `train_lighting` feeds LightNet
    mask = maps["mask"][..., 0] > 0.5
    prepared = prepare_view(
        maps["im"],
        *shared["material"],
        shared["net"],
        float(camera["fov_x_deg"]),
        mask=mask,
        gt_maps=maps,
        mask_prediction=cfg.ssrt_depth == "valid",
    )
    view_id = f"{scene}/{view}"
    seed = view_seed(int(cfg.render.seed), view_id)
    ctx = {
        "id": view_id,
        "seed": seed,
        "view": prepared,
        "layers": shared["layers"],
        "ring_layer": shared.get("ring_layer"),
        "constants": shared["constants"],
        "light": light,
        "w2v": np.asarray(camera["world_from_view"]),
        "oracle": (
            MitsubaOracle(room, room.cameras[int(view)], shared["max_depth"], int(cfg.oracle.paths), seed)
            if oracle
            else None
        ),
    }
    return ctx, cases


def score_rows(cfg: DictConfig, rows: tuple, progress: bool = False) -> tuple[dict[str, float], list[dict]]:
    """The stage's summary metrics for `rows` only (the first `lightnet`), and the per-case records
    ({view, kind, label, <row>/<score>}), without its files: what the ablations score every preset's
    LightNet export (`cfg.light_path`) with."""
    if rows[0] != "lightnet" or not set(rows) <= set(ROWS):
        raise ValueError(f"rows={rows}: the first must be lightnet, all of {ROWS}")
    shared = stage_setup(cfg)
    records = []
    for scene, view in tqdm(shared["views"], desc="insertion", unit="view", disable=not progress):
        ctx, cases = view_context(shared, scene, view, cfg, oracle="oracle" in rows)
        for res in score_view(ctx, cases, cfg, rows):
            row = {"view": ctx["id"], "kind": res["case"].kind, "label": res["case"].label}
            for name, sc in res["rows"].items():
                row.update({f"{name}/{k}": v for k, v in sc.items()})
            records.append(row)
    if not records:
        raise iv.DatasetError(f"{shared['root']}: the {cfg.split} views' case files list no case")
    return summarise(records, int(cfg.bootstrap), int(cfg.seed), rows), records
