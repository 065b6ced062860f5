"""Stage `finetune`: MaterialNet fine-tuned on IIW judgements (ranking loss) and NYUv2 depth/normals mixed
with synthetic batches. Real data when `iiw_root` / `nyuv2_root` are set, otherwise format-faithful
stand-ins built from the synthetic test views (`data.standins`); every report names its source.

Writes under `out_dir` (the DVC out): model.pt (the MaterialNet export) and standins/, the same bytes
for the same seed; beside it, under `checkpoint_dir(out_dir)` (outputs/checkpoints/finetune): last.ckpt;
under `report_dir`: metrics.json and sources.json.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import DataLoader

from pipeline.data import iiw
from pipeline.data.benchmarks import IIWSet, NYUSet, collate_iiw, collate_nyu
from pipeline.data.datamodules import InteriorVerseDataModule
from pipeline.data.datasets import read_manifest
from pipeline.data.standins import benchmark_roots
from pipeline.models.export import save_material_export
from pipeline.models.material_net import load_material_export
from pipeline.systems.finetune import FinetuneSystem
from pipeline.systems.trainer import checkpoint_dir, stage_trainer
from pipeline.tracking import publish, stage_run


def run(cfg: DictConfig) -> dict[str, float]:
    import lightning as L
    import mlflow
    from lightning.pytorch.utilities import CombinedLoader

    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    net, meta = load_material_export(cfg.model_path)
    size = tuple(meta["input_size"])
    bench = benchmark_roots(cfg.iiw_root, cfg.nyuv2_root, cfg.standin_dir, cfg.data_dir, int(cfg.seed), cfg.standin)
    ft = cfg.finetune
    iiw_ids = iiw.split_ids(iiw.list_ids(bench["iiw"][0]))["train"]
    loaders = {
        "synthetic": InteriorVerseDataModule(
            cfg.data_dir, batch_size=int(ft.batch_size), seed=int(cfg.seed), lighting=False, augment=True
        ).train_dataloader(),
        "iiw": DataLoader(
            IIWSet(bench["iiw"][0], iiw_ids, size),
            batch_size=int(ft.batch_size),
            shuffle=True,
            generator=torch.Generator().manual_seed(int(cfg.seed)),
            collate_fn=collate_iiw,
        ),
        "nyu": DataLoader(
            NYUSet(bench["nyuv2"][0], "train", size),
            batch_size=int(ft.batch_size),
            shuffle=True,
            generator=torch.Generator().manual_seed(int(cfg.seed) + 1),
            collate_fn=collate_nyu,
        ),
    }
    sched = OmegaConf.select(cfg, "optim.scheduler")
    system = FinetuneSystem(
        model=meta["model"],
        weights=net.state_dict(),
        loss=OmegaConf.to_container(cfg.loss, resolve=True),
        optimizer=instantiate(cfg.optim.optimizer),
        scheduler=instantiate(sched) if sched is not None else None,
        iiw_weight=float(ft.iiw_weight),
        nyu_weight=float(ft.nyu_weight),
        ranking_margin=float(ft.ranking_margin),
    )
    sources = {"iiw": bench["iiw"][1], "nyuv2": bench["nyuv2"][1]}
    out, report = Path(cfg.out_dir), Path(cfg.report_dir)
    with stage_run("finetune", cfg, tags={"data_source": f"synthetic+{sources['iiw']}+{sources['nyuv2']}"}) as run:
        mlflow.log_params({"iiw_source": sources["iiw"], "nyuv2_source": sources["nyuv2"], "iiw_train": len(iiw_ids)})
        ckpt_dir = checkpoint_dir(out)
        trainer = stage_trainer(
            run, OmegaConf.to_container(cfg.trainer, resolve=True), ckpt_dir, (), bool(cfg.progress)
        )
        trainer.fit(system, train_dataloaders=CombinedLoader(loaders, mode="max_size_cycle"))
        trainer.save_checkpoint(ckpt_dir / "last.ckpt", weights_only=True)
        save_material_export(
            out / "model.pt",
            meta["model"],
            system.net,
            size,
            meta["depth_scale"],
            finetuned_on=[sources["iiw"], sources["nyuv2"]],
        )
        logged = {k: float(v) for k, v in trainer.callback_metrics.items() if k.endswith("_epoch") or "loss_" in k}
        metrics = {k.replace("finetune/", ""): v for k, v in logged.items()}
        metrics.update({"global_step": float(trainer.global_step), "iiw_train_images": float(len(iiw_ids))})
        metrics["nyu_train_images"] = float(len(loaders["nyu"].dataset))
        report.mkdir(parents=True, exist_ok=True)
        sources["synthetic"] = read_manifest(cfg.data_dir).get("source")
        (report / "sources.json").write_text(json.dumps(sources, indent=1) + "\n")
        publish(report, metrics, (report / "sources.json",))
    return metrics
