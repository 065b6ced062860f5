"""Contact sheet of generated (or any InteriorVerse-layout) views: image and every map side by side."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from pipeline.data import interiorverse as iv
from pipeline.data.formats.photo import tonemap


def _light_panel(light: dict | None) -> tuple[np.ndarray | None, np.ndarray | None]:
    if not light or not len(light["surf_radiance"]):
        return None, None
    hemi = tonemap(light["surf_radiance"][len(light["surf_radiance"]) // 2])
    sphere = tonemap(light["free_radiance"][0]) if len(light["free_radiance"]) else None
    return hemi, sphere


def contact_sheet(root: str | Path, views: list[tuple[str, str]], path: str | Path) -> Path:
    """Write a PNG with one row per (scene, view): image, albedo, normal, depth, roughness, metallic, mask,
    a surface-probe hemisphere and a free-point sphere (lighting ground truth) when present."""
    cols = [
        "image (tonemapped)",
        "albedo",
        "normal",
        "depth (m)",
        "roughness",
        "metallic",
        "mask",
        "surface probe L_i",
        "free point L_i",
    ]
    fig = Figure(figsize=(2.0 * len(cols), 1.75 * len(views) + 0.4))
    axes = fig.subplots(len(views), len(cols), squeeze=False)
    for r, (scene, view) in enumerate(views):
        check = iv.read_view(root, scene, view)
        if not check.ok:
            raise iv.DatasetError(f"{root}/{scene}/{view}: cannot show an invalid view: {check.reasons}")
        m = check.maps
        depth = np.where(m["mask"][..., 0] > 0, m["depth"][..., 0] / 1000.0, np.nan)
        hemi, sphere = _light_panel(check.light)
        panels = [
            tonemap(m["im"]),
            np.clip(m["albedo"], 0, 1) ** (1 / 2.2),
            (m["normal"] + 1) / 2,
            depth,
            m["material"][..., 0],
            m["material"][..., 1],
            m["mask"][..., 0],
            hemi,
            sphere,
        ]
        for c, img in enumerate(panels):
            ax = axes[r, c]
            ax.set_xticks([])
            ax.set_yticks([])
            if img is None:
                ax.set_axis_off()
                continue
            if img.ndim == 2:
                cmap = "viridis" if c == 3 else "gray"
                vmax = None if c == 3 else 1.0
                ax.imshow(img, cmap=cmap, vmin=0 if c != 3 else None, vmax=vmax, interpolation="nearest")
            else:
                ax.imshow(np.clip(img, 0, 1), interpolation="nearest")
            if r == 0:
                ax.set_title(cols[c], fontsize=7)
        axes[r, 0].set_ylabel(f"{scene}\nview {view}", fontsize=7)
    fig.tight_layout(pad=0.3)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path
