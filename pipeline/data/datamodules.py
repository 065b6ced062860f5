"""LightningDataModule over the preprocess shards (train/val/test split by scene)."""

from __future__ import annotations

from pathlib import Path

import lightning as L
import torch
from torch.utils.data import DataLoader

from pipeline.data.datasets import ShardDataset, collate_views


class InteriorVerseDataModule(L.LightningDataModule):
    """Loads `<root>/manifest.json` shards; the train loader shuffles with a seeded generator."""

    def __init__(
        self, root: str | Path, batch_size: int = 8, num_workers: int = 0, seed: int = 0, lighting: bool = True
    ):
        super().__init__()
        self.root, self.batch_size, self.num_workers = Path(root), int(batch_size), int(num_workers)
        self.seed, self.lighting = int(seed), lighting
        self.splits: dict[str, ShardDataset] = {}

    def setup(self, stage: str | None = None) -> None:
        wanted = {"fit": ("train", "val"), "validate": ("val",), "test": ("test",), "predict": ("test",)}
        for split in wanted.get(stage, ("train", "val", "test")):
            if split not in self.splits:
                self.splits[split] = ShardDataset(self.root, split, lighting=self.lighting)

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        gen = torch.Generator().manual_seed(self.seed) if shuffle else None
        return DataLoader(
            self.splits[split],
            batch_size=self.batch_size,
            shuffle=shuffle,
            generator=gen,
            num_workers=self.num_workers,
            collate_fn=collate_views,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", True)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", False)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", False)
