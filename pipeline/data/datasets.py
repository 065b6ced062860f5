"""Map-style dataset over the shards written by `preprocess` (see pipeline/data/preprocess.py)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F
from torch.utils.data import Dataset

from pipeline.data import interiorverse as iv
from pipeline.data.lighting import ViewLighting
from pipeline.data.preprocess import SHARD_KEYS

MAP_KEYS = ("im", "albedo", "normal", "depth", "material", "mask")


def read_manifest(root: str | Path) -> dict:
    path = Path(root) / "manifest.json"
    if not path.is_file():
        raise iv.DatasetError(f"{path}: no shard manifest; run the preprocess stage first")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise iv.DatasetError(f"{path}: not valid JSON ({exc})") from exc


class ShardDataset(Dataset):
    """Views of one split, held in memory. Item: dict of float tensors im/albedo/normal (3,H,W),
    depth (1,H,W) metres (0 = invalid), material (2,H,W) roughness+metallic, mask (1,H,W) bool,
    fov_x_deg scalar, `id` "<scene>/<view>", and `light` (`ViewLighting`) when present."""

    def __init__(self, root: str | Path, split: str, verify: bool = True, lighting: bool = True):
        if split not in iv.SPLITS:
            raise ValueError(f"split={split!r}: choose one of {iv.SPLITS}")
        self.root = Path(root)
        manifest = read_manifest(self.root)
        if split not in manifest["splits"]:
            raise iv.DatasetError(f"{self.root / 'manifest.json'}: has no split {split!r}")
        entry = manifest["splits"][split]
        self.ids: list[str] = list(entry["views"])
        self.height, self.width = manifest["height"], manifest["width"]
        chunks: dict[str, list[np.ndarray]] = {k: [] for k in SHARD_KEYS}
        self.light: list[dict | None] = []
        for shard in entry["shards"]:
            path = self.root / shard["file"]
            if verify and hashlib.sha256(path.read_bytes()).hexdigest() != shard["sha256"]:
                raise iv.DatasetError(f"{path}: checksum differs from manifest.json (stale or corrupt shard)")
            with np.load(path) as z:
                for k in SHARD_KEYS:
                    chunks[k].append(z[k])
                self.light.extend(
                    _split_light(z, shard["count"]) if lighting and shard["lighting"] else [None] * shard["count"]
                )
        self.arrays = {k: np.concatenate(v) for k, v in chunks.items()}
        if len(self.arrays["im"]) != len(self.ids):
            raise iv.DatasetError(
                f"{self.root}: split {split!r} shards hold {len(self.arrays['im'])} views, "
                f"manifest lists {len(self.ids)}"
            )

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, i: int) -> dict:
        item = {k: torch.from_numpy(np.array(self.arrays[k][i])) for k in MAP_KEYS}
        item["mask"] = item["mask"].bool()
        item["fov_x_deg"] = torch.tensor(float(self.arrays["fov_x_deg"][i]))
        item["id"] = self.ids[i]
        if self.light[i] is not None:
            item["light"] = ViewLighting.from_arrays(self.light[i])
        return item


def _split_light(z, count: int) -> list[dict]:
    out = []
    for v in range(count):
        d = {}
        for prefix in ("surf", "free"):
            off = z[f"light_{prefix}_offsets"]
            for key in iv.LIGHT_KEYS:
                if key.startswith(prefix):
                    d[key] = z[f"light_{key}"][off[v] : off[v + 1]]
        out.append(d)
    return out


def collate_views(items: list[dict]) -> dict:
    """Stack the fixed-size maps; keep ids and per-view lighting (variable probe counts) as lists."""
    batch = {k: torch.stack([it[k] for it in items]) for k in (*MAP_KEYS, "fov_x_deg")}
    batch["id"] = [it["id"] for it in items]
    if all("light" in it for it in items):
        batch["light"] = [it["light"] for it in items]
    return batch


def augment_views(batch: dict, generator: torch.Generator, permute: bool = True, min_scale: float = 1.0) -> dict:
    """Per view of a collated batch, augmentations that stay true to the rendering:
    - a left-right mirror with probability 1/2 (the normal's view-space x changes sign);
    - with `permute`, a random permutation of the RGB channels of image and albedo together (RGB rendering
      is per channel, so the permuted image is the same scene under permuted albedo and light colours);
    - with `min_scale` < 1, a random crop of a fraction s ~ U(min_scale, 1) of each side, resized back to
      (H, W): a longer focal length of the same camera, so view-space normals and z-depth keep their
      values; the image is resampled bilinearly, the ground-truth maps by nearest texel (no mixed labels),
      and fov_x_deg becomes 2 atan(s tan(fov / 2)).
    Batches with lighting probes, which would need the same transforms, are returned unchanged."""
    if "light" in batch:
        return batch
    if not 0.0 < min_scale <= 1.0:
        raise ValueError(f"augment min_scale={min_scale}: must be in (0, 1]")
    B, _, H, W = batch["im"].shape
    flip = torch.rand(B, generator=generator) < 0.5
    perms = [torch.randperm(3, generator=generator) if permute else torch.arange(3) for _ in range(B)]
    out = {k: (v.clone() if k in MAP_KEYS else v) for k, v in batch.items()}
    for k in MAP_KEYS:
        out[k][flip] = out[k][flip].flip(-1)
    out["normal"][flip, 0] *= -1
    for i, perm in enumerate(perms):
        out["im"][i] = out["im"][i, perm]
        out["albedo"][i] = out["albedo"][i, perm]
    if min_scale < 1.0:
        out["fov_x_deg"] = out["fov_x_deg"].clone()
        scales = min_scale + (1.0 - min_scale) * torch.rand(B, generator=generator)
        for i in range(B):
            h, w = max(1, round(H * float(scales[i]))), max(1, round(W * float(scales[i])))
            top = int(torch.randint(0, H - h + 1, (1,), generator=generator))
            left = int(torch.randint(0, W - w + 1, (1,), generator=generator))
            for k in MAP_KEYS:
                crop = out[k][i : i + 1, :, top : top + h, left : left + w]
                if k == "im":
                    crop = F.interpolate(crop, size=(H, W), mode="bilinear", align_corners=False)
                else:
                    crop = F.interpolate(crop.float(), size=(H, W), mode="nearest-exact").to(out[k].dtype)
                out[k][i] = crop[0]
            half = torch.deg2rad(out["fov_x_deg"][i].double()) / 2
            out["fov_x_deg"][i] = torch.rad2deg(2 * torch.atan(torch.tan(half) * w / W)).to(out["fov_x_deg"].dtype)
    return out
