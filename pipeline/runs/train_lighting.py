"""Stage `train_lighting`: LightNet trained with the HDR light loss and the MC re-rendering loss, scored
on the test split beside content-blind baselines and oracles (`systems.lighting_baselines`).

Writes under `out_dir`: checkpoints/best.ckpt and last.ckpt (Lightning), model.pt (the LightNet export
with the weights `test_weights` names); under `report_dir`: metrics.json, rerender.png, envmaps.png.
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
from pipeline.systems.trainer import epoch_checkpoints, resume_checkpoint, stage_trainer
from pipeline.tracking import publish, stage_run

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
        optimizer=instantiate(cfg.optim.optimizer),
        scheduler=instantiate(sched) if sched is not None else None,
        seed=int(cfg.seed),
    )


@torch.no_grad()
def test_scores(system: LightingSystem, loader) -> dict[str, float]:
    """`evaluate_batch` over `loader`'s batches, each metric the mean weighted by batch size as Lightning
    reduces the test step's logs, outside Lightning (before training: the seeded initialisation, which
    then stays out of the run's `test/` history). The system's train/eval mode is restored afterwards."""
    was_training = system.training
    system.eval()
    sums, weights = {}, {}
    for batch in loader:
        n = len(batch["im"])
        for k, v in system.evaluate_batch(batch).items():
            sums[k], weights[k] = sums.get(k, 0.0) + v * n, weights.get(k, 0) + n
    system.train(was_training)
    return {k: sums[k] / weights[k] for k in sums}


def run(cfg: DictConfig) -> dict[str, float]:
    import lightning as L
    import mlflow

    if cfg.test_weights not in TEST_WEIGHTS:
        raise ValueError(f"test_weights={cfg.test_weights!r}: choose one of {TEST_WEIGHTS}")
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    system = build_system(cfg)
    dm = InteriorVerseDataModule(cfg.data_dir, batch_size=int(cfg.batch_size), seed=int(cfg.seed), lighting=True)
    dm.setup("fit")
    dm.setup("test")
    constants = mean_training_radiance(dm.plain_loader("train"))
    out, report = Path(cfg.out_dir), Path(cfg.report_dir)
    source = read_manifest(cfg.data_dir).get("source", "unspecified")
    mode = str(cfg.model.light_net.mode)
    tags = {"data_source": source, "mode": mode, "render": str(cfg.render.estimator)}
    resume, resume_run_id = resume_checkpoint(cfg.resume, out / "checkpoints")
    with stage_run("train_lighting", cfg, tags=tags, resume_run_id=resume_run_id) as run:
        ckpt, last_ckpt = epoch_checkpoints(out / "checkpoints", "val/render_psnr", "max")
        trainer = stage_trainer(
            run, OmegaConf.to_container(cfg.trainer, resolve=True), out, [ckpt, last_ckpt], bool(cfg.progress)
        )
        # the first validation pass (before any training step) records the starting re-render PSNR; a
        # resumed run repeats it on the same seeded initialisation, so it reports the same number
        start = trainer.validate(system, datamodule=dm, verbose=False)[0] if cfg.lighting.validate_before else None
        untrained = test_scores(system, dm.test_dataloader()) if cfg.lighting.test_before else {}
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
        publish(report, metrics)
        if int(cfg.lighting.figure_views) > 0:
            batch = next(iter(dm.plain_loader("test", batch_size=int(cfg.lighting.figure_views))))
            for figure in lighting_figures(system, batch, constants, report):
                mlflow.log_artifact(str(figure), "figures")
    return metrics
