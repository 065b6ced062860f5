"""Checkpoint callbacks of the training stages: last.ckpt holds the last epoch, best.ckpt the best one."""

import lightning as L
import torch

from pipeline.systems.trainer import epoch_checkpoints, stage_trainer

EPOCHS = 4


class WorseningModule(L.LightningModule):
    """One weight, stepped by SGD on a constant loss; its validation score gets worse every epoch, so
    epoch 0 stays the best and every later epoch is one that does not improve."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(()))

    def training_step(self, batch, batch_idx):
        return self.w * batch.sum()

    def validation_step(self, batch, batch_idx):
        self.log("val/score", float(self.current_epoch))

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)

    def train_dataloader(self):
        return torch.utils.data.DataLoader(torch.ones(2, 1), batch_size=1)

    def val_dataloader(self):
        return torch.utils.data.DataLoader(torch.ones(1, 1), batch_size=1)


def test_last_checkpoint_is_the_last_epoch_after_epochs_without_improvement(tmp_path):
    best, last = epoch_checkpoints(tmp_path / "checkpoints", "val/score", "min")
    trainer = stage_trainer(None, {"max_epochs": EPOCHS}, tmp_path, [best, last], progress=False)
    trainer.fit(WorseningModule())
    ckpt_dir = tmp_path / "checkpoints"
    saved = {name: torch.load(ckpt_dir / f"{name}.ckpt", weights_only=True) for name in ("best", "last")}
    assert sorted(p.name for p in ckpt_dir.iterdir()) == ["best.ckpt", "last.ckpt"]
    assert saved["best"]["epoch"] == 0 and best.best_model_path.endswith("best.ckpt")
    assert saved["last"]["epoch"] == EPOCHS - 1 and saved["last"]["global_step"] == 2 * EPOCHS
    assert last.best_model_path.endswith("last.ckpt")


def test_last_checkpoint_follows_unvalidated_epochs_and_resumes(tmp_path):
    # validation every second epoch: epochs 0 and 2 end without one, and last.ckpt must still follow them
    ckpt_dir = tmp_path / "checkpoints"

    def fit(max_epochs, ckpt_path=None):
        best, last = epoch_checkpoints(ckpt_dir, "val/score", "min")
        trainer = stage_trainer(
            None, {"max_epochs": max_epochs, "check_val_every_n_epoch": 2}, tmp_path, [best, last], progress=False
        )
        trainer.fit(WorseningModule(), ckpt_path=ckpt_path, weights_only=True)
        return {name: torch.load(ckpt_dir / f"{name}.ckpt", weights_only=True)["epoch"] for name in ("best", "last")}

    assert fit(3) == {"best": 1, "last": 2}
    # resumed from last.ckpt (epoch 2 done): two more epochs, the best still the first validated one
    assert fit(5, ckpt_path=str(ckpt_dir / "last.ckpt")) == {"best": 1, "last": 4}
    assert sorted(p.name for p in ckpt_dir.iterdir()) == ["best.ckpt", "last.ckpt"]
