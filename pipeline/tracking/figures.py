"""Figures people look at: predicted vs ground-truth maps, written as PNG (and logged to MLflow by callers)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from pipeline.data.synth.figures import tonemap  # noqa: E402


def save(fig, path: str | Path, title: str = "") -> Path:
    """Title, tight layout, write the PNG (creating its folder), close the figure."""
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _display(key: str, x: torch.Tensor, mask: torch.Tensor | None = None, depth_max: float | None = None):
    """(C, H, W) map -> (H, W, 3) or (H, W) array in [0, 1] for display."""
    x = x.detach().float().cpu()
    if key == "im":
        img = tonemap(x.permute(1, 2, 0).numpy())
    elif key == "albedo":
        img = x.clamp(0, 1).permute(1, 2, 0).numpy() ** (1 / 2.2)
    elif key == "normal":
        img = (x * 0.5 + 0.5).clamp(0, 1).permute(1, 2, 0).numpy()
    elif key in ("roughness", "metallic"):
        img = x[0].clamp(0, 1).numpy()
    else:  # depth
        d = x[0].numpy()
        img = np.clip(d / (depth_max or max(float(d.max()), 1e-6)), 0, 1)
    if mask is not None:
        m = mask[0].cpu().numpy()
        img = img * (m[..., None] if img.ndim == 3 else m)
    return img


def map_comparison(pred: dict, batch: dict, path: str | Path, title: str = "") -> Path:
    """Grid: one row pair per view (ground truth above, prediction below); columns input, albedo, normal,
    roughness, metallic, depth. Predicted depth is shown after its least-squares scale to the ground truth."""
    from pipeline.metrics.synthetic import depth_mask, ls_scale

    n = batch["im"].shape[0]
    cols = ("im", "albedo", "normal", "roughness", "metallic", "depth")
    m = depth_mask(batch["depth"], batch["mask"])
    gt_depth = torch.where(m, batch["depth"], torch.zeros_like(batch["depth"]))
    depth = ls_scale(pred["depth"].double(), gt_depth.double(), m).float() * pred["depth"]
    maps = {
        "gt": {"im": batch["im"], "albedo": batch["albedo"], "normal": batch["normal"], "depth": gt_depth},
        "pred": {"im": batch["im"], "albedo": pred["albedo"], "normal": pred["normal"], "depth": depth},
    }
    for src, mat in (("gt", batch["material"]), ("pred", pred["material"])):
        maps[src]["roughness"], maps[src]["metallic"] = mat[:, :1], mat[:, 1:]
    fig, axes = plt.subplots(2 * n, len(cols), figsize=(1.9 * len(cols), 1.5 * 2 * n), squeeze=False)
    for v in range(n):
        dmax = float(gt_depth[v].max())
        for r, src in enumerate(("gt", "pred")):
            for c, key in enumerate(cols):
                ax = axes[2 * v + r, c]
                img = _display(key, maps[src][key][v], batch["mask"][v] if key != "im" else None, dmax)
                ax.imshow(img, cmap=None if img.ndim == 3 else "viridis", vmin=0, vmax=1)
                ax.set_xticks([]), ax.set_yticks([])
                if v == 0 and r == 0:
                    ax.set_title(key, fontsize=8)
                if c == 0:
                    ax.set_ylabel(f"{src}\n{batch['id'][v]}", fontsize=6)
    return save(fig, path, title)


def prediction_sheet(im: np.ndarray, maps: dict[str, np.ndarray], path: str | Path, title: str = "") -> Path:
    """One row: input (tonemapped), albedo, normal, roughness, metallic, depth of `invrender predict`
    (maps as written: (H, W, C) arrays, depth (H, W) in mm)."""
    panels = [
        ("input", tonemap(im)),
        ("albedo", np.clip(maps["albedo"], 0, 1) ** (1 / 2.2)),
        ("normal", np.clip(maps["normal"] * 0.5 + 0.5, 0, 1)),
        ("roughness", maps["material"][..., 0]),
        ("metallic", maps["material"][..., 1]),
        ("depth (m)", maps["depth"] / 1000.0),
    ]
    fig, axes = plt.subplots(1, len(panels), figsize=(2.2 * len(panels), 2.2))
    for ax, (name, img) in zip(axes, panels, strict=True):
        shown = ax.imshow(img, cmap=None if img.ndim == 3 else "viridis")
        if name == "depth (m)":
            fig.colorbar(shown, ax=ax, fraction=0.046)
        ax.set_title(name, fontsize=8)
        ax.set_xticks([]), ax.set_yticks([])
    return save(fig, path, title)


def ranked_cases(net, meta, nyu_root, rows: list[dict], key: str, path: str | Path, k: int = 3) -> Path:
    """Best and worst `k` NYUv2-layout test images by rows[key] (lower is better): input, ground-truth and
    predicted normals, ground-truth and predicted depth (the latter median-scaled)."""
    from pipeline.data import iiw, nyuv2
    from pipeline.systems.material_predict import predict_maps

    nyu_root = Path(nyu_root)
    ranked = sorted((r for r in rows if np.isfinite(r[key])), key=lambda r: r[key])
    picks = [("best", r) for r in ranked[:k]] + [("worst", r) for r in ranked[::-1][:k]]
    fig, axes = plt.subplots(len(picks), 5, figsize=(10, 2.0 * max(len(picks), 1)), squeeze=False)
    for row_axes, (tag, r) in zip(axes, picks, strict=True):
        images, depths = nyuv2.read_labeled(nyu_root / "nyu_depth_v2_labeled.mat", [r["index"]])
        gt_n, valid = nyuv2.read_normal(nyu_root / "normals", nyu_root / "masks", r["index"], depths[0].shape)
        maps = predict_maps(net, meta, iiw.srgb_to_linear(images[0] / 255.0).astype(np.float32))
        d = maps["depth"] / 1000.0
        d = d * np.median(depths[0]) / max(float(np.median(d)), 1e-9)
        vmax = float(np.percentile(depths[0], 99))
        panels = [
            (images[0], None),
            (np.clip(gt_n * 0.5 + 0.5, 0, 1) * valid[..., None], None),
            (np.clip(maps["normal"] * 0.5 + 0.5, 0, 1), None),
            (depths[0], vmax),
            (d, vmax),
        ]
        for c, (ax, (img, vm)) in enumerate(zip(row_axes, panels, strict=True)):
            ax.imshow(img, cmap=None if img.ndim == 3 else "viridis", vmin=0, vmax=vm)
            ax.set_xticks([]), ax.set_yticks([])
            if c == 0:
                ax.set_ylabel(f"{tag} #{r['index']}\n{key}={r[key]:.1f}", fontsize=7)
    for ax, title in zip(
        axes[0], ("input", "normal gt", "normal pred", "depth gt (m)", "depth pred (scaled)"), strict=True
    ):
        ax.set_title(title, fontsize=8)
    return save(fig, path)
