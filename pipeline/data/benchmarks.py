"""Torch datasets over IIW and NYUv2 layouts (real or stand-in) at a network's input size.

Images become linear RGB (sRGB decoding) resized with an area filter to (height, width); IIW points keep
their normalised coordinates, so a point lands where truncation puts it at the network resolution.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F
from torch.utils.data import Dataset

from pipeline.data import iiw, nyuv2
from pipeline.data.formats.photo import srgb8_to_linear

LABEL_CODES = {"1": 0, "2": 1, "E": 2}


def _to_tensor_image(srgb8: np.ndarray, size: tuple[int, int]) -> torch.Tensor:
    lin = torch.from_numpy(srgb8_to_linear(srgb8)).permute(2, 0, 1)[None]
    return F.interpolate(lin, size=size, mode="area")[0]


def comparisons_tensor(judgements: dict, size: tuple[int, int]) -> dict[str, torch.Tensor]:
    """The comparisons that count for WHDR (valid label, weight > 0, both points opaque) as tensors:
    p1, p2 (K, 2) long (row, col) at `size`; label (K,) long (0: point 1 darker, 1: point 2, 2: equal);
    weight (K,) float."""
    H, W = size
    pts = {p["id"]: p for p in judgements["intrinsic_points"]}
    rows = []
    for c in judgements["intrinsic_comparisons"]:
        w, d = c.get("darker_score"), c.get("darker")
        a, b = pts[c["point1"]], pts[c["point2"]]
        if d not in LABEL_CODES or w is None or not w > 0 or not (a["opaque"] and b["opaque"]):
            continue
        rows.append(
            (
                int(a["y"] * H),
                int(a["x"] * W),
                int(b["y"] * H),
                int(b["x"] * W),
                LABEL_CODES[d],
                float(w),
            )
        )
    t = torch.tensor(rows, dtype=torch.float64).reshape(-1, 6)
    return {
        "p1": t[:, 0:2].long(),
        "p2": t[:, 2:4].long(),
        "label": t[:, 4].long(),
        "weight": t[:, 5].float(),
    }


class IIWSet(Dataset):
    """Item: im (3, h, w) linear, `comparisons` (see `comparisons_tensor`), id."""

    def __init__(self, root: str | Path, ids: list[str], size: tuple[int, int]):
        if not ids:
            raise ValueError(f"{root}: IIW split is empty")
        self.root, self.ids, self.size = Path(root), list(ids), tuple(size)

    def __len__(self):
        return len(self.ids)

    def __getitem__(self, i):
        image_id = self.ids[i]
        return {
            "im": _to_tensor_image(iiw.read_photo(self.root, image_id), self.size),
            "comparisons": comparisons_tensor(iiw.read_judgements(self.root, image_id), self.size),
            "id": image_id,
        }


class NYUSet(Dataset):
    """Item: im (3, h, w) linear, depth (1, h, w) metres, normal (3, h, w), mask (1, h, w) bool (valid
    normal), index (0-based image number)."""

    def __init__(self, root: str | Path, split: str, size: tuple[int, int]):
        self.root, self.size = Path(root), tuple(size)
        self.mat = self.root / "nyu_depth_v2_labeled.mat"
        self.indices = nyuv2.read_splits(self.root / "splits.mat", nyuv2.count_images(self.mat))[split]
        self.images, self.depths = nyuv2.read_labeled(self.mat, self.indices)

    def __len__(self):
        return len(self.indices)

    def __getitem__(self, i):
        index = int(self.indices[i])
        shape = self.depths[i].shape
        normal, valid = nyuv2.read_normal(self.root / "normals", self.root / "masks", index, shape)
        depth = torch.from_numpy(self.depths[i])[None, None]
        n = torch.from_numpy(normal).permute(2, 0, 1)[None]
        m = torch.from_numpy(valid)[None, None].float()
        return {
            "im": _to_tensor_image(self.images[i], self.size),
            "depth": F.interpolate(depth, size=self.size, mode="nearest")[0],
            "normal": F.normalize(F.interpolate(n, size=self.size, mode="nearest")[0], dim=0, eps=1e-6),
            "mask": F.interpolate(m, size=self.size, mode="nearest")[0] > 0.5,
            "index": index,
        }


def collate_iiw(items: list[dict]) -> dict:
    return {
        "im": torch.stack([it["im"] for it in items]),
        "comparisons": [it["comparisons"] for it in items],
        "id": [it["id"] for it in items],
    }


def collate_nyu(items: list[dict]) -> dict:
    out = {k: torch.stack([it[k] for it in items]) for k in ("im", "depth", "normal", "mask")}
    out["index"] = [it["index"] for it in items]
    return out
