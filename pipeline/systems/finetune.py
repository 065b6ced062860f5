"""Fine-tuning MaterialNet on real-image supervision (docs/design.md, section 5): albedo on IIW judgements with
Li et al. 2020's ranking loss, depth and normals on NYUv2, each batch mixed with a synthetic one."""

from __future__ import annotations

from collections.abc import Callable

import lightning as L
import torch

from pipeline.models.material_net import MaterialNet
from pipeline.systems.material_losses import MaterialLoss, depth_loss, normal_loss, ranking_loss


class FinetuneSystem(L.LightningModule):
    """Training batches are dicts {"synthetic", "iiw", "nyu"} (Lightning's CombinedLoader); the loss is
    synthetic MaterialLoss + iiw_weight * ranking + nyu_weight * (depth + normal). model: MaterialNet
    kwargs; weights: the state dict to start from."""

    def __init__(
        self,
        model: dict,
        weights: dict,
        loss: dict,
        optimizer: Callable,
        scheduler: Callable | None = None,
        iiw_weight: float = 1.0,
        nyu_weight: float = 1.0,
        ranking_margin: float = 0.5,
    ):
        super().__init__()
        self.save_hyperparameters({"model": dict(model), "loss": dict(loss)})
        self.net = MaterialNet(**model)
        self.net.load_state_dict(weights)
        self.loss = MaterialLoss(**loss)
        self.optimizer_fn, self.scheduler_fn = optimizer, scheduler
        self.iiw_weight, self.nyu_weight, self.margin = float(iiw_weight), float(nyu_weight), float(ranking_margin)

    def training_step(self, batch, batch_idx):
        terms = {}
        syn = batch["synthetic"]
        terms["synthetic"], _ = self.loss(self.net(syn["im"]), syn)
        iiw = batch.get("iiw")
        if iiw is not None:
            terms["iiw_ranking"] = ranking_loss(self.net(iiw["im"])["albedo"], iiw["comparisons"], self.margin)
        nyu = batch.get("nyu")
        if nyu is not None:
            pred = self.net(nyu["im"])
            terms["nyu_depth"] = depth_loss(pred["depth"], nyu["depth"], torch.ones_like(nyu["mask"]))
            terms["nyu_normal"] = normal_loss(pred["normal"], nyu["normal"], nyu["mask"])
        total = (
            terms["synthetic"]
            + self.iiw_weight * terms.get("iiw_ranking", 0.0)
            + self.nyu_weight * (terms.get("nyu_depth", 0.0) + terms.get("nyu_normal", 0.0))
        )
        bs = syn["im"].shape[0]
        self.log("finetune/loss", total, on_step=True, on_epoch=True, prog_bar=True, batch_size=bs)
        for k, v in terms.items():
            self.log(f"finetune/loss_{k}", v, on_step=False, on_epoch=True, batch_size=bs)
        return total

    def configure_optimizers(self):
        opt = self.optimizer_fn(self.parameters())
        if self.scheduler_fn is None:
            return opt
        return {"optimizer": opt, "lr_scheduler": {"scheduler": self.scheduler_fn(opt), "interval": "epoch"}}
