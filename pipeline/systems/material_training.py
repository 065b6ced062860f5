"""What the `train_material` stage does, shared by that stage and `ablate` (its presets train the same way),
the benches and the tests: building the system and scoring it, and the whole training run
(`train_material`). MaterialNet training -> test metrics, trivial baselines, gate, export.

Writes under `out_dir` (the DVC out): model.pt (the best weights with the network config, for `invrender
predict`), the same bytes for the same seed; beside it, under `checkpoint_dir(out_dir)`
(outputs/checkpoints/train_material): best.ckpt and last.ckpt (Lightning; they name the MLflow run,
for `resume=last`); under `report_dir`: metrics.json, test_views.csv (`test_view_scores`) and
test_maps.png.
"""

from __future__ import annotations

from pathlib import Path

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from pipeline.data.datamodules import InteriorVerseDataModule
from pipeline.data.datasets import read_manifest
from pipeline.metrics.synthetic import depth_mask, ls_scale, material_metrics
from pipeline.models.export import save_material_export
from pipeline.models.material_net import parameter_count
from pipeline.systems.material import METRICS, MaterialSystem
from pipeline.systems.material_baselines import MaterialBaselines, accuracy_gate
from pipeline.systems.trainer import checkpoint_dir, epoch_checkpoints, resume_checkpoint, stage_trainer
from pipeline.tracking import publish, stage_run
from pipeline.tracking.figures import map_comparison
from pipeline.tracking.views_file import write_views


@torch.no_grad()
def median_depth_scale(system: MaterialSystem, loader) -> float:
    """Median over views of the least-squares scale that maps the network's depth to metres."""
    system.eval()
    scales = []
    for batch in loader:
        m = depth_mask(batch["depth"], batch["mask"])
        pred = system.net(batch["im"].to(system.device))["depth"].cpu().double()
        gt = torch.where(m, batch["depth"], torch.zeros_like(batch["depth"])).double()
        s = ls_scale(pred, gt, m).flatten()
        scales.extend(s[m.flatten(1).any(1)].tolist())
    if not scales:
        raise ValueError("validation split has no valid depth pixels; cannot calibrate the depth scale")
    return float(torch.tensor(scales).median())


@torch.no_grad()
def test_view_scores(system: MaterialSystem, loader, baselines: MaterialBaselines) -> list[dict]:
    """One row per test view, in the loader's order: its id, the model's score on every test metric
    (`model/<metric>`) and every trivial baseline's (`<baseline>/<metric>`), by the functions the test
    pass scores with (`material_metrics`, `MaterialBaselines.metrics`). Both are per image, and the test
    pass's `test/` and `test_baseline/` numbers are their means over images (NaN, a view without valid
    pixels for a map, left out): the mean of a column over its finite values is the stage's number, up
    to the float32 the test pass accumulates in."""
    system.eval()
    rows = []
    for batch in loader:
        pred = {k: v.cpu() for k, v in system.net(batch["im"].to(system.device)).items()}
        per = {f"model/{k}": v for k, v in material_metrics(pred, batch).items()}
        per.update(baselines.metrics(batch))
        for i, view in enumerate(batch["id"]):
            rows.append({"id": view, **{k: float(v[i]) for k, v in per.items()}})
    return rows


def build_system(cfg: DictConfig) -> MaterialSystem:
    sched = OmegaConf.select(cfg, "optim.scheduler")
    return MaterialSystem(
        model=OmegaConf.to_container(cfg.model.material_net, resolve=True),
        loss=OmegaConf.to_container(cfg.loss, resolve=True),
        optimizer=instantiate(cfg.optim.optimizer),
        scheduler=instantiate(sched) if sched is not None else None,
        figure_every=int(cfg.figure_every),
        figure_views=int(cfg.figure_views),
    )


def build_datamodule(cfg: DictConfig) -> InteriorVerseDataModule:
    return InteriorVerseDataModule(
        cfg.data_dir,
        batch_size=int(cfg.batch_size),
        num_workers=int(cfg.num_workers),
        seed=int(cfg.seed),
        lighting=False,
        augment=bool(cfg.augment),
        permute=bool(cfg.augment_permute),
        min_scale=float(cfg.augment_min_scale),
    )


def train_material(cfg: DictConfig) -> dict[str, float]:
    """The `train_material` stage's work (`pipeline.runs.train_material.run` and each `ablate` preset that trains)."""
    import lightning as L
    import mlflow

    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    out, report = Path(cfg.out_dir), Path(cfg.report_dir)
    ckpt_dir = checkpoint_dir(out)
    resume, resume_run_id = resume_checkpoint(cfg.resume, ckpt_dir)
    source = read_manifest(cfg.data_dir).get("source", "unspecified")
    dm = build_datamodule(cfg)
    dm.setup("fit")
    dm.setup("test")
    baselines = MaterialBaselines.fit(dm.plain_loader("train"))
    system = build_system(cfg)
    tags = {"data_source": source}
    with stage_run("train_material", cfg, tags, bool(cfg.system_metrics), resume_run_id) as run:
        if run is not None and resume_run_id != run.info.run_id:  # a continued run has them already
            mlflow.log_params(
                {"loss.perceptual_on": system.loss.perceptual_on, "model.parameters": parameter_count(system.net)}
            )
        ckpt, last_ckpt = epoch_checkpoints(ckpt_dir, "val/loss", "min")
        trainer = stage_trainer(
            run, OmegaConf.to_container(cfg.trainer, resolve=True), ckpt_dir, [ckpt, last_ckpt], bool(cfg.progress)
        )
        trainer.fit(system, datamodule=dm, ckpt_path=resume, weights_only=True)
        best = ckpt.best_model_path or last_ckpt.best_model_path
        state = torch.load(best, map_location="cpu", weights_only=True)["state_dict"]
        system.load_state_dict(state)
        system.baselines = baselines
        trainer.test(system, datamodule=dm, verbose=False)
        if run is None:  # a distributed process other than rank 0: rank 0 reports, exports and tracks
            return {}
        logged = {k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("test")}
        model_metrics = {m: logged[f"test/{m}"] for m in METRICS}
        base_metrics = {
            k.removeprefix("test_baseline/"): v for k, v in logged.items() if k.startswith("test_baseline/")
        }
        metrics = {
            **{f"test/{k}": v for k, v in model_metrics.items()},
            **{f"baseline/{k}": v for k, v in base_metrics.items()},
            **accuracy_gate(model_metrics, base_metrics, float(cfg.gate_margin)),
            "epochs": float(trainer.current_epoch),
            "global_step": float(trainer.global_step),
            "parameters": float(parameter_count(system.net)),
        }
        if ckpt.best_model_score is not None:
            metrics["best_val_loss"] = float(ckpt.best_model_score)
        depth_scale = median_depth_scale(system, dm.plain_loader("val"))
        size = (dm.splits["train"].height, dm.splits["train"].width)
        model_path = save_material_export(out / "model.pt", system.hparams["model"], system.net, size, depth_scale)
        metrics["depth_scale"] = depth_scale
        views = write_views(report / "test_views.csv", test_view_scores(system, dm.test_dataloader(), baselines))
        publish(report, metrics, (views,))
        figure = _test_figure(system, dm, report / "test_maps.png", int(cfg.figure_views))
        mlflow.log_artifact(str(figure), "figures")
        mlflow.set_tag("model_path", str(model_path.resolve()))
    return metrics


@torch.no_grad()
def _test_figure(system: MaterialSystem, dm: InteriorVerseDataModule, path: Path, views: int) -> Path:
    system.eval()
    batch = next(iter(dm.plain_loader("test", batch_size=max(views, 1))))
    pred = system.net(batch["im"].to(system.device))
    return map_comparison({k: v.cpu() for k, v in pred.items()}, batch, path, title="test views")
