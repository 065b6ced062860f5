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
- `probe_profile_oracle`: the mean oracle shaped by the training split's mean angular profile: each texel
  gets its probe's true mean times how bright, relative to its probe's mean, training texels of that kind
  were on average at the same elevation (view-space up component of the texel's centre direction, in
  `PROFILE_BINS` equal solid-angle bands). Light energy known, placement only the typical "lamps above,
  floor below": the nMSE a model could reach by getting each probe's energy right without locating its
  sources.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.data.lighting import ViewLighting, probe_rays
from pipeline.metrics.image import psnr_tonemapped
from pipeline.metrics.lighting import light_errors
from pipeline.models.light_net.branches import image_scale
from pipeline.models.render_layer import PointRadianceFn
from pipeline.ops.camera import grid_pixels, pixel_values
from pipeline.ops.envmap import hemisphere_lookup
from pipeline.systems.per_view import split_views

PROFILE_BINS = 8  # elevation bands of the angular profile, equal in solid angle (uniform in the up component)


@dataclass
class Constants:
    """constant (3,): mean training radiance; ratio (3,): mean training radiance in image means;
    profile: {kind: (PROFILE_BINS,)} mean texel radiance relative to its probe's mean, by elevation band."""

    constant: torch.Tensor
    ratio: torch.Tensor
    profile: dict[str, torch.Tensor]

    def to(self, device) -> Constants:
        profile = {k: v.to(device) for k, v in self.profile.items()}
        return Constants(self.constant.to(device), self.ratio.to(device), profile)


def constant_light(constants: Constants) -> PointRadianceFn:
    """The `constant` baseline as an incident-radiance callback: the mean training radiance from every
    direction at every point (reads only how many queries there are)."""

    def radiance(idx, origin, wi, image):
        return constants.constant.expand(len(image), 3)

    return radiance


def scaled_constant_light(constants: Constants, scale: torch.Tensor) -> PointRadianceFn:
    """The `scaled_constant` baseline as an incident-radiance callback: the mean training radiance in
    image means times the mean of the query's image, scale (B,) the views' image means (`image_scale`;
    one view's 0-dim mean serves a single view)."""
    per_image = scale.reshape(-1)

    def radiance(idx, origin, wi, image):
        return constants.ratio * per_image[image, None]

    return radiance


def elevation_band(directions: torch.Tensor) -> torch.Tensor:
    """Band index (...,) in [0, PROFILE_BINS) of unit view-space directions (..., 3) by their up (y)
    component: band 0 looks straight down, the last straight up (OpenGL view space, y up)."""
    y = directions[..., 1].clamp(-1.0, 1.0)
    return ((y + 1.0) * 0.5 * PROFILE_BINS).long().clamp(max=PROFILE_BINS - 1)


def _relative_texels(probes) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(band (N,), radiance over its probe's mean (N,)) for the N texels of one kind's probes, each
    channel divided by that channel's probe mean and then averaged over RGB, so a tinted probe shapes the
    profile as a grey one does. A probe with a black channel has no shape to learn and is left out."""
    d, r = probes.texels()
    mean = r.double().mean(1, keepdim=True)  # (P, 1, 3)
    lit = (mean > 0).all(-1).squeeze(1)  # (P,)
    if not lit.any():
        return None
    rel = (r.double()[lit] / mean[lit]).mean(-1)
    return elevation_band(d[lit]).reshape(-1), rel.reshape(-1)


def mean_training_radiance(loader) -> Constants:
    """Both constants and the angular profiles over every probe texel of the training split (a loader of
    collated batches). A band no training texel fell in gets 1 (the probe's mean)."""
    total, ratio, n = torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), 0
    band_sum = {k: torch.zeros(PROFILE_BINS, dtype=torch.float64) for k in ViewLighting.KINDS}
    band_n = {k: torch.zeros(PROFILE_BINS, dtype=torch.float64) for k in ViewLighting.KINDS}
    for batch in loader:
        scale = image_scale(batch["im"]).double()
        for b, light in enumerate(batch.get("light", [])):
            for kind in ViewLighting.KINDS:
                r = light.kind(kind).radiance.double().reshape(-1, 3)
                total += r.sum(0)
                ratio += r.sum(0) / scale[b]
                n += len(r)
                rel = _relative_texels(light.kind(kind))
                if rel is not None:
                    band_sum[kind].index_add_(0, rel[0], rel[1])
                    band_n[kind].index_add_(0, rel[0], torch.ones_like(rel[1]))
    if n == 0:
        raise ValueError("the training split has no lighting ground truth (run synthesize with lighting)")
    profile = {k: torch.where(band_n[k] > 0, band_sum[k] / band_n[k].clamp(min=1), 1.0).float() for k in band_sum}
    return Constants((total / n).float(), (ratio / n).float(), profile)


def probe_oracle_light(
    lights: list[ViewLighting], kind: str, scale: torch.Tensor, profile: torch.Tensor | None = None
) -> dict[str, tuple] | None:
    """{"probe_mean_oracle" | "probe_median_oracle" [| "probe_profile_oracle"]: (pred (M, 3), target (M, 3),
    scale (M,))} over the batch's probes of `kind` (texels in `probe_rays` order), scale (B,) the image
    means, profile (PROFILE_BINS,) the kind's `Constants.profile` (None: no profile oracle); None if no
    probes. The profile oracle is renormalised per probe, so its mean over the probe's texels is the
    probe's true mean."""
    names = ["probe_mean_oracle", "probe_median_oracle"] + (["probe_profile_oracle"] if profile is not None else [])
    preds, targets, scales = {name: [] for name in names}, [], []
    for b, light in enumerate(lights):
        d, r = light.kind(kind).texels()  # (P, T, 3) each
        if not len(r):
            continue
        mean = r.mean(1, keepdim=True)
        preds["probe_mean_oracle"].append(mean.expand_as(r).reshape(-1, 3))
        preds["probe_median_oracle"].append(r.median(1, keepdim=True).values.expand_as(r).reshape(-1, 3))
        if profile is not None:
            w = profile.to(r)[elevation_band(d)]  # (P, T)
            # a hemisphere sees only some bands (a floor's only the upper ones), so the profile's mean over
            # its texels is not 1: rescale, so the probe keeps its true mean and only the shape is the prior
            w = w / w.mean(1, keepdim=True).clamp(min=1e-12)
            preds["probe_profile_oracle"].append((mean * w[..., None]).reshape(-1, 3))
        targets.append(r.reshape(-1, 3))
        scales.append(scale[b].expand(len(targets[-1])))
    if not targets:
        return None
    target, s = torch.cat(targets), torch.cat(scales)
    return {name: (torch.cat(p), target, s) for name, p in preds.items()}


@torch.no_grad()
def baseline_metrics(batch: dict, constants: Constants, system, views: list[dict] | None = None) -> dict[str, float]:
    """Every baseline's light errors and re-render PSNR on one batch, keyed `<baseline>/<metric>`; the
    renders use the system's evaluation layer and generator seed, so each draws the model's directions.
    views (one dict per view of the batch): also each view's own values, the same keys
    (`per_view.split_views`)."""
    fov = system.fov(batch)
    scale = image_scale(batch["im"])
    constants = constants.to(scale.device)  # the test step runs where Lightning put the batch
    constant, scaled_constant = constant_light(constants), scaled_constant_light(constants, scale)
    out = {}
    for kind in ViewLighting.KINDS:
        rays = probe_rays(batch["light"], kind)
        if rays is None:
            continue
        s = scale[rays.image]
        cases = {  # the constant lights ignore direction: one query per texel reads its value
            "constant": (constant(None, rays.origin, None, rays.image), rays.radiance, s),
            "scaled_constant": (scaled_constant(None, rays.origin, None, rays.image), rays.radiance, s),
            **probe_oracle_light(batch["light"], kind, scale, constants.profile.get(kind)),
        }
        for name, (pred, target, sc) in cases.items():
            out.update({f"{name}/{kind}_{k}": v for k, v in light_errors(pred, target, sc).items()})
            split_views(views, rays.image, light_errors, pred, target, sc, prefix=f"{name}/{kind}_")
    B, _, H, W = batch["im"].shape
    layer = system.eval_layer

    def psnr(key, gbuf, pixels, radiance) -> None:
        rgb, b = layer.render_pixels(gbuf, fov, pixels, radiance, system.eval_generator())
        target = pixel_values(batch["im"], pixels)
        out[key] = float(psnr_tonemapped(rgb, target, scale[b]))
        split_views(views, b, lambda r, t, sc: {key: psnr_tonemapped(r, t, sc)}, rgb, target, scale[b])

    pix = grid_pixels(batch["mask"][:, 0], system.eval_stride)
    model_gb = system.gbuffers(batch)  # what the model sees (predicted or ground truth, per config)
    psnr("constant/render_psnr", model_gb, pix, constant)
    psnr("scaled_constant/render_psnr", model_gb, pix, scaled_constant)
    surf = [light.surf for light in batch["light"]]
    probe_pix = torch.cat([bi * H * W + p.pixel[:, 0] * W + p.pixel[:, 1] for bi, p in enumerate(surf)])
    normals = torch.cat([p.normal for p in surf])
    rads = torch.cat([p.radiance for p in surf])
    keep = batch["mask"][:, 0].reshape(-1)[probe_pix]
    probe_pix, normals, rads = probe_pix[keep], normals[keep], rads[keep]
    gt = {k: batch[k] for k in ("albedo", "normal", "material")}
    gt["depth"] = torch.where(batch["mask"][:, 0], batch["depth"][:, 0], torch.zeros_like(batch["depth"][:, 0]))
    psnr(
        "gt_probes/render_psnr_at_probes",
        gt,
        probe_pix,
        lambda idx, o, wi, b: hemisphere_lookup(rads, idx, normals[idx], wi),
    )
    ctx = system.net.encode(batch["im"], model_gb["depth"], fov, normal=model_gb["normal"])
    gen = system.eval_generator()
    rgb, b = layer.render_pixels(model_gb, fov, probe_pix, system.light_fn(ctx, model_gb, fov, gen), gen)
    target = pixel_values(batch["im"], probe_pix)
    out["model/render_psnr_at_probes"] = float(psnr_tonemapped(rgb, target, scale[b]))
    split_views(
        views, b, lambda r, t, sc: {"model/render_psnr_at_probes": psnr_tonemapped(r, t, sc)}, rgb, target, scale[b]
    )
    return out
