"""LightningModule that scores a MaterialNet export on the benchmark test sets through `Trainer.test`.

Test dataloaders, in order (`BENCHMARKS`), each yielding one image per batch as the protocols of
docs/design.md, section 6, score one image at a time:
  iiw        {"id", "photo" (H, W, 3) uint8 sRGB, "judgements"}: WHDR in % (gamma and linear conventions)
  nyuv2      {"index", "photo", "depth" (H, W) m, "normal" (H, W, 3), "valid" (H, W)}: normal angle, si-RMSE,
             median-scaled depth errors, and the angles for the pooled statistics
The synthetic test split is scored once per model beside its baselines by `out_of_distribution`
(`material_view_rows`), not here.
Per-image rows are kept in `rows[benchmark]` (written as CSV by the stage); their means are logged per
model and benchmark.
"""

from __future__ import annotations

from pathlib import Path

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from pipeline.data import iiw, nyuv2
from pipeline.data.formats.photo import srgb8_to_linear
from pipeline.metrics import depth as depth_metrics
from pipeline.metrics import normal as normal_metrics
from pipeline.metrics.whdr import whdr
from pipeline.models.material_net import MaterialNet, predict_maps

BENCHMARKS = ("iiw", "nyuv2")


class IIWTest(Dataset):
    """IIW test images (every 5th id sorted as strings) with their judgements."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.ids = iiw.split_ids(iiw.list_ids(self.root))["test"]

    def __len__(self):
        return len(self.ids)

    def __getitem__(self, i):
        image_id = self.ids[i]
        return {
            "id": image_id,
            "photo": iiw.read_photo(self.root, image_id),
            "judgements": iiw.read_judgements(self.root, image_id),
        }


class NYUTest(Dataset):
    """NYUv2 test images (splits.mat testNdxs) with depth, ground-truth normals and their mask."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.mat = self.root / "nyu_depth_v2_labeled.mat"
        self.indices = [
            int(i) for i in nyuv2.read_splits(self.root / "splits.mat", nyuv2.count_images(self.mat))["test"]
        ]

    def __len__(self):
        return len(self.indices)

    def __getitem__(self, i):
        index = self.indices[i]
        images, depths = nyuv2.read_labeled(self.mat, [index])
        normal, valid = nyuv2.read_normal(self.root / "normals", self.root / "masks", index, depths[0].shape)
        return {"index": index, "photo": images[0], "depth": depths[0], "normal": normal, "valid": valid}


def one_item(items: list):
    return items[0]


def test_loaders(iiw_root, nyu_root) -> list[DataLoader]:
    """The test dataloaders in `BENCHMARKS` order, one image per batch."""
    sets = (IIWTest(iiw_root), NYUTest(nyu_root))
    for name, ds, root in zip(BENCHMARKS, sets, (iiw_root, nyu_root), strict=True):
        if len(ds) == 0:
            raise ValueError(f"the {name} test split is empty ({root})")
    return [DataLoader(ds, batch_size=1, collate_fn=one_item) for ds in sets]


class BenchmarkEvaluation(L.LightningModule):
    """net: a MaterialNet export's network; meta: the export (input_size, depth_scale); name: the model's
    name in the stage (`trained`, `finetuned`), the prefix of what it logs (`test/<name>/<bench>/<score>`),
    so two models scored in one MLflow run do not write the same metric."""

    def __init__(self, net: MaterialNet, meta: dict, name: str = "model"):
        super().__init__()
        self.net, self.meta, self.name = net.eval(), meta, name
        self.rows: dict[str, list[dict]] = {b: [] for b in BENCHMARKS}
        self.pooled_angles: list[np.ndarray] = []

    @torch.no_grad()
    def test_step(self, item, batch_idx, dataloader_idx: int = 0):
        bench = BENCHMARKS[dataloader_idx]
        row = getattr(self, f"_score_{bench}")(item)
        self.rows[bench].append(row)
        for k, v in row.items():
            if k not in ("id", "index"):
                self.log(f"test/{self.name}/{bench}/{k}", float(v), batch_size=1, add_dataloader_idx=False)

    def _score_iiw(self, item) -> dict:
        albedo = predict_maps(self.net, self.meta, srgb8_to_linear(item["photo"]))["albedo"]
        return {
            "id": item["id"],
            "whdr_gamma": 100 * whdr(albedo, item["judgements"], convention="gamma"),
            "whdr_linear": 100 * whdr(albedo, item["judgements"], convention="linear"),
        }

    def _score_nyuv2(self, item) -> dict:
        maps = predict_maps(self.net, self.meta, srgb8_to_linear(item["photo"]), renormalize_normals=False)
        gt_n, valid, depth = item["normal"], item["valid"], item["depth"]
        self.pooled_angles.append(normal_metrics.angles(maps["normal"], gt_n, valid, renormalize=True))
        pred_m = maps["depth"] / 1000.0
        return {
            "index": item["index"],
            "normal_deg": normal_metrics.mean_angular_error(maps["normal"], gt_n, valid),
            "normal_deg_renormalized": normal_metrics.mean_angular_error(maps["normal"], gt_n, valid, True),
            "depth_si": depth_metrics.si_rmse(pred_m, depth),
            "depth_si_nosqrt": depth_metrics.si_error(pred_m, depth),
            **depth_metrics.median_scaled(pred_m, depth),
        }
