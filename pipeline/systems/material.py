"""LightningModule for MaterialNet: losses, synthetic-test metrics (torchmetrics), baselines, figures."""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from pathlib import Path

import lightning as L
import torch
from torchmetrics import MeanMetric, MetricCollection

from pipeline.metrics.synthetic import material_metrics
from pipeline.models.material_net import MaterialNet
from pipeline.systems.material_baselines import MaterialBaselines
from pipeline.systems.material_losses import MaterialLoss
from pipeline.tracking.figures import map_comparison

METRICS = ("albedo_mse", "normal_angle_deg", "roughness_mse", "metallic_mse", "depth_log_mse")


def _mean_metrics(keys) -> MetricCollection:
    # NaN (an image without valid pixels) is left out of the mean rather than poisoning it
    return MetricCollection({k.replace("/", "__"): MeanMetric(nan_strategy="ignore") for k in keys})


class MaterialSystem(L.LightningModule):
    """model: MaterialNet kwargs; loss: MaterialLoss kwargs; optimizer/scheduler: partials taking the
    parameters / the optimizer (Hydra `_partial_`); figure_every: epochs between MLflow figures of the
    first `figure_views` validation views (0 = never). Hyperparameters are stored as plain containers so
    checkpoints load with `weights_only=True`."""

    def __init__(
        self,
        model: dict,
        loss: dict,
        optimizer: Callable | None = None,
        scheduler: Callable | None = None,
        figure_every: int = 5,
        figure_views: int = 2,
    ):
        super().__init__()
        self.save_hyperparameters({"model": dict(model), "loss": dict(loss)})
        self.net = MaterialNet(**model)
        self.loss = MaterialLoss(**loss)
        self.optimizer_fn, self.scheduler_fn = optimizer, scheduler
        self.figure_every, self.figure_views = int(figure_every), int(figure_views)
        self.baselines: MaterialBaselines | None = None
        self.val_metrics = _mean_metrics(METRICS)
        self.test_metrics = _mean_metrics(METRICS)
        self.test_baseline_metrics: MetricCollection | None = None
        self._figure_batch: dict | None = None

    def forward(self, im: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.net(im)

    def _step(self, batch: dict, stage: str) -> tuple[torch.Tensor, dict]:
        pred = self.net(batch["im"])
        total, terms = self.loss(pred, batch)
        bs = batch["im"].shape[0]
        on_step = stage == "train"
        # sync_dist: means over every DDP process (a no-op in one process)
        self.log(f"{stage}/loss", total, on_step=on_step, on_epoch=True, prog_bar=True, batch_size=bs, sync_dist=True)
        for k, v in terms.items():
            self.log(f"{stage}/loss_{k}", v, on_step=on_step, on_epoch=True, batch_size=bs, sync_dist=True)
        return total, pred

    def training_step(self, batch, batch_idx):
        return self._step(batch, "train")[0]

    def validation_step(self, batch, batch_idx):
        _, pred = self._step(batch, "val")
        for k, v in material_metrics(pred, batch).items():
            self.val_metrics[k].update(v)
        if batch_idx == 0:
            n = self.figure_views
            self._figure_batch = {
                "pred": {k: v[:n].detach().cpu() for k, v in pred.items()},
                "batch": {k: (v[:n].cpu() if torch.is_tensor(v) else v[:n]) for k, v in batch.items() if k != "light"},
            }

    def on_validation_epoch_end(self):
        self.log_dict({f"val/{k}": m.compute() for k, m in self.val_metrics.items()}, sync_dist=True)
        self.val_metrics.reset()
        if self.figure_every and self._figure_batch is not None and self.current_epoch % self.figure_every == 0:
            self._log_figure()

    def _log_figure(self) -> None:
        import mlflow

        if mlflow.active_run() is None or self.trainer.sanity_checking:
            return
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / f"maps_epoch{self.current_epoch:03d}.png"
            fb = self._figure_batch
            map_comparison(fb["pred"], fb["batch"], path, title=f"epoch {self.current_epoch}")
            mlflow.log_artifact(str(path), "figures/val_maps")

    def test_step(self, batch, batch_idx):
        pred = self.net(batch["im"])
        for k, v in material_metrics(pred, batch).items():
            self.test_metrics[k].update(v)
        if self.baselines is not None:
            per = self.baselines.metrics(batch)
            if self.test_baseline_metrics is None:
                self.test_baseline_metrics = _mean_metrics(per).to(self.device)
            for k, v in per.items():
                self.test_baseline_metrics[k.replace("/", "__")].update(v)

    def on_test_epoch_end(self):
        self.log_dict({f"test/{k}": m.compute() for k, m in self.test_metrics.items()}, sync_dist=True)
        if self.test_baseline_metrics is not None:
            self.log_dict(
                {f"test_baseline/{k.replace('__', '/')}": m.compute() for k, m in self.test_baseline_metrics.items()},
                sync_dist=True,
            )

    def configure_optimizers(self):
        if self.optimizer_fn is None:
            raise ValueError("optim.optimizer is not set")
        opt = self.optimizer_fn(self.parameters())
        if self.scheduler_fn is None:
            return opt
        return {"optimizer": opt, "lr_scheduler": {"scheduler": self.scheduler_fn(opt), "interval": "epoch"}}
