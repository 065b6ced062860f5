"""Figures people look at: predicted vs ground-truth maps, written as PNG (and logged to MLflow by callers)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle
from matplotlib.ticker import FuncFormatter

from pipeline.data.formats.photo import tonemap


def save(fig: Figure, path: str | Path, title: str = "") -> Path:
    """Title, tight layout, write the PNG (creating its folder)."""
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
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
    fig = Figure(figsize=(1.9 * len(cols), 1.5 * 2 * n))
    axes = fig.subplots(2 * n, len(cols), squeeze=False)
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
    fig = Figure(figsize=(2.2 * len(panels), 2.2))
    axes = fig.subplots(1, len(panels))
    for ax, (name, img) in zip(axes, panels, strict=True):
        shown = ax.imshow(img, cmap=None if img.ndim == 3 else "viridis")
        if name == "depth (m)":
            fig.colorbar(shown, ax=ax, fraction=0.046)
        ax.set_title(name, fontsize=8)
        ax.set_xticks([]), ax.set_yticks([])
    return save(fig, path, title)


def ranked_cases(panels: list[dict], path: str | Path) -> Path:
    """One row per case: input photo, ground-truth and predicted normals (in [0, 1] for display),
    ground-truth and predicted depth (m, one colour scale per row up to the ground truth's 99th
    percentile). panels: {"label", "photo", "normal_gt", "normal_pred", "depth_gt", "depth_pred"}."""
    keys = ("photo", "normal_gt", "normal_pred", "depth_gt", "depth_pred")
    titles = ("input", "normal gt", "normal pred", "depth gt (m)", "depth pred (scaled)")
    fig = Figure(figsize=(10, 2.0 * max(len(panels), 1)))
    axes = fig.subplots(len(panels), 5, squeeze=False)
    for row_axes, p in zip(axes, panels, strict=True):
        vmax = float(np.percentile(p["depth_gt"], 99))
        for c, (ax, key) in enumerate(zip(row_axes, keys, strict=True)):
            img = p[key]
            ax.imshow(img, cmap=None if img.ndim == 3 else "viridis", vmin=0, vmax=vmax if img.ndim == 2 else None)
            ax.set_xticks([]), ax.set_yticks([])
            if c == 0:
                ax.set_ylabel(p["label"], fontsize=7)
    for ax, title in zip(axes[0], titles, strict=True):
        ax.set_title(title, fontsize=8)
    return save(fig, path)


def _input_exposure(hdr: np.ndarray) -> float:
    """The exposure `tonemap` would pick for this input (median positive value to 0.3), so the other
    panels of a row can be shown at the input's exposure."""
    x = np.nan_to_num(hdr, nan=0.0)
    return 0.3 / max(float(np.median(x[x > 0])) if (x > 0).any() else 1.0, 1e-6)


def rerender_comparison(views: list[dict], path: str | Path, title: str = "") -> Path:
    """One row per view: the input, LightNet's re-render, the constant light's re-render (at the photo's
    exposure) and |LightNet - input| in units of the image mean. views: {"id", "input", "model",
    "constant": (H, W, 3) HDR arrays (NaN where nothing was rendered), "scale": image mean, "psnr":
    {"model": dB, "constant": dB}}. A row's panels share the input's exposure, so brightness compares."""
    cols = ("input", "LightNet re-render", "constant-light re-render", "|error| / image mean")
    fig = Figure(figsize=(2.4 * len(cols), 1.9 * len(views)))
    axes = fig.subplots(len(views), len(cols), squeeze=False)
    for row, v in zip(axes, views, strict=True):
        exposure = _input_exposure(v["input"])
        err = np.abs(v["model"] - v["input"]).mean(-1) / v["scale"]
        panels = [tonemap(v[k], exposure) for k in ("input", "model", "constant")] + [np.nan_to_num(err, nan=0.0)]
        for c, (ax, img) in enumerate(zip(row, panels, strict=True)):
            ax.imshow(img, cmap=None if img.ndim == 3 else "magma", vmin=0, vmax=1)
            ax.set_xticks([]), ax.set_yticks([])
            if c == 1:
                ax.set_xlabel(f"{v['psnr']['model']:.1f} dB", fontsize=7)
            if c == 2:
                ax.set_xlabel(f"{v['psnr']['constant']:.1f} dB", fontsize=7)
        row[0].set_ylabel(str(v["id"]), fontsize=6)
    for ax, name in zip(axes[0], cols, strict=True):
        ax.set_title(name, fontsize=8)
    return save(fig, path, title)


def envmap_comparison(rows: list[dict], path: str | Path, title: str = "") -> Path:
    """One row per probe: the input (a surface probe's pixel marked), then the ground-truth and the
    predicted incident radiance as lat-long maps (rows: polar angle from the probe's normal, or from +y
    for a free point's sphere; columns: azimuth). rows: {"label", "input" (H, W, 3), "pixel": (row, col)
    or None, "gt", "pred": (R, C, 3) HDR}. A row shares the input's exposure."""
    cols = ("probe", "ground truth", "LightNet")
    fig = Figure(figsize=(2.6 * len(cols), 1.5 * len(rows)))
    axes = fig.subplots(len(rows), len(cols), squeeze=False)
    for row, r in zip(axes, rows, strict=True):
        exposure = _input_exposure(r["input"])
        row[0].imshow(tonemap(r["input"], exposure))
        if r["pixel"] is not None:
            row[0].plot([r["pixel"][1]], [r["pixel"][0]], "o", ms=5, mfc="none", mec="cyan")
        for ax, key in zip(row[1:], ("gt", "pred"), strict=True):
            ax.imshow(tonemap(r[key], exposure), aspect="auto", interpolation="nearest")
        for ax in row:
            ax.set_xticks([]), ax.set_yticks([])
        row[0].set_ylabel(r["label"], fontsize=6)
    for ax, name in zip(axes[0], cols, strict=True):
        ax.set_title(name, fontsize=8)
    return save(fig, path, title)


def _crop_box(pixels: np.ndarray, height: int, width: int, min_side: int = 24) -> tuple[slice, slice]:
    """The window around flat pixels: their bounding box grown by a quarter of its size on each side,
    at least min_side pixels a side, inside the image."""

    def span(lo: int, hi: int, size: int) -> slice:
        extent = hi - lo + 1
        side = min(size, max(min_side, int(round(1.5 * extent))))
        start = int(np.clip((lo + hi + 1) // 2 - side // 2, 0, size - side))
        return slice(start, start + side)

    rows, cols = np.divmod(pixels, width)
    return span(rows.min(), rows.max(), height), span(cols.min(), cols.max(), width)


def insertion_grid(panels: list[dict], path: str | Path, title: str = "") -> Path:
    """One row per case: the input photo (the case's window boxed), then zoomed crops of the ground truth
    and of each row's composite (PSNR on the case's pixels below), and |LightNet - ground truth| in units
    of the photo's mean. panels: {"label", "photo", "gt" (H, W, 3) HDR, "rows": {name: (H, W, 3)},
    "psnr": {name: dB}, "pixels" (M,) flat, "scale": the photo's mean}. A row shares the photo's exposure."""
    names = list(panels[0]["rows"])
    cols = ["input", "ground truth", *names, "|LightNet - truth|"]
    fig = Figure(figsize=(1.55 * len(cols), 1.6 * len(panels)))
    axes = fig.subplots(len(panels), len(cols), squeeze=False)
    for row, p in zip(axes, panels, strict=True):
        H, W = p["photo"].shape[:2]
        exposure = _input_exposure(p["photo"])
        rs, cs = _crop_box(p["pixels"], H, W)
        row[0].imshow(tonemap(p["photo"], exposure))
        row[0].add_patch(
            Rectangle((cs.start - 0.5, rs.start - 0.5), cs.stop - cs.start, rs.stop - rs.start, fill=False, ec="cyan")
        )
        images = [p["gt"], *(p["rows"][n] for n in names)]
        for ax, img in zip(row[1 : 2 + len(names)], images, strict=True):
            ax.imshow(tonemap(img[rs, cs], exposure), interpolation="nearest")
        for ax, n in zip(row[2 : 2 + len(names)], names, strict=True):
            ax.set_xlabel(f"{p['psnr'][n]:.1f} dB", fontsize=6, labelpad=1)
        err = np.abs(p["rows"][names[0]] - p["gt"]).mean(-1) / p["scale"]
        row[-1].imshow(np.clip(err[rs, cs], 0, 1), cmap="magma", vmin=0, vmax=1, interpolation="nearest")
        for ax in row:
            ax.set_xticks([]), ax.set_yticks([])
        row[0].set_ylabel(p["label"], fontsize=5)
    for ax, name in zip(axes[0], cols, strict=True):
        ax.set_title(name.replace("_", " "), fontsize=6)
    return save(fig, path, title)


def pareto_front(xs: list[float], ys: list[float]) -> list[int]:
    """Indices of the points no other point beats on both axes (lower x = faster, higher y = better),
    ordered by x. Non-finite points are never on the front."""
    idx = [i for i in range(len(xs)) if np.isfinite(xs[i]) and np.isfinite(ys[i])]
    front = [
        i for i in idx if not any(xs[j] <= xs[i] and ys[j] >= ys[i] and (xs[j] < xs[i] or ys[j] > ys[i]) for j in idx)
    ]
    return sorted(front, key=lambda i: xs[i])


def _label_points(ax, labelled: list[tuple[str, float, float]], fontsize: float = 7) -> None:
    """Annotate each (label, x, y) beside its dot; a label that would overlap one already placed moves to
    the nearest free text line (down, then up), and one past the axes' right edge goes left of its dot, so
    points close in speed and accuracy stay readable. Positions in display pixels; a thin line joins a
    moved label to its dot."""
    ax.figure.draw_without_rendering()  # fix the limits and scales so data -> pixel transforms are final
    to_points = 72 / ax.figure.dpi
    line = fontsize / to_points * 1.25
    placed: list[tuple[float, float, float]] = []  # (x0, x1, y) pixel extents of placed labels
    for label, x, y in sorted(labelled, key=lambda t: -t[2]):
        px, py = ax.transData.transform((x, y))
        width = 0.6 * fontsize / to_points * len(label)
        right = px + 3 + width <= ax.get_window_extent().x1  # else the label goes left of its dot
        x0, x1 = (px + 3, px + 3 + width) if right else (px - 3 - width, px - 3)
        for shift in (0, -1, 1, -2, 2, -3, 3, -4, 4, -5, 5, -6):  # nearest free line, below first
            ty = py + 3 + shift * line
            if not any(a0 < x1 and x0 < a1 and abs(ty - b) < line for a0, a1, b in placed):
                break
        placed.append((x0, x1, ty))
        moved = ty != py + 3
        ax.annotate(
            label,
            (x, y),
            xytext=(3 if right else -3, (ty - py) * to_points),
            textcoords="offset points",
            ha="left" if right else "right",
            fontsize=fontsize,
            arrowprops={"arrowstyle": "-", "lw": 0.4, "color": "0.5"} if moved else None,
        )


def pareto_figure(points: list[dict], path: str | Path, title: str = "") -> Path:
    """Accuracy against cost, one labelled dot per point ({label, seconds, train_minutes, insertion_psnr,
    render_psnr}, each optionally with `<key>_err`: the seeds' spread, drawn as error bars), the Pareto
    front (of the means) as a line: columns insertion PSNR / re-render PSNR, rows against seconds per
    image / training minutes."""
    fig = Figure(figsize=(12, 9))
    axes = fig.subplots(2, 2)
    labels = []
    for col, (acc, acc_label) in enumerate(
        (("insertion_psnr", "insertion PSNR, all objects (dB)"), ("render_psnr", "test re-render PSNR (dB)"))
    ):
        for row, (cost, cost_label) in enumerate(
            (("seconds", "full-frame re-render, s/image"), ("train_minutes", "training, minutes"))
        ):
            ax = axes[row, col]
            xs = [p[cost] for p in points]
            ys = [p[acc] for p in points]
            shown = [i for i in range(len(points)) if np.isfinite(xs[i]) and np.isfinite(ys[i])]
            ax.scatter([xs[i] for i in shown], [ys[i] for i in shown], s=28, color="tab:blue", zorder=3)
            xerr = [points[i].get(f"{cost}_err", 0.0) for i in shown]
            yerr = [points[i].get(f"{acc}_err", 0.0) for i in shown]
            if any(e > 0 for e in xerr + yerr):  # half the seeds' range, where a point has several seeds
                ax.errorbar(
                    [xs[i] for i in shown],
                    [ys[i] for i in shown],
                    xerr=np.nan_to_num(xerr),
                    yerr=np.nan_to_num(yerr),
                    fmt="none",
                    ecolor="tab:blue",
                    elinewidth=0.8,
                    alpha=0.6,
                    zorder=2,
                )
            positive = [xs[i] for i in shown if xs[i] > 0]
            if len(positive) == len(shown) and positive and max(positive) > 4 * min(positive):
                ax.set_xscale("log")  # one slow setting (no_mc) would squeeze every other point into a column
                plain = FuncFormatter(lambda v, _: f"{v:g}")
                ax.xaxis.set_major_formatter(plain), ax.xaxis.set_minor_formatter(plain)
            front = pareto_front(xs, ys)
            if front:
                ax.plot([xs[i] for i in front], [ys[i] for i in front], color="tab:red", lw=1.2, label="Pareto front")
                ax.legend(fontsize=8, loc="lower right")
            labels.append((ax, [(points[i]["label"], xs[i], ys[i]) for i in shown]))
            ax.set_xlabel(cost_label)
            ax.set_ylabel(acc_label)
            ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()  # final axes sizes before labels are placed in display space
    for ax, labelled in labels:
        _label_points(ax, labelled)
    return save(fig, path, title)


def paired_scatter(
    reference: np.ndarray, model: np.ndarray, groups: list[str], path: str | Path, labels=("", ""), title: str = ""
) -> Path:
    """One dot per case, the reference's score (x) against the model's (y) on the same case, coloured by
    group, with the diagonal: dots above it are cases the model wins. reference/model (N,) scores; groups
    N names; labels the two axes."""
    reference, model = np.asarray(reference, float), np.asarray(model, float)
    fig = Figure(figsize=(5.2, 4.8))
    ax = fig.subplots()
    for i, group in enumerate(sorted(set(groups))):
        sel = np.array([g == group for g in groups])
        won = float(np.mean(model[sel] > reference[sel]))
        ax.scatter(reference[sel], model[sel], s=14, color=f"C{i}", label=f"{group} ({sel.sum()}, wins {won:.0%})")
    finite = np.concatenate([reference, model])
    finite = finite[np.isfinite(finite)]
    if len(finite):
        lo, hi = float(finite.min()), float(finite.max())
        ax.plot([lo, hi], [lo, hi], color="0.4", lw=0.8, ls="--")
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    return save(fig, path, title)
