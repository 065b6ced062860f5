"""Stage `ablate`: one `conf/ablation/` preset at one seed, trained under the ablation schedule (the
profile's `ablation_schedule`) by the preset's own stage (`train_lighting` or `train_material`, composed
with `ablation=<preset>`), and scored as the main stages score:

- the stage's test metrics (LightNet keys without their mode prefix, so presets share keys);
- LightNet presets: the insertion and editing scores of the `edit` stage for the preset's LightNet and
  the exposure-scaled constant on the same cases (paired; a preset trained on ground-truth G-buffers
  adds the `lightnet_gt_gbuffers` row), the median seconds of a full-frame re-render at the evaluation
  spp over `timing_views` test images, and for the `full` preset the test metrics and seconds at each
  test-time out-of-view threshold (`test_time_thresholds`: the out-of-view branch queried only where
  u >= t);
- the wall minutes of the training stage (fit, validation and test passes) and of each scoring step
  (`timing_`, `test_time_thresholds_`, `insertion_minutes`), and of the whole run (`stage_minutes`).

A preset that needs something absent here (`preset.requires`, e.g. VGG16 weights) reports
`available: 0` and why, and trains nothing: no pretend version.

Writes `outputs/ablate/<preset>-s<seed>/` (the stage's checkpoints and export) and
`reports/ablate/<preset>-s<seed>/{metrics.json, timings.json, preset.json}` (LightNet presets also
`worst_views.json` and `insertion_scatter.png`, every case's PSNR against the scaled constant's); the
stage's own report goes to `.../stage/`. One MLflow run `ablate-<profile>` per preset and seed (tags
preset, seed) holds them, its figures under `figures/` (a MaterialNet preset's test maps), with the
training stage's run nested in it.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from pipeline.data.datamodules import InteriorVerseDataModule
from pipeline.models.light_net import load_light_export
from pipeline.runs import edit, train_lighting, train_material
from pipeline.tracking import publish, stage_run
from pipeline.tracking.figures import paired_scatter

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"
STAGES = {"train_lighting": train_lighting, "train_material": train_material}
INSERTION_ROWS = ("lightnet", "scaled_constant")


def compose(name: str, overrides: list[str]) -> DictConfig:
    """Compose `conf/<name>.yaml` from inside a Hydra app (its search path) or from plain Python."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        return hydra_compose(config_name=name, overrides=overrides)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return hydra_compose(config_name=name, overrides=overrides)


def preset_stage(preset: str) -> str:
    """The training stage a preset applies to: the schedule it includes (`common/lighting` or
    `common/material`). Raises naming the preset file when it is missing or includes neither."""
    import yaml

    path = CONF_DIR / "ablation" / f"{preset}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise FileNotFoundError(f"ablation={preset}: no {path} (presets: {', '.join(known)})")
    defaults = (yaml.safe_load(path.read_text()) or {}).get("defaults") or []
    stages = {"common/lighting": "train_lighting", "common/material": "train_material"}
    found = [stages[d] for d in defaults if isinstance(d, str) and d in stages]
    if len(found) != 1:
        raise ValueError(f"{path}: its defaults must include exactly one of {sorted(stages)}")
    return found[0]


def stage_config(cfg: DictConfig) -> DictConfig:
    """The preset's training stage config: that stage's yaml with `ablation=<preset>`, this run's seed,
    profile, paths and tracking, its outputs under this run's folders."""
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
    return compose(preset_stage(str(cfg.preset)), [*common, *where, *list(cfg.stage_overrides)])


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
    return {f"test/{k}": v for k, v in train_lighting.test_scores(system, loader).items()}


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
    ctx = system.net.encode(batch["im"], gb["depth"], fov)
    pix = torch.nonzero(batch["mask"][:, 0].reshape(-1)).squeeze(-1)
    rgb, _ = system.eval_layer.render_pixels(gb, fov, pix, system.light_fn(ctx, gb, fov, gen), gen)
    return rgb


def lighting_extras(cfg: DictConfig, stage_cfg: DictConfig) -> tuple[dict, dict, list[dict], Path]:
    """(metrics, timings, worst views, figure) beyond the stage's own: insertion/editing scores, seconds
    per image, the test-time thresholds for the `full` preset, the views LightNet renders worst, and the
    per-case insertion figure (`insertion_figure`)."""
    export = Path(stage_cfg.out_dir) / "model.pt"
    net, _ = load_light_export(export)
    system = train_lighting.build_system(stage_cfg)
    system.net.load_state_dict(net.state_dict())
    dm = InteriorVerseDataModule(stage_cfg.data_dir, batch_size=int(stage_cfg.batch_size), seed=int(cfg.seed))
    views = list(dm.plain_loader("test", batch_size=1))[: int(cfg.timing_views)]
    base = float(stage_cfg.model.light_net.out_threshold)
    t0 = time.perf_counter()
    metrics, timings = {}, {"seconds_per_image": seconds_per_image(system, views, base)}
    timings["timing_minutes"] = (time.perf_counter() - t0) / 60.0
    t0 = time.perf_counter()
    if str(cfg.preset) == "full":  # the out-of-view branch queried only where SSRT is unsure (u >= t)
        for t in cfg.test_time_thresholds:
            if float(t) == base:  # the preset's own threshold: its stage's test pass already scored it
                continue
            tested = lighting_test(system, dm.plain_loader("test"), float(t))
            metrics.update({f"out_threshold_{float(t):g}/{k}": v for k, v in tested.items()})
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
            f"render={stage_cfg.render.estimator}",  # the preset's estimator (its option names it)
            f"bootstrap={int(cfg.bootstrap)}",
        ],
    )
    rows = (
        INSERTION_ROWS if stage_cfg.gbuffers == "predicted" else ("lightnet", "lightnet_gt_gbuffers", "scaled_constant")
    )
    insertion, records = edit.score_rows(edit_cfg, rows, progress=bool(cfg.progress))
    metrics.update({f"edit/{k}": v for k, v in insertion.items()})
    timings["insertion_minutes"] = (time.perf_counter() - t0) / 60.0
    worst = worst_views(records, int(cfg.worst_views))
    figure = insertion_figure(records, Path(cfg.report_dir) / "insertion_scatter.png", f"{cfg.preset}, seed {cfg.seed}")
    return metrics, timings, worst, figure


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
    report.mkdir(parents=True, exist_ok=True)
    why = unavailable(stage_cfg)
    described = {**preset, "seed": int(cfg.seed), **({"unavailable": why} if why is not None else {})}
    (report / "preset.json").write_text(json.dumps(described, indent=1))
    with stage_run("ablate", cfg, tags=tags) as run:
        if why is not None:
            mlflow.set_tag("unavailable", why)
            out = Path(cfg.out_dir)  # the stage's out exists and says why it holds no model
            out.mkdir(parents=True, exist_ok=True)
            (out / "UNAVAILABLE.txt").write_text(f"ablation={cfg.preset} did not run: {why}\n")
            publish(report, {"available": 0.0}, artifacts=(report / "preset.json",))
            return {"available": 0.0}
        t0 = time.perf_counter()
        stage_metrics = STAGES[stage].run(stage_cfg)
        minutes = (time.perf_counter() - t0) / 60.0
        mode = f"{stage_cfg.model.light_net.mode}/" if stage == "train_lighting" else ""
        metrics = {"available": 1.0, **{k.removeprefix(mode): v for k, v in stage_metrics.items()}}
        timings = {"train_minutes": minutes}
        artifacts = [report / "preset.json"]
        if stage == "train_lighting":
            extra, extra_timings, worst, figure = lighting_extras(cfg, stage_cfg)
            metrics.update(extra)
            timings.update(extra_timings)
            (report / "worst_views.json").write_text(json.dumps(worst, indent=1))
            artifacts.append(report / "worst_views.json")
            mlflow.log_artifact(str(figure), "figures")
        else:  # the training stage's test maps (train_material always writes them), also on the ablate run
            mlflow.log_artifact(str(Path(stage_cfg.report_dir) / "test_maps.png"), "figures")
        metrics.update(training_health(run.info.run_id, metrics))
        timings["stage_minutes"] = (time.perf_counter() - started) / 60.0  # from the start of run(): imports excluded
        publish(report, metrics, artifacts=tuple(artifacts), timings=timings)
    return metrics
