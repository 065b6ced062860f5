"""What the `train_lighting` stage does, shared by that stage and `ablate` (its presets train the same way),
the benches and the tests: building the system and scoring it, and the whole training run
(`train_lighting`). LightNet trained with the HDR light loss and the MC re-rendering loss, scored
on the test split beside content-blind baselines and oracles (`systems.lighting_baselines`).

Writes under `out_dir` (the DVC out): model.pt (the LightNet export with the weights `test_weights`
names), the same bytes for the same seed; beside it, under `checkpoint_dir(out_dir)`
(outputs/checkpoints/train_lighting): best.ckpt and last.ckpt (Lightning; they name the MLflow run, for
`resume=last`); under `report_dir`: metrics.json, test_views.csv (`view_rows`), rerender.png, envmaps.png.
"""

from __future__ import annotations

from pathlib import Path

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from pipeline.data.datamodules import InteriorVerseDataModule
from pipeline.data.datasets import read_manifest
from pipeline.models.export import save_light_export
from pipeline.models.material_net import load_material_export
from pipeline.systems.lighting import LightingSystem
from pipeline.systems.lighting_baselines import mean_training_radiance
from pipeline.systems.lighting_figures import lighting_figures
from pipeline.systems.trainer import checkpoint_dir, epoch_checkpoints, gather_rows, resume_checkpoint, stage_trainer
from pipeline.tracking import publish, stage_run
from pipeline.tracking.views_file import write_views

TEST_WEIGHTS = ("last", "best")  # `test_weights`: the last epoch's, or the best validated re-render's


def build_system(cfg: DictConfig) -> LightingSystem:
    material = None
    if cfg.gbuffers == "predicted":
        _, material = load_material_export(cfg.material_path)
    sched = OmegaConf.select(cfg, "optim.scheduler")
    lt = cfg.lighting
    return LightingSystem(
        light_net=OmegaConf.to_container(cfg.model.light_net, resolve=True),
        material=material,
        render=OmegaConf.to_container(cfg.render, resolve=True),
        gbuffers=str(cfg.gbuffers),
        pixels=int(lt.pixels),
        probes=int(lt.probes),
        texels=int(lt.texels),
        free_probes=int(lt.free_probes),
        render_weight=float(lt.render_weight),
        light_weight=float(lt.light_weight),
        light_loss=str(lt.light_loss),
        nmse_weight=float(lt.nmse_weight),
        eval_stride=int(lt.eval_stride),
        ssrt_depth=str(lt.get("ssrt_depth", "valid")),
        render_loss=str(lt.render_loss),
        optimizer=instantiate(cfg.optim.optimizer),
        scheduler=instantiate(sched) if sched is not None else None,
        seed=int(cfg.seed),
    )


def initialise_from_export(system: LightingSystem, path) -> list[str]:
    """Load a LightNet export's weights (`models.export`, e.g. `invrender import-released lightnet`) into
    the system's network before training (`init_light_path`). The export's LightNet options must be the
    configured ones: every differing option is named and nothing is loaded. Returns the options checked."""
    from pipeline.models.export import LIGHT_FORMAT, ExportError, read_export

    blob = read_export(path, LIGHT_FORMAT)
    want = system.hparams["light_net"]
    differ = sorted(k for k in set(want) | set(blob["light_net"]) if want.get(k) != blob["light_net"].get(k))
    if differ:
        detail = "; ".join(f"{k}: export {blob['light_net'].get(k)!r}, config {want.get(k)!r}" for k in differ)
        raise ExportError(f"{path}: its LightNet options differ from model.light_net ({detail})")
    try:
        system.net.load_state_dict(blob["state_dict"])
    except RuntimeError as exc:
        raise ExportError(f"{path}: incompatible with the configured LightNet ({exc})") from exc
    return sorted(want)


@torch.no_grad()
def test_scores(system: LightingSystem, loader, views: list[dict] | None = None) -> dict[str, float]:
    """`evaluate_batch` over `loader`'s batches, each metric the mean weighted by batch size as Lightning
    reduces the test step's logs, outside Lightning (before training: the seeded initialisation, which
    then stays out of the run's `test/` history). views (a list): each view's own scores appended, one
    dict per view with its id, as the test step collects them. The system's train/eval mode is restored
    afterwards."""
    was_training = system.training
    system.eval()
    sums, weights = {}, {}
    for batch in loader:
        n = len(batch["im"])
        per = None if views is None else [{"id": view} for view in batch["id"]]
        for k, v in system.evaluate_batch(batch, per).items():
            sums[k], weights[k] = sums.get(k, 0.0) + v * n, weights.get(k, 0) + n
        if views is not None:
            views.extend(per)
    system.train(was_training)
    return {k: sums[k] / weights[k] for k in sums}


def view_rows(mode: str, tested: list[dict], untrained: list[dict] | None = None) -> list[dict]:
    """test_views.csv's rows from the test step's per-view scores (`LightingSystem.test_views`): the
    model's metrics as `<mode>/<metric>` (first, so the file names the model before the baselines; the
    baselines' `model/render_psnr_at_probes` too), each baseline's as `<baseline>/<metric>`, and the
    untrained network's (`untrained`, `test_scores`'s views) as `<mode>/untrained/<metric>`.

    Each value is that view's own: the metric's function on the view's texels or pixels alone, with the
    draws the batch's evaluation made (`systems.per_view`). metrics.json holds means over test batches
    (weighted by batch size) of values pooled over each batch's views, so a column's mean equals the
    stage's number when the test batches hold one view each (batch_size=1); otherwise relMSE and log-L1
    are the texel- or pixel-count-weighted means of their batch's views, and PSNR and nMSE (a log and a
    ratio of sums) are not means of the views' values."""
    before = {r["id"]: r for r in untrained or []}
    rows = []
    for view in tested:
        row = {"id": view["id"]}
        row.update({f"{mode}/{k}": v for k, v in view.items() if k != "id" and "/" not in k})
        row.update(
            {
                f"{mode}/{k.removeprefix('model/')}" if k.startswith("model/") else k: v
                for k, v in view.items()
                if "/" in k
            }
        )
        row.update({f"{mode}/untrained/{k}": v for k, v in before.get(view["id"], {}).items() if k != "id"})
        rows.append(row)
    return rows


def train_lighting(cfg: DictConfig) -> dict[str, float]:
    """The `train_lighting` stage's work (`pipeline.runs.train_lighting.run` and each `ablate` preset that trains)."""
    import lightning as L
    import mlflow

    if cfg.test_weights not in TEST_WEIGHTS:
        raise ValueError(f"test_weights={cfg.test_weights!r}: choose one of {TEST_WEIGHTS}")
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    system = build_system(cfg)
    if cfg.get("init_light_path"):  # start from an export's weights instead of the seeded initialisation
        initialise_from_export(system, cfg.init_light_path)
    dm = InteriorVerseDataModule(cfg.data_dir, batch_size=int(cfg.batch_size), seed=int(cfg.seed), lighting=True)
    dm.setup("fit")
    dm.setup("test")
    constants = mean_training_radiance(dm.plain_loader("train"))
    out, report = Path(cfg.out_dir), Path(cfg.report_dir)
    source = read_manifest(cfg.data_dir).get("source", "unspecified")
    mode = str(cfg.model.light_net.mode)
    tags = {"data_source": source, "mode": mode, "render": str(cfg.render.estimator)}
    ckpt_dir = checkpoint_dir(out)
    resume, resume_run_id = resume_checkpoint(cfg.resume, ckpt_dir)
    with stage_run("train_lighting", cfg, tags=tags, resume_run_id=resume_run_id) as run:
        ckpt, last_ckpt = epoch_checkpoints(ckpt_dir, "val/render_psnr", "max")
        trainer = stage_trainer(
            run, OmegaConf.to_container(cfg.trainer, resolve=True), ckpt_dir, [ckpt, last_ckpt], bool(cfg.progress)
        )
        # the first validation pass (before any training step) records the starting re-render PSNR; a
        # resumed run repeats it on the same seeded initialisation, so it reports the same number
        start = trainer.validate(system, datamodule=dm, verbose=False)[0] if cfg.lighting.validate_before else None
        untrained_views = []
        untrained = test_scores(system, dm.test_dataloader(), untrained_views) if cfg.lighting.test_before else {}
        trainer.fit(system, datamodule=dm, ckpt_path=resume, weights_only=True)
        if system.validated_at_step == trainer.global_step:  # the last epoch was validated: same weights
            last = float(trainer.callback_metrics["val/render_psnr"])
        else:
            last = float(trainer.validate(system, datamodule=dm, verbose=False)[0]["val/render_psnr"])
        # test_weights=best: the test split, the baselines' model row and model.pt use the best validated
        # re-render instead of the last epoch (for a constant rate, whose late epochs jump; with the cosine
        # schedule the best re-render is often an early epoch with the worst light errors)
        chosen, after = "last", last
        if (
            cfg.test_weights == "best"
            and ckpt.best_model_path
            and ckpt.best_model_score is not None
            and float(ckpt.best_model_score) > last
        ):
            best = torch.load(ckpt.best_model_path, map_location="cpu", weights_only=True)
            system.load_state_dict(best["state_dict"])
            chosen, after = f"best (epoch {best['epoch']})", float(ckpt.best_model_score)
        mlflow.set_tag("test_weights", chosen)
        system.baselines = constants
        trainer.test(system, datamodule=dm, verbose=False)
        tested = gather_rows(system.test_views)  # every process's test views (each scored its share)
        if run is None:  # a distributed process other than rank 0: rank 0 reports, exports and tracks
            return {}
        logged = {
            k.removeprefix("test/"): float(v) for k, v in trainer.callback_metrics.items() if k.startswith("test/")
        }
        metrics = {f"{mode}/test/{k}": v for k, v in logged.items() if "/" not in k}
        metrics.update({f"baseline/{k}": v for k, v in logged.items() if "/" in k})
        if start is not None:
            metrics[f"{mode}/val/render_psnr_before_training"] = float(start["val/render_psnr"])
        metrics.update({f"{mode}/untrained/test/{k}": v for k, v in untrained.items()})
        metrics[f"{mode}/val/render_psnr_after_training"] = after
        metrics[f"{mode}/val/render_psnr_last_epoch"] = last
        metrics["global_step"] = float(trainer.global_step)
        save_light_export(out / "model.pt", system.hparams["light_net"], system.net)
        views = write_views(report / "test_views.csv", view_rows(mode, tested, untrained_views))
        publish(report, metrics, (views,))
        if int(cfg.lighting.figure_views) > 0:
            batch = next(iter(dm.plain_loader("test", batch_size=int(cfg.lighting.figure_views))))
            for figure in lighting_figures(system, batch, constants, report):
                mlflow.log_artifact(str(figure), "figures")
    return metrics
