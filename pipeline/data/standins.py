"""Format-faithful IIW and NYUv2 stand-ins built from synthetic views (for machines without the real data).

They are written in exactly the published layouts (see `iiw.py`, `nyuv2.py`) so the same loaders,
metrics and stages read them; reports label them `standin-iiw` / `standin-nyuv2`, never IIW or NYUv2.

IIW stand-in: `<id>.png` is the view's HDR image exposed and sRGB-encoded to 8 bits; `<id>.json` holds
points at random valid pixels (points on metallic surfaces are marked non-opaque, as IIW marks glossy or
transparent ones) and comparisons between point pairs judged by simulated annotators: each perceives the
ground-truth albedo ratio (channel means) with log-normal noise and votes darker/equal with IIW's 10 %
threshold; the majority is `darker`, the agreement fraction its `darker_score` weight.
NYUv2 stand-in: the HDF5 `.mat` with images (N, 3, W, H) uint8 and depths (N, W, H) metres (MATLAB axis
order; pixels without a surface are filled with the view's farthest depth, as NYUv2's depths are
filled), `splits.mat` with 1-based train/test indices, and normal/mask PNGs numbered by 0-based index.
"""

from __future__ import annotations

import io
import json
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from pipeline.data import nyuv2
from pipeline.data.formats.photo import linear_to_srgb

IIW_SOURCE, NYU_SOURCE = "standin-iiw", "standin-nyuv2"


def expose_to_srgb8(im: np.ndarray) -> np.ndarray:
    """(H, W, 3) linear HDR -> uint8 sRGB with the 99th percentile at 0.9 (a camera-like auto exposure)."""
    im = np.nan_to_num(np.asarray(im, np.float64), nan=0.0, posinf=0.0).clip(min=0)
    scale = 0.9 / max(float(np.percentile(im, 99)), 1e-6)
    return np.round(linear_to_srgb(im * scale) * 255).astype(np.uint8)


def judge(l1: float, l2: float, rng: np.random.Generator, annotators: int = 5, noise: float = 0.12, delta: float = 0.1):
    """Simulated annotators' verdict on two reflectances: (darker in {"1","2","E"}, agreement in (0, 1])."""
    votes = []
    for _ in range(annotators):
        r = (l2 / l1) * float(np.exp(rng.normal(0.0, noise)))
        votes.append("1" if r > 1 + delta else "2" if 1 / r > 1 + delta else "E")
    labels, counts = np.unique(votes, return_counts=True)
    best = int(np.argmax(counts))
    return str(labels[best]), float(counts[best] / annotators)


def build_iiw(views: Sequence[dict], out: str | Path, seed: int, points: int = 40, comparisons: int = 60) -> list[str]:
    """Write an IIW-layout folder from views (dicts with im, albedo (H,W,3), material (H,W,2), mask (H,W)
    bool, `id`); returns the image ids ("1000", "1001", ...)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    ids = []
    for k, view in enumerate(views):
        image_id = str(1000 + k)
        H, W = view["mask"].shape
        valid = np.flatnonzero(view["mask"].ravel())
        if valid.size < 2:
            raise ValueError(f"view {view.get('id')}: fewer than 2 valid pixels; cannot place IIW points")
        picks = rng.choice(valid, size=min(points, valid.size), replace=False)
        pts = []
        for pid, flat in enumerate(picks):
            row, col = divmod(int(flat), W)
            pts.append(
                {
                    "id": pid,
                    "x": (col + rng.uniform(0.05, 0.95)) / W,  # anywhere in the pixel; truncation finds it
                    "y": (row + rng.uniform(0.05, 0.95)) / H,
                    "opaque": bool(view["material"][row, col, 1] < 0.5),
                    "_albedo": float(view["albedo"][row, col].mean()),
                }
            )
        comps = []
        for cid in range(comparisons):
            a, b = rng.choice(len(pts), size=2, replace=False)
            darker, agreement = judge(max(pts[a]["_albedo"], 1e-4), max(pts[b]["_albedo"], 1e-4), rng)
            comps.append({"id": cid, "point1": int(a), "point2": int(b), "darker": darker, "darker_score": agreement})
        for p in pts:
            del p["_albedo"]
        from PIL import Image

        Image.fromarray(expose_to_srgb8(view["im"])).save(out / f"{image_id}.png")
        (out / f"{image_id}.json").write_text(
            json.dumps({"intrinsic_points": pts, "intrinsic_comparisons": comps, "source_view": view.get("id")})
        )
        ids.append(image_id)
    (out / "SOURCE.txt").write_text(f"{IIW_SOURCE}: built from synthetic views, not the IIW dataset\n")
    return ids


def build_nyuv2(views: Sequence[dict], out: str | Path, test_every: int = 3) -> dict[str, list[int]]:
    """Write a NYUv2-layout folder from views (dicts with im, normal (H,W,3), depth (H,W) metres with 0 or
    inf where there is no surface, mask (H,W) bool). Every `test_every`-th view (1-based positions 1,
    1+k, ...) is a test image. Returns the 0-based split indices."""
    import h5py
    from PIL import Image
    from scipy.io import savemat

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    images, depths = [], []
    for idx, view in enumerate(views):
        d = np.asarray(view["depth"], np.float64)
        ok = np.isfinite(d) & (d > 0)
        if not ok.any():
            raise ValueError(f"view {view.get('id')}: no valid depth; cannot build a NYUv2 stand-in image")
        images.append(expose_to_srgb8(view["im"]))
        depths.append(np.where(ok, d, d[ok].max()).astype(np.float32))
        nyuv2.write_normal_png(out / "normals" / f"{idx:04d}.png", np.asarray(view["normal"]))
        mask = np.repeat((np.asarray(view["mask"], bool) & ok)[..., None] * np.uint8(255), 3, -1)
        (out / "masks").mkdir(exist_ok=True)
        Image.fromarray(mask).save(out / "masks" / f"{idx:04d}.png")
    with h5py.File(out / "nyu_depth_v2_labeled.mat", "w") as f:
        f["images"] = np.ascontiguousarray(np.transpose(np.stack(images), (0, 3, 2, 1)))
        f["depths"] = np.ascontiguousarray(np.transpose(np.stack(depths), (0, 2, 1)))
    n = len(views)
    test = [i for i in range(n) if i % test_every == 0]
    train = [i for i in range(n) if i % test_every != 0]
    mat = io.BytesIO()
    savemat(
        mat,
        {"trainNdxs": np.array(train, np.float64)[:, None] + 1, "testNdxs": np.array(test, np.float64)[:, None] + 1},
    )
    # the MAT header's 116-byte text ends "Created on: <date and time>": a fixed text instead, so the same
    # views give the same bytes (finetune's DVC out, hashed into dvc.lock)
    (out / "splits.mat").write_bytes(MAT_HEADER + mat.getvalue()[len(MAT_HEADER) :])
    (out / "SOURCE.txt").write_text(f"{NYU_SOURCE}: built from synthetic views, not NYU Depth v2\n")
    return {"train": train, "test": test}


MAT_HEADER = b"MATLAB 5.0 MAT-file, written by invrender".ljust(116)  # a MAT-file's descriptive text, fixed

STANDIN_DEFAULTS = {"points": 40, "comparisons": 60, "nyu_test_every": 3}


def synthetic_test_views(data_dir: str | Path) -> list[dict]:
    """The preprocess shards' test views as (H, W, C) arrays (im, albedo, normal, material; depth and
    mask (H, W)), the source of both stand-ins."""
    from pipeline.data.datasets import ShardDataset

    ds = ShardDataset(data_dir, "test", lighting=False)
    views = []
    for i in range(len(ds)):
        it = ds[i]
        view = {k: it[k].permute(1, 2, 0).numpy() for k in ("im", "albedo", "normal", "material")}
        views.append({"id": it["id"], **view, "depth": it["depth"][0].numpy(), "mask": it["mask"][0].numpy()})
    if not views:
        raise ValueError(f"{data_dir}: the synthetic test split is empty; cannot build stand-ins")
    return views


def benchmark_roots(
    iiw_root: str | None,
    nyuv2_root: str | None,
    standin_dir: str | Path,
    data_dir: str | Path,
    seed: int,
    settings: Mapping | None = None,
    build: bool = True,
) -> dict[str, tuple[Path, str]]:
    """{"iiw": (root, source), "nyuv2": (root, source)}: the real roots where given (checked to exist),
    otherwise stand-ins under `standin_dir` built from the synthetic test views with `settings`
    {"points", "comparisons", "nyu_test_every"} (`conf/standin`; missing keys take 40, 60, 3). Stand-ins are reused only
    when `done.json` records the same views, seed and settings; otherwise they are rebuilt, or, with
    build=False (a reader such as `evaluate`, which must not rewrite another stage's output), refused
    with an error saying what differs."""
    out = {}
    standin = Path(standin_dir)
    for key, real, source in (("iiw", iiw_root, IIW_SOURCE), ("nyuv2", nyuv2_root, NYU_SOURCE)):
        if real:
            if not Path(real).is_dir():
                raise FileNotFoundError(f"{key}_root={real}: no such folder")
            out[key] = (Path(real), key)
        else:
            out[key] = (standin / key, source)
    if iiw_root and nyuv2_root:
        return out
    views = synthetic_test_views(data_dir)
    record = {
        "views": [v["id"] for v in views],
        "seed": int(seed),
        **{k: int((settings or {}).get(k, v)) for k, v in STANDIN_DEFAULTS.items()},
    }
    done = standin / "done.json"
    try:
        built = json.loads(done.read_text()) if done.is_file() else None
    except json.JSONDecodeError:
        built = None  # a torn write: rebuild
    if built != record and not build:
        differs = sorted(k for k in record if (built or {}).get(k) != record[k]) if built else ["(none built)"]
        raise ValueError(
            f"{done}: the stand-ins were built with other settings ({', '.join(differs)} differ); "
            "re-run `finetune` with these settings (dvc repro finetune)"
        )
    if built != record:
        for key in ("iiw", "nyuv2"):  # no file of an older build may survive into the new one
            shutil.rmtree(standin / key, ignore_errors=True)
        build_iiw(views, standin / "iiw", int(seed), record["points"], record["comparisons"])
        build_nyuv2(views, standin / "nyuv2", record["nyu_test_every"])
        done.write_text(json.dumps(record))
    return out
