"""Stage `ablate`: one `conf/ablation/` preset at one seed, trained under the ablation schedule (the
profile's `ablation_schedule`) by the preset's own stage (`train_lighting` or `train_material`, composed
with `ablation=<preset>`), and scored as the main stages score. A render-time preset (`preset.weights_from`:
`no_mc_render`, `uniform_render`) trains nothing: it scores `full`'s export at the same seed with another
render layer (`scoring.render`), so the layer is the only difference.

- the test metrics (LightNet keys without their mode prefix, so presets share keys): the training stage's
  own when it tested with the layer the preset is scored with, else the test split scored here;
- LightNet presets: the glossy-pixel re-render PSNR (`glossy_render`: ground-truth roughness <=
  `glossy.max_roughness`), the insertion and editing scores of the `edit` stage for the preset's LightNet
  and the exposure-scaled constant on the same cases (paired; a preset trained on ground-truth G-buffers
  adds the `lightnet_gt_gbuffers` row), the median seconds of a full-frame re-render at the evaluation
  spp over `timing_views` test images, and for the `full` preset at `test_time_threshold_seeds` the
  test metrics and seconds at each test-time out-of-view threshold (`test_time_thresholds`: the
  out-of-view branch queried only where u >= t);
- the wall minutes of the training stage (fit, validation and test passes; none for a render-time
  preset) and of each scoring step (`scoring_`, `timing_`, `test_time_thresholds_`, `insertion_minutes`),
  and of the whole run (`stage_minutes`).

A preset that needs something absent here (`preset.requires`, e.g. VGG16 weights) reports
`available: 0` and why, and trains nothing: no pretend version.

Writes `outputs/ablate/<preset>-s<seed>/` (the stage's checkpoints and export; a render-time preset's
`weights.json` names the export it scored and its SHA-256) and
`reports/ablate/<preset>-s<seed>/{metrics.json, timings.json, preset.json, views.csv}` (`views.csv`: each
test view's glossy re-render PSNR, which a render-time claim is paired on view by view; LightNet presets also
`worst_views.json`, at `worst_view_figure_seeds` `worst_views.png` (each worst view's worst case:
photo, Mitsuba, LightNet, scaled constant), and `insertion_scatter.png`, every case's PSNR against the
scaled constant's; a preset scored with another layer than it trained with, `layers.png`: the paper's
fig. 4 on the test view with the most glossy pixels); the stage's own report goes to `.../stage/`. One
MLflow run `ablate-<profile>` per preset and seed (tags preset, seed) holds them, its figures under
`figures/` (a MaterialNet preset's test maps), with the training stage's run nested in it.
"""

from __future__ import annotations

import csv
import hashlib
import json
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from pipeline.data.datamodules import InteriorVerseDataModule
from pipeline.metrics.image import psnr_tonemapped, tonemap
from pipeline.models.light_net import load_light_export
from pipeline.models.render_layer import MCRenderLayer
from pipeline.ops.camera import grid_pixels, pixel_values
from pipeline.systems import insertion_scoring
from pipeline.systems.lighting_figures import render_samples
from pipeline.systems.lighting_training import build_system, test_scores, train_lighting
from pipeline.systems.material_training import train_material
from pipeline.tracking import publish, stage_run
from pipeline.tracking.compose import compose, preset_stage
from pipeline.tracking.figures import paired_scatter

STAGES = {"train_lighting": train_lighting, "train_material": train_material}
INSERTION_ROWS = ("lightnet", "scaled_constant")


def stage_config(cfg: DictConfig, extra: tuple[str, ...] = ()) -> DictConfig:
    """The preset's training stage config: that stage's yaml with `ablation=<preset>`, this run's seed,
    profile, paths and tracking, its outputs under this run's folders; `extra` overrides after those."""
    common = [
        f"ablation={cfg.preset}",
        f"profile={cfg.profile_name}",
        f"seed={int(cfg.seed)}",
        f"paths.outputs={cfg.paths.outputs}",
        f"paths.reports={cfg.paths.reports}",
        f"progress={bool(cfg.progress)}",
    ]
    if OmegaConf.select(cfg, "tracking.uri"):
        common.append(f"tracking.uri={cfg.tracking.uri}")
    common.append(f"tracking.experiment={cfg.tracking.experiment}")
    where = [f"out_dir={cfg.out_dir}", f"report_dir={Path(cfg.report_dir) / 'stage'}"]
    return compose(preset_stage(str(cfg.preset)), [*common, *where, *extra, *list(cfg.stage_overrides)])


def scoring_config(cfg: DictConfig, stage_cfg: DictConfig) -> DictConfig:
    """The LightNet preset's config as `ablate` scores it: the stage's own, with the render layer of
    `scoring.render` when a preset changes the layer at one end only (`no_mc` trains with Li's layer and
    is scored with the MC layer; `no_mc_render` the reverse)."""
    wanted = str(stage_cfg.scoring.render)
    return stage_cfg if wanted == str(stage_cfg.render.estimator) else stage_config(cfg, (f"render={wanted}",))


def reused_weights(cfg: DictConfig, stage_cfg: DictConfig) -> Path | None:
    """A render-time preset's LightNet (`preset.weights_from`): that preset's export at this run's seed,
    beside this run's folder; None for a preset that trains its own. Raises naming the missing file."""
    source = OmegaConf.select(stage_cfg, "preset.weights_from")
    if not source:
        return None
    path = Path(cfg.out_dir).parent / f"{source}-s{int(cfg.seed)}" / "model.pt"
    if not path.is_file():
        raise FileNotFoundError(
            f"preset={cfg.preset} scores {source}'s weights at seed {int(cfg.seed)}: {path} is missing "
            f"(run `python -m stages.ablate preset={source} seed={int(cfg.seed)}` first)"
        )
    return path


def unavailable(stage_cfg: DictConfig) -> str | None:
    """Why the preset cannot run here (a required key unset), or None."""
    for key in OmegaConf.select(stage_cfg, "preset.requires") or []:
        if OmegaConf.select(stage_cfg, key) in (None, ""):
            return f"{key} is not set (see the preset's comment)"
    return None


@torch.no_grad()
def lighting_test(system, loader, threshold: float) -> dict[str, float]:
    """Test metrics of `system` at out-of-view threshold `threshold` (`train_lighting.test_scores`: what
    the stage's test pass logs)."""
    system.net.out_threshold = float(threshold)
    return {f"test/{k}": v for k, v in test_scores(system, loader).items()}


@torch.no_grad()
def seconds_per_image(system, views: list[dict], threshold: float) -> float:
    """Median wall seconds of a full-frame re-render (`full_frame_render`) over `views` (batches of 1)."""
    system.eval()
    system.net.out_threshold = float(threshold)
    times = []
    for batch in views:
        t0 = time.perf_counter()
        full_frame_render(system, batch)
        times.append(time.perf_counter() - t0)
    return float(torch.tensor(times).median())


def full_frame_render(system, batch) -> torch.Tensor:
    """Every valid pixel of the batch re-rendered at the evaluation spp: G-buffers, LightNet's
    encoding, the render layer. (M, 3)."""
    gen = system.eval_generator()
    fov = system.fov(batch)
    gb = system.gbuffers(batch)
    ctx = system.net.encode(batch["im"], gb["depth"], fov, normal=gb["normal"])
    pix = torch.nonzero(batch["mask"][:, 0].reshape(-1)).squeeze(-1)
    rgb, _ = system.eval_layer.render_pixels(gb, fov, pix, system.light_fn(ctx, gb, fov, gen), gen)
    return rgb


def lighting_extras(
    cfg: DictConfig, stage_cfg: DictConfig, score_cfg: DictConfig, export: Path, tested: dict[str, float] | None
) -> tuple[dict, dict, list[dict], list[Path], list[dict]]:
    """(metrics, timings, worst views, figures, per-view glossy scores) of the LightNet in `export` scored as
    the preset says (`score_cfg`, `scoring_config`'s): the test metrics (`tested`, the training stage's own
    when it tested with that layer; else None and the test split is scored here), the glossy-pixel
    re-render (`glossy_render`),
    seconds per image, the test-time thresholds for the `full` preset, insertion and editing, the views
    LightNet renders worst, the per-case insertion figure (`insertion_figure`) and, for a preset that
    changes the layer at render time, the layers' comparison on one view (`layer_figure`)."""
    net, _ = load_light_export(export)
    system = build_system(score_cfg)
    system.net.load_state_dict(net.state_dict())
    system.eval()
    dm = InteriorVerseDataModule(stage_cfg.data_dir, batch_size=int(stage_cfg.batch_size), seed=int(cfg.seed))
    views = list(dm.plain_loader("test", batch_size=1))[: int(cfg.timing_views)]
    base = float(stage_cfg.model.light_net.out_threshold)
    t0 = time.perf_counter()
    metrics = dict(tested) if tested is not None else lighting_test(system, dm.plain_loader("test"), base)
    glossy, per_view = glossy_render(system, dm.plain_loader("test", batch_size=1), cfg.glossy)
    metrics.update(glossy)
    timings = {"scoring_minutes": (time.perf_counter() - t0) / 60.0}
    t0 = time.perf_counter()
    timings["seconds_per_image"] = seconds_per_image(system, views, base)
    timings["timing_minutes"] = (time.perf_counter() - t0) / 60.0
    t0 = time.perf_counter()
    if str(cfg.preset) == "full" and int(cfg.seed) in cfg.test_time_threshold_seeds:
        # the out-of-view branch queried only where SSRT is unsure (u >= t)
        for t in cfg.test_time_thresholds:
            if float(t) == base:  # the preset's own threshold: its stage's test pass already scored it
                continue
            at_t = lighting_test(system, dm.plain_loader("test"), float(t))
            metrics.update({f"out_threshold_{float(t):g}/{k}": v for k, v in at_t.items()})
            timings[f"out_threshold_{float(t):g}/seconds_per_image"] = seconds_per_image(system, views, float(t))
        system.net.out_threshold = base
        timings["test_time_thresholds_minutes"] = (time.perf_counter() - t0) / 60.0
    t0 = time.perf_counter()
    edit_cfg = compose(
        "edit",
        [
            f"profile={cfg.profile_name}",
            f"seed={int(cfg.seed)}",
            f"paths.outputs={cfg.paths.outputs}",
            f"paths.reports={cfg.paths.reports}",
            f"light_path={export}",
            f"render={score_cfg.render.estimator}",  # the layer the preset is scored with
            f"bootstrap={int(cfg.bootstrap)}",
            f"scoring.spp={int(cfg.insertion_spp)}",
            # Sobol samples and the light guide need BRDF importance sampling: another estimator is scored
            # with its own render layer, as the preset renders
            f"scoring.layer={'converged' if score_cfg.render.estimator == 'importance' else 'render'}",
        ],
    )
    rows = (
        INSERTION_ROWS if stage_cfg.gbuffers == "predicted" else ("lightnet", "lightnet_gt_gbuffers", "scaled_constant")
    )
    insertion, records = insertion_scoring.score_rows(edit_cfg, rows, progress=bool(cfg.progress))
    metrics.update({f"edit/{k}": v for k, v in insertion.items()})
    timings["insertion_minutes"] = (time.perf_counter() - t0) / 60.0
    worst = worst_views(records, int(cfg.worst_views))
    report = Path(cfg.report_dir)
    figures = [insertion_figure(records, report / "insertion_scatter.png", f"{cfg.preset}, seed {cfg.seed}")]
    if worst and int(cfg.seed) in cfg.worst_view_figure_seeds:
        name = f"{cfg.preset}, seed {cfg.seed}: each worst view's worst inserted object or edit"
        figures.append(worst_view_figure(edit_cfg, records, worst, report / "worst_views.png", name))
    if score_cfg.render.estimator != stage_cfg.render.estimator and per_view:
        view = max(per_view, key=lambda v: v["pixels"])["id"]
        batch = next(b for b in dm.plain_loader("test", batch_size=1) if b["id"][0] == view)
        trained_layer = MCRenderLayer.from_config(stage_cfg.render, "eval_spp")
        figures.append(layer_figure(system, trained_layer, batch, cfg.glossy, report / "layers.png"))
    return metrics, timings, worst, figures, per_view


VIEW_COLUMNS = ("id", "test/glossy_render_psnr")  # views.csv: the per-view scores a render-time claim is tested on


def write_views(path: Path, per_view: list[dict]) -> Path:
    """`views.csv`: one row per test view with glossy pixels (`glossy_render`'s records): its id and glossy
    re-render PSNR, so that the report can pair a render-time preset with `full` view by view (header only
    for a run that scores no views)."""
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(VIEW_COLUMNS)
        w.writerows((v["id"], repr(float(v["psnr"]))) for v in per_view)
    return path


def write_view_outputs(report: Path, worst: list[dict], per_view: list[dict]) -> tuple[Path, Path]:
    """The two per-view outs every run writes (empty for a run that scores no views' light, so that every
    declared out exists): `worst_views.json` (`worst_views`) and `views.csv` (`write_views`)."""
    (report / "worst_views.json").write_text(json.dumps(worst, indent=1))
    return report / "worst_views.json", write_views(report / "views.csv", per_view)


def worst_view_figure(edit_cfg: DictConfig, records: list[dict], worst: list[dict], path: Path, title: str) -> Path:
    """The case LightNet renders worst in each of the `worst` views (`worst_views`), re-rendered as the
    insertion scoring rendered it (the same view seeds and case order), in `insertion_grid`: the photo,
    Mitsuba's ground truth, LightNet's and the scaled constant's composites. records: `score_rows`'s."""
    from pipeline.tracking.figures import insertion_grid

    order = [w["view"] for w in worst]
    shared = insertion_scoring.stage_setup(edit_cfg)
    panels = {}
    for scene, view in shared["views"]:
        if f"{scene}/{view}" not in order:
            continue
        ctx, cases = insertion_scoring.view_context(shared, scene, view, edit_cfg, oracle=False)
        results = insertion_scoring.score_view(ctx, cases, edit_cfg, INSERTION_ROWS)
        mine = [r for r in records if r["view"] == ctx["id"]]  # score_rows's records, in the same case order
        res = results[int(np.argmin([r["lightnet/psnr"] for r in mine]))]
        panels[ctx["id"]] = insertion_scoring.case_panel(
            res, ctx["view"].photo, ctx["view"].scale, ctx["id"], INSERTION_ROWS
        )
    return insertion_grid([panels[v] for v in order if v in panels], path, title)


def glossy_pixels(batch: dict, max_roughness: float) -> torch.Tensor:
    """(B, H, W) bool: valid pixels whose ground-truth roughness is at most `max_roughness` (mirrors,
    lacquer, polished floors: where a render layer's handling of the specular lobe shows)."""
    return batch["mask"][:, 0].bool() & (batch["material"][:, 0] <= float(max_roughness))


@torch.no_grad()
def glossy_render(system, loader, glossy: DictConfig) -> tuple[dict[str, float], list[dict]]:
    """Re-render PSNR (tone-mapped, `psnr_tonemapped`) on the glossy pixels (`glossy_pixels`) of each
    test view on every `glossy.stride`-th row and column, with the system's evaluation layer and seed;
    `loader` batches of one view. Returns ({test/glossy_render_psnr: the mean over views with such
    pixels, test/glossy_views, test/glossy_pixels: their count and the pixels' mean per view}, one
    {id, pixels, psnr} per such view)."""
    per_view = []
    for batch in loader:
        pix = grid_pixels(glossy_pixels(batch, glossy.max_roughness), int(glossy.stride))
        if len(pix) == 0:
            continue
        gen = system.eval_generator()
        fov, gb = system.fov(batch), system.gbuffers(batch)
        ctx = system.net.encode(batch["im"], gb["depth"], fov, normal=gb["normal"])
        rgb, b = system.eval_layer.render_pixels(gb, fov, pix, system.light_fn(ctx, gb, fov, gen), gen)
        score = psnr_tonemapped(rgb, pixel_values(batch["im"], pix), ctx["scale"][b])
        per_view.append({"id": batch["id"][0], "pixels": len(pix), "psnr": float(score)})
    if not per_view:
        return {"test/glossy_views": 0.0}, []
    return {
        "test/glossy_render_psnr": float(np.mean([v["psnr"] for v in per_view])),
        "test/glossy_views": float(len(per_view)),
        "test/glossy_pixels": float(np.mean([v["pixels"] for v in per_view])),
    }, per_view


@torch.no_grad()
def layer_figure(system, trained_layer, batch: dict, glossy: DictConfig, path: Path) -> Path:
    """The paper's fig. 4 on one test view: the window (a third of the image's height and width) holding
    the most glossy pixels, re-rendered at every valid pixel by `trained_layer` (the layer the network
    trained with) and by the system's evaluation layer (the preset's), beside the input photo (the
    ground truth), all tone-mapped alike; PSNR on the window's glossy pixels in the titles."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    from pipeline.tracking.figures import save

    mask = batch["mask"][0, 0].bool()
    gloss = glossy_pixels(batch, glossy.max_roughness)[0]
    H, W = mask.shape
    h, w = max(H // 3, 1), max(W // 3, 1)
    counts = torch.nn.functional.avg_pool2d(gloss[None, None].float(), (h, w), stride=1)[0, 0]
    top, left = divmod(int(counts.argmax()), counts.shape[1])
    window = torch.zeros_like(mask)
    window[top : top + h, left : left + w] = True
    pix = torch.nonzero((window & mask).reshape(-1)).squeeze(-1)
    fov, gb = system.fov(batch), system.gbuffers(batch)
    ctx = system.net.encode(batch["im"], gb["depth"], fov, normal=gb["normal"])
    target = pixel_values(batch["im"], pix)
    scale = ctx["scale"][0]
    glossy_sel = gloss.reshape(-1)[pix]

    def crop(rgb: torch.Tensor) -> np.ndarray:
        img = torch.zeros(H * W, 3)
        img[pix] = tonemap(rgb, scale.expand(len(rgb)))
        return img.reshape(H, W, 3)[top : top + h, left : left + w].numpy()

    panels = [("input photo (ground truth)", crop(target), None)]
    for layer in (trained_layer, system.eval_layer):
        gen = system.eval_generator()
        rgb, _ = layer.render_pixels(gb, fov, pix, system.light_fn(ctx, gb, fov, gen), gen)
        score = psnr_tonemapped(rgb[glossy_sel], target[glossy_sel], scale.expand(int(glossy_sel.sum())))
        panels.append((render_samples(layer), crop(rgb), float(score)))
    fig = Figure(figsize=(3.2 * (len(panels) + 1), 3.2))
    axes = fig.subplots(1, len(panels) + 1)
    full = tonemap(pixel_values(batch["im"], torch.arange(H * W)), scale.expand(H * W)).reshape(H, W, 3)
    axes[0].imshow(full.numpy())
    axes[0].add_patch(Rectangle((left - 0.5, top - 0.5), w, h, fill=False, color="tab:red", lw=1.5))
    axes[0].contour(gloss.numpy(), levels=[0.5], colors="yellow", linewidths=0.6)
    axes[0].set_title(f"{batch['id'][0]}: window, glossy pixels (yellow)", fontsize=8)
    for ax, (title, img, score) in zip(axes[1:], panels, strict=True):
        ax.imshow(img, interpolation="nearest")
        ax.set_title(title if score is None else f"{title}\nglossy PSNR {score:.2f} dB", fontsize=8)
    for ax in axes:
        ax.set_axis_off()
    return save(fig, path, f"the same LightNet under two render layers (roughness <= {float(glossy.max_roughness):g})")


def insertion_figure(records: list[dict], path: Path, name: str) -> Path:
    """Every insertion and editing case's PSNR under this preset's LightNet against the exposure-scaled
    constant on the same case (`paired_scatter`), grouped by object class and edit kind."""
    groups = [f"{'object' if r['kind'] == 'object' else 'edit'} {r['label']}" for r in records]
    return paired_scatter(
        np.array([r["scaled_constant/psnr"] for r in records]),
        np.array([r["lightnet/psnr"] for r in records]),
        groups,
        path,
        labels=("scaled constant PSNR (dB)", "LightNet PSNR (dB)"),
        title=f"{name}: insertion and editing cases against Mitsuba",
    )


def worst_views(records: list[dict], k: int) -> list[dict]:
    """The `k` test views whose inserted objects and edits LightNet renders worst (mean PSNR of its
    cases), with that PSNR and the exposure-scaled constant's on the same cases."""
    by_view: dict[str, list[dict]] = {}
    for r in records:
        by_view.setdefault(r["view"], []).append(r)
    rows = [
        {
            "view": view,
            "cases": len(rs),
            "lightnet_psnr": float(sum(r["lightnet/psnr"] for r in rs) / len(rs)),
            "scaled_constant_psnr": float(sum(r["scaled_constant/psnr"] for r in rs) / len(rs)),
        }
        for view, rs in by_view.items()
    ]
    return sorted(rows, key=lambda r: r["lightnet_psnr"])[:k]


def training_health(ablate_run_id: str, metrics: dict[str, float]) -> dict[str, float]:
    """Non-finite training losses (the step history of the nested training run), non-finite test
    metrics, and `diverged` (either, or the median loss of the last third of the logged steps above 10x
    that of the first third)."""
    import math

    import mlflow

    client = mlflow.MlflowClient()
    children = client.search_runs(
        [client.get_run(ablate_run_id).info.experiment_id],
        filter_string=f"tags.mlflow.parentRunId = '{ablate_run_id}'",
    )
    losses = []
    for child in children:
        for key in ("train/loss_step", "train/loss_epoch"):  # per step when logged, else per epoch
            history = client.get_metric_history(child.info.run_id, key)
            if history:
                losses = [m.value for m in sorted(history, key=lambda m: (m.step, m.timestamp))]
                break
    nonfinite_losses = sum(not math.isfinite(v) for v in losses)
    nonfinite_metrics = sum(not math.isfinite(v) for v in metrics.values())
    finite = [v for v in losses if math.isfinite(v)]
    third = max(1, len(finite) // 3)  # medians of the first and last thirds: the light loss is spiky
    blown = len(finite) >= 3 and float(np.median(finite[-third:])) > 10 * float(np.median(finite[:third]))
    return {
        "health/nonfinite_train_losses": float(nonfinite_losses),
        "health/nonfinite_test_metrics": float(nonfinite_metrics),
        "health/logged_train_losses": float(len(losses)),
        "health/diverged": float(bool(nonfinite_losses or nonfinite_metrics or blown)),
    }


def run(cfg: DictConfig) -> dict[str, float]:
    import mlflow

    started = time.perf_counter()
    report = Path(cfg.report_dir)
    stage_cfg = stage_config(cfg)
    preset = OmegaConf.to_container(stage_cfg.preset, resolve=True)
    stage = preset["stage"]
    tags = {"preset": str(cfg.preset), "seed": str(int(cfg.seed)), "ablation_stage": stage}
    why = unavailable(stage_cfg)
    weights = reused_weights(cfg, stage_cfg) if stage == "train_lighting" and why is None else None
    report.mkdir(parents=True, exist_ok=True)
    described = {**preset, "seed": int(cfg.seed), **({"unavailable": why} if why is not None else {})}
    (report / "preset.json").write_text(json.dumps(described, indent=1))
    with stage_run("ablate", cfg, tags=tags) as run:
        if why is not None:
            mlflow.set_tag("unavailable", why)
            out = Path(cfg.out_dir)  # the stage's out exists and says why it holds no model
            out.mkdir(parents=True, exist_ok=True)
            (out / "UNAVAILABLE.txt").write_text(f"ablation={cfg.preset} did not run: {why}\n")
            write_view_outputs(report, [], [])
            timings = {"stage_minutes": (time.perf_counter() - started) / 60.0}
            publish(report, {"available": 0.0}, artifacts=(report / "preset.json",), timings=timings)
            return {"available": 0.0}
        timings = {}
        if weights is None:
            t0 = time.perf_counter()
            stage_metrics = STAGES[stage](stage_cfg)
            timings["train_minutes"] = (time.perf_counter() - t0) / 60.0
            export = Path(stage_cfg.out_dir) / "model.pt"
        else:  # a render-time preset trains nothing: its out names the weights it scored
            stage_metrics, export = {}, weights
            out = Path(cfg.out_dir)
            out.mkdir(parents=True, exist_ok=True)
            digest = hashlib.sha256(weights.read_bytes()).hexdigest()
            (out / "weights.json").write_text(json.dumps({"weights": str(weights), "sha256": digest}, indent=1))
        mode = f"{stage_cfg.model.light_net.mode}/" if stage == "train_lighting" else ""
        metrics = {"available": 1.0, **{k.removeprefix(mode): v for k, v in stage_metrics.items()}}
        artifacts = [report / "preset.json"]
        if stage == "train_lighting":
            # the stage tested with its training layer: scored with another, its test numbers (and the
            # baselines' under that layer) stay in its own report and the test split is scored again
            score_cfg = scoring_config(cfg, stage_cfg)
            if weights is not None or score_cfg.render.estimator != stage_cfg.render.estimator:
                metrics = {k: v for k, v in metrics.items() if not k.startswith(("test/", "baseline/"))}
            tested = {k: v for k, v in metrics.items() if k.startswith("test/")} or None
            extra, extra_timings, worst, figures, per_view = lighting_extras(cfg, stage_cfg, score_cfg, export, tested)
            metrics.update(extra)
            timings.update(extra_timings)
            artifacts += list(write_view_outputs(report, worst, per_view))
            for figure in figures:
                mlflow.log_artifact(str(figure), "figures")
        else:  # the training stage's test maps (train_material always writes them), also on the ablate run
            write_view_outputs(report, [], [])  # a MaterialNet preset scores no views' light
            mlflow.log_artifact(str(Path(stage_cfg.report_dir) / "test_maps.png"), "figures")
        metrics.update(training_health(run.info.run_id, metrics))
        timings["stage_minutes"] = (time.perf_counter() - started) / 60.0  # from the start of run(): imports excluded
        publish(report, metrics, artifacts=tuple(artifacts), timings=timings)
    return metrics
