"""Figures of a trained LightNet on fixed test views: re-render vs input, predicted vs ground-truth probes.

Both are written as PNG under the stage's report folder and logged to MLflow by the stage. Renders use
the system's evaluation layer and generator (`render.seed`) and fixed probe picks, so runs compare figure
to figure. This module runs inference and hands arrays to `tracking.figures`, which only draws.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from pipeline.data.lighting import ProbeRays, probe_rays
from pipeline.metrics.image import psnr_tonemapped
from pipeline.ops.camera import grid_pixels, pixel_values
from pipeline.systems.lighting import LightingSystem
from pipeline.systems.lighting_baselines import Constants, scaled_constant_light
from pipeline.tracking.figures import envmap_comparison, rerender_comparison


def scatter_grid(values: torch.Tensor, pixels: torch.Tensor, shape: tuple, stride: int) -> np.ndarray:
    """Place values (M, 3) of flat pixel indices (M,) (into B*H*W, all on the stride grid) into
    (B, ceil(H / stride), ceil(W / stride), 3) images; NaN where no pixel was given."""
    B, H, W = shape
    h, w = -(-H // stride), -(-W // stride)
    out = torch.full((B, h, w, 3), float("nan"))
    b, rc = pixels // (H * W), pixels % (H * W)
    out[b, (rc // W) // stride, (rc % W) // stride] = values.detach().float().cpu()
    return out.numpy()


@torch.no_grad()
def rerender_views(system: LightingSystem, batch: dict, constants: Constants, stride: int = 2) -> list[dict]:
    """Re-render every valid pixel of the views' stride grid with LightNet and with the constant light at
    the photo's exposure (the `scaled_constant` baseline); same directions."""
    fov = system.fov(batch)
    gb = system.gbuffers(batch)
    ctx = system.net.encode(batch["im"], gb["depth"], fov, normal=gb["normal"])
    scale = ctx["scale"]
    pix = grid_pixels(batch["mask"][:, 0], stride)
    layer, gen = system.eval_layer, system.eval_generator()
    model, b = layer.render_pixels(gb, fov, pix, system.light_fn(ctx, gb, fov, gen), gen)
    const, _ = layer.render_pixels(gb, fov, pix, scaled_constant_light(constants, scale), system.eval_generator())
    target = pixel_values(batch["im"], pix)
    B, _, H, W = batch["im"].shape
    images = {k: scatter_grid(v, pix, (B, H, W), stride) for k, v in (("model", model), ("constant", const))}
    views = []
    for v in range(B):
        sel = b == v
        psnr = {
            k: float(psnr_tonemapped(x[sel], target[sel], scale[b[sel]]))
            for k, x in (("model", model), ("constant", const))
        }
        inp = batch["im"][v, :, ::stride, ::stride].permute(1, 2, 0).float().cpu().numpy()
        views.append(
            {
                "id": batch["id"][v],
                "input": inp,
                "model": images["model"][v],
                "constant": images["constant"][v],
                "scale": float(scale[v]),
                "psnr": psnr,
            }
        )
    return views


def render_samples(layer) -> str:
    """How many directions a render layer takes per pixel, in words (li2020 ignores spp)."""
    if layer.estimator == "li2020":
        return f"the li2020 {layer.li_size[0]}x{layer.li_size[1]} grid"
    return f"{layer.spp} spp ({layer.estimator}{', adaptive' if layer.adaptive else ''})"


def spread_indices(n: int, k: int) -> list[int]:
    """k indices spread evenly over range(n) (fewer if n < k)."""
    return sorted({int(i) for i in np.linspace(0, n - 1, min(k, n)).round()}) if n else []


@torch.no_grad()
def probe_envmaps(system: LightingSystem, batch: dict, surface: int = 2, free: int = 1) -> list[dict]:
    """For each view: `surface` surface probes and `free` free points (evenly spread over the view's
    probe lists), each with its ground-truth map and LightNet's prediction at the same texel directions."""
    fov = system.fov(batch)
    gb = system.gbuffers(batch)
    ctx = system.net.encode(batch["im"], gb["depth"], fov, normal=gb["normal"])
    rows = []
    for v, light in enumerate(batch["light"]):
        inp = batch["im"][v].permute(1, 2, 0).float().cpu().numpy()
        for kind, k in (("surf", surface), ("free", free)):
            probes = light.kind(kind)
            rays = probe_rays([light], kind)  # every texel of every probe, texel-averaged directions
            R, C = probes.radiance.shape[1:3]
            for i in spread_indices(len(probes), k):
                sel = slice(i * R * C, (i + 1) * R * C)
                one = ProbeRays(
                    rays.origin[sel], rays.direction[sel], rays.radiance[sel], rays.image[sel] + v, rays.pixel[sel]
                )
                pred = system.query(ctx, gb, fov, one.to(system.device), system.eval_generator())["radiance"]
                pixel = None if probes.pixel is None else tuple(int(x) for x in probes.pixel[i])
                label = f"{batch['id'][v]}\n{'surface' if kind == 'surf' else 'free point'} {i}"
                rows.append(
                    {
                        "label": label,
                        "input": inp,
                        "pixel": pixel,
                        "gt": probes.radiance[i].numpy().astype(np.float32),
                        "pred": pred.reshape(R, C, 3).cpu().numpy(),
                    }
                )
    return rows


def lighting_figures(system: LightingSystem, batch: dict, constants: Constants, report: Path) -> list[Path]:
    """rerender.png and envmaps.png for the views of `batch` under `report`; returns their paths."""
    system.eval()
    return [
        rerender_comparison(
            rerender_views(system, batch, constants),
            report / "rerender.png",
            title=f"test views, re-render with {render_samples(system.eval_layer)} (every 2nd pixel)",
        ),
        envmap_comparison(
            probe_envmaps(system, batch), report / "envmaps.png", title="incident radiance at test probes (lat-long)"
        ),
    ]
