"""The `preprocess` stage's work: validate an InteriorVerse-layout root, resize, write shards + manifest.

Resizing only ever shrinks (an area filter; upsampling would invent detail) and is mask-aware:
  im                      plain area average over all pixels (HDR, never clipped)
  albedo, material, depth mask-weighted area average over valid source pixels
  normal                  mask-weighted average, renormalised to unit length
  mask                    valid only where *every* source pixel under the target pixel was valid, so
                          no target pixel mixes a surface with sky, a lamp or another object's edge
Depth is converted to metres (0 where invalid). Views that fail validation are listed with the file
and reason in the returned `rejected` list; nothing is dropped silently.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from pipeline.data import interiorverse as iv

SHARD_KEYS = ("im", "albedo", "normal", "depth", "material", "mask", "fov_x_deg")


@dataclass
class PreprocessResult:
    manifest: dict
    rejected: list[dict]
    seconds: float


def _area(x: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W, C) -> (h, w, C) area average (adaptive average pooling), float64."""
    t = torch.from_numpy(np.ascontiguousarray(x, np.float64)).permute(2, 0, 1)[None]
    return F.adaptive_avg_pool2d(t, size)[0].permute(1, 2, 0).numpy()


def resize_view(maps: dict[str, np.ndarray], height: int, width: int) -> dict[str, np.ndarray]:
    """Resize validated maps (H, W, C) to (height, width); returns channel-first float32 arrays
    (C, h, w) with depth in metres and mask in {0, 1}. Raises ValueError when asked to upsample."""
    H, W = maps["im"].shape[:2]
    if height > H or width > W:
        raise ValueError(f"preprocess.height/width={height}x{width} exceeds the source {H}x{W}; refusing to upsample")
    size = (height, width)
    valid = maps["mask"][..., :1] > 0.5
    depth_m = np.where(valid, maps["depth"], 0.0) / 1000.0
    cover = _area(valid.astype(np.float64), size)
    full = cover >= 1.0 - 1e-9
    w = np.maximum(cover, 1e-12)

    def masked(x):
        return _area(np.where(valid, x, 0.0), size) / w

    normal = masked(maps["normal"])
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    out = {
        "im": _area(maps["im"], size),
        "albedo": masked(maps["albedo"]),
        "normal": normal,
        "depth": masked(depth_m),
        "material": masked(maps["material"]),
        "mask": full.astype(np.float64),
    }
    for k in ("albedo", "normal", "depth", "material"):
        out[k] = np.where(full, out[k], 0.0)
    return {k: np.ascontiguousarray(v.transpose(2, 0, 1), np.float32) for k, v in out.items()}


def rescale_light(light: dict, src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> dict:
    """Lighting ground truth is resolution-free (metres, directions) except the probes' pixel indices."""
    out = dict(light)
    scale = np.array(dst_hw, float) / np.array(src_hw, float)
    out["surf_pixel"] = np.floor((light["surf_pixel"] + 0.5) * scale).astype(np.int32)
    return out


def _fov(root: Path, scene: str, view: str, cameras: dict | None, default: float | None) -> float:
    if cameras is not None:
        path = root / scene / "cameras.json"
        if view not in cameras or "fov_x_deg" not in cameras[view]:
            raise iv.DatasetError(f"{path}: no fov_x_deg for view {view!r}")
        fov = cameras[view]["fov_x_deg"]
        if isinstance(fov, bool) or not isinstance(fov, int | float) or not 0.0 < fov < 180.0:
            raise iv.DatasetError(f"{path}: view {view!r} has fov_x_deg={fov!r}, expected degrees in (0, 180)")
        return float(fov)
    if default is None:
        raise iv.DatasetError(f"{root / scene}: no cameras.json; set data.interiorverse.fov_x_deg for this dataset")
    return float(default)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _write_shard(path: Path, views: list[dict]) -> dict:
    arrays = {k: np.stack([v[k] for v in views]) for k in SHARD_KEYS}
    arrays["mask"] = arrays["mask"].astype(np.uint8)
    lights = [v.get("light") for v in views]
    if all(light is not None for light in lights):
        for key in iv.LIGHT_KEYS:
            arrays[f"light_{key}"] = np.concatenate([light[key] for light in lights])
        for prefix in ("surf", "free"):
            counts = [len(light[f"{prefix}_position"]) for light in lights]
            arrays[f"light_{prefix}_offsets"] = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    np.savez(path, **arrays)
    return {
        "file": path.name,
        "count": len(views),
        "sha256": _sha256(path),
        "lighting": all(light is not None for light in lights),
    }


def preprocess(
    root: str | Path,
    out: str | Path,
    height: int,
    width: int,
    shard_size: int = 64,
    max_inconsistent_fraction: float = 0.01,
    default_fov_x_deg: float | None = None,
    progress: bool = True,
    source: str = "unspecified",
    required: tuple[str, ...] = iv.SPLITS,
) -> PreprocessResult:
    """Validate every view listed by the split files of `root`, resize to (height, width) and write
    `<out>/<split>_<k>.npz` shards and `<out>/manifest.json` (which records `source`, the data's
    provenance: synthetic or a real dataset). Returns the manifest and rejections. Every split in
    `required` must keep a valid view; another may be empty only when its split file lists no scene (a
    test-only set), and a split whose listed views were all rejected is always an error."""
    t0 = time.perf_counter()
    root, out = Path(root), Path(out)
    if not root.is_dir():
        raise iv.DatasetError(f"{root}: dataset root does not exist (data.interiorverse.root)")
    if shard_size < 1:
        raise ValueError(f"preprocess.shard_size={shard_size}: must be >= 1")
    splits = iv.read_splits(root, optional=tuple(s for s in iv.SPLITS if s not in required))
    out.mkdir(parents=True, exist_ok=True)
    for stale in out.glob("*.npz"):
        stale.unlink()
    rejected: list[dict] = []
    manifest: dict = {
        "source": source,
        "source_root": str(root.resolve()),
        "height": height,
        "width": width,
        "depth_unit": "m",
        "layout": "channels-first (N, C, H, W)",
        "splits": {},
    }
    jobs = iv.split_views(root, splits)
    bar = tqdm(jobs, desc="preprocess", unit="view", disable=not progress)
    done: dict[str, list[dict]] = {s: [] for s in iv.SPLITS}
    cameras_cache: dict[str, dict | None] = {}
    fixed = 0
    for split, scene, view in bar:
        if scene not in cameras_cache:
            cameras_cache[scene] = iv.read_cameras(root, scene)
        check = iv.read_view(root, scene, view, max_inconsistent_fraction)
        if not check.ok:
            rejected.extend(check.rejections(split))
            continue
        maps = resize_view(check.maps, height, width)
        maps["fov_x_deg"] = np.float32(_fov(root, scene, view, cameras_cache[scene], default_fov_x_deg))
        src_hw = check.maps["im"].shape[:2]
        maps["light"] = rescale_light(check.light, src_hw, (height, width)) if check.light else None
        maps["id"] = f"{scene}/{view}"
        fixed += check.fixed_pixels
        done[split].append(maps)
    for split in iv.SPLITS:
        views = done[split]
        if not views and split not in required and not splits[split]:
            continue  # listed empty, allowed: the manifest has no such split (`ShardDataset` names it)
        if not views:
            raise iv.DatasetError(
                f"{root / (split + '.txt')}: no valid view left in split {split!r} "
                f"({sum(r['split'] == split for r in rejected)} rejected)"
            )
        shards = [
            _write_shard(out / f"{split}_{k:03d}.npz", views[s : s + shard_size])
            for k, s in enumerate(range(0, len(views), shard_size))
        ]
        manifest["splits"][split] = {
            "views": [v["id"] for v in views],
            "shards": shards,
            "scenes": sorted({v["id"].split("/")[0] for v in views}),
        }
    manifest["lighting"] = all(s["lighting"] for sp in manifest["splits"].values() for s in sp["shards"])
    manifest["rejected_views"] = len({(r["scene"], r["view"]) for r in rejected})
    manifest["fixed_pixels"] = fixed
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return PreprocessResult(manifest, rejected, time.perf_counter() - t0)
