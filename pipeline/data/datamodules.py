"""LightningDataModule over the preprocess shards (train/val/test split by scene)."""

from __future__ import annotations

from pathlib import Path

import lightning as L
import torch
from torch.utils.data import DataLoader

from pipeline.data.datasets import ShardDataset, augment_views, collate_views


class InteriorVerseDataModule(L.LightningDataModule):
    """Loads `<root>/manifest.json` shards; the train loader shuffles with a seeded generator and, with
    `augment`, mirrors views and permutes their colour channels at random (seeded, see `augment_views`).

    The two generators live as long as the module and their states travel in Lightning checkpoints
    (`state_dict`), so a run resumed from an epoch-end checkpoint draws the same order and the same
    augmentations for its next epoch as the uninterrupted run does."""

    def __init__(
        self,
        root: str | Path,
        batch_size: int = 8,
        num_workers: int = 0,
        seed: int = 0,
        lighting: bool = True,
        augment: bool = False,
        permute: bool = True,
        min_scale: float = 1.0,
    ):
        super().__init__()
        if batch_size < 1:
            raise ValueError(f"batch_size={batch_size}: must be >= 1")
        self.root, self.batch_size, self.num_workers = Path(root), int(batch_size), int(num_workers)
        self.seed, self.lighting, self.augment = int(seed), lighting, augment
        self.permute, self.min_scale = bool(permute), float(min_scale)
        if not 0.0 < self.min_scale <= 1.0:
            raise ValueError(f"min_scale={min_scale}: must be in (0, 1] (1 = no crop augmentation)")
        self.splits: dict[str, ShardDataset] = {}
        self.shuffle_generator = torch.Generator().manual_seed(self.seed)
        self.augment_generator = torch.Generator().manual_seed(self.seed + 1)

    def state_dict(self) -> dict:
        return {
            "shuffle_generator": self.shuffle_generator.get_state(),
            "augment_generator": self.augment_generator.get_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.shuffle_generator.set_state(state["shuffle_generator"])
        self.augment_generator.set_state(state["augment_generator"])

    def setup(self, stage: str | None = None) -> None:
        wanted = {"fit": ("train", "val"), "validate": ("val",), "test": ("test",), "predict": ("test",)}
        for split in wanted.get(stage, ("train", "val", "test")):
            if split not in self.splits:
                self.splits[split] = ShardDataset(self.root, split, lighting=self.lighting)

    def _loader(self, split: str, shuffle: bool, augment: bool = False, batch_size: int | None = None) -> DataLoader:
        if split not in self.splits:
            self.setup({"train": "fit", "val": "validate", "test": "test"}[split])
        if len(self.splits[split]) == 0:
            raise ValueError(f"{self.root}: split {split!r} has no views")
        gen = self.shuffle_generator if shuffle else None
        collate = collate_views
        if augment:
            aug_gen = self.augment_generator

            def collate(items):
                return augment_views(collate_views(items), aug_gen, self.permute, self.min_scale)

        return DataLoader(
            self.splits[split],
            batch_size=batch_size or self.batch_size,
            shuffle=shuffle,
            generator=gen,
            num_workers=self.num_workers,
            collate_fn=collate,
        )

    def plain_loader(self, split: str, batch_size: int | None = None) -> DataLoader:
        """In order, no augmentation (statistics, figures)."""
        return self._loader(split, False, batch_size=batch_size)

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", True, augment=self.augment)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", False)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", False)
