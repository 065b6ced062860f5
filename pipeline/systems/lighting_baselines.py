"""Content-blind baselines and oracle references for LightNet, scored by `LightingSystem.test_step` on the
same views, probe texels, pixels and sample directions as the model.

- `constant`: the mean incident radiance of the training probes, everywhere.
- `scaled_constant`: the training probes' mean in units of their image's mean, times the test image's
  mean: the constant light at the photo's exposure (what a network ignoring the content still gets right).
- `gt_probes`: the ground-truth G-buffers re-rendered under the ground-truth surface probes (bilinear
  between texel centres) at the probe pixels, beside the model at the same pixels. Not an upper bound
  here: the probes are coarse (8x16 texels, solid-angle averages read bilinearly), see README.
- `probe_mean_oracle` / `probe_median_oracle`: each probe's own ground-truth mean / median radiance over
  its texels, predicted for every texel. They know all but where in the probe the light comes from; a
  model at the light loss's fixed point (the conditional mean) that cannot place sources within a probe
  scores about like the mean oracle, and the gap to the median shows how much relMSE and log-L1 reward a
  low prediction rather than the light's energy.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.data.lighting import ViewLighting, probe_rays
from pipeline.metrics.image import psnr_tonemapped
from pipeline.metrics.lighting import light_errors
from pipeline.models.light_net.branches import image_scale
from pipeline.ops.camera import grid_pixels, pixel_values
from pipeline.ops.envmap import hemisphere_lookup


@dataclass
class Constants:
    """constant (3,): mean training radiance; ratio (3,): mean training radiance in image means."""

    constant: torch.Tensor
    ratio: torch.Tensor

    def to(self, device) -> Constants:
        return Constants(self.constant.to(device), self.ratio.to(device))


def mean_training_radiance(loader) -> Constants:
    """Both constants over every probe texel of the training split (a loader of collated batches)."""
    total, ratio, n = torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), 0
    for batch in loader:
        scale = image_scale(batch["im"]).double()
        for b, light in enumerate(batch.get("light", [])):
            for kind in ViewLighting.KINDS:
                r = light.kind(kind).radiance.double().reshape(-1, 3)
                total += r.sum(0)
                ratio += r.sum(0) / scale[b]
                n += len(r)
    if n == 0:
        raise ValueError("the training split has no lighting ground truth (run synthesize with lighting)")
    return Constants((total / n).float(), (ratio / n).float())


def probe_oracle_light(lights: list[ViewLighting], kind: str, scale: torch.Tensor) -> dict[str, tuple] | None:
    """{"probe_mean_oracle" | "probe_median_oracle": (pred (M, 3), target (M, 3), scale (M,))} over the
    batch's probes of `kind` (texels in `probe_rays` order), scale (B,) the image means; None if none."""
    preds, targets, scales = {"probe_mean_oracle": [], "probe_median_oracle": []}, [], []
    for b, light in enumerate(lights):
        r = light.kind(kind).texels()[1]  # (P, T, 3)
        if not len(r):
            continue
        preds["probe_mean_oracle"].append(r.mean(1, keepdim=True).expand_as(r).reshape(-1, 3))
        preds["probe_median_oracle"].append(r.median(1, keepdim=True).values.expand_as(r).reshape(-1, 3))
        targets.append(r.reshape(-1, 3))
        scales.append(scale[b].expand(len(targets[-1])))
    if not targets:
        return None
    target, s = torch.cat(targets), torch.cat(scales)
    return {name: (torch.cat(p), target, s) for name, p in preds.items()}


@torch.no_grad()
def baseline_metrics(batch: dict, constants: Constants, system) -> dict[str, float]:
    """Every baseline's light errors and re-render PSNR on one batch, keyed `<baseline>/<metric>`; the
    renders use the system's evaluation layer and generator seed, so each draws the model's directions."""
    fov = system.fov(batch)
    scale = image_scale(batch["im"])
    constants = constants.to(scale.device)  # the test step runs where Lightning put the batch
    out = {}
    for kind in ViewLighting.KINDS:
        rays = probe_rays(batch["light"], kind)
        if rays is None:
            continue
        s = scale[rays.image]
        cases = {
            "constant": (constants.constant.expand_as(rays.radiance), rays.radiance, s),
            "scaled_constant": (constants.ratio * s[:, None], rays.radiance, s),
            **probe_oracle_light(batch["light"], kind, scale),
        }
        for name, (pred, target, sc) in cases.items():
            out.update({f"{name}/{kind}_{k}": v for k, v in light_errors(pred, target, sc).items()})
    B, _, H, W = batch["im"].shape
    layer = system.eval_layer

    def psnr(gbuf, pixels, radiance) -> float:
        rgb, b = layer.render_pixels(gbuf, fov, pixels, radiance, system.eval_generator())
        return float(psnr_tonemapped(rgb, pixel_values(batch["im"], pixels), scale[b]))

    pix = grid_pixels(batch["mask"][:, 0], system.eval_stride)
    model_gb = system.gbuffers(batch)  # what the model sees (predicted or ground truth, per config)
    c, ratio = constants.constant, constants.ratio
    out["constant/render_psnr"] = psnr(model_gb, pix, lambda idx, o, wi, b: c.expand(len(wi), 3))
    out["scaled_constant/render_psnr"] = psnr(model_gb, pix, lambda idx, o, wi, b: ratio * scale[b, None])
    surf = [light.surf for light in batch["light"]]
    probe_pix = torch.cat([bi * H * W + p.pixel[:, 0] * W + p.pixel[:, 1] for bi, p in enumerate(surf)])
    normals = torch.cat([p.normal for p in surf])
    rads = torch.cat([p.radiance for p in surf])
    keep = batch["mask"][:, 0].reshape(-1)[probe_pix]
    probe_pix, normals, rads = probe_pix[keep], normals[keep], rads[keep]
    gt = {k: batch[k] for k in ("albedo", "normal", "material")}
    gt["depth"] = torch.where(batch["mask"][:, 0], batch["depth"][:, 0], torch.zeros_like(batch["depth"][:, 0]))
    out["gt_probes/render_psnr_at_probes"] = psnr(
        gt, probe_pix, lambda idx, o, wi, b: hemisphere_lookup(rads, idx, normals[idx], wi)
    )
    ctx = system.net.encode(batch["im"], model_gb["depth"], fov)
    gen = system.eval_generator()
    rgb, b = layer.render_pixels(model_gb, fov, probe_pix, system.light_fn(ctx, model_gb, fov, gen), gen)
    out["model/render_psnr_at_probes"] = float(psnr_tonemapped(rgb, pixel_values(batch["im"], probe_pix), scale[b]))
    return out
