"""Stage `train_lighting`: LightNet training, test metrics per mode, and the two baselines.

Baselines on the same test views: a constant light (the mean incident radiance of the training probes),
the same at each photo's exposure (the training probes' mean in units of their image's mean, times the
test image's mean: what a network that ignores the image's content can still get right), and the
ground-truth G-buffers re-rendered under the ground-truth probe light at the surface-probe pixels
(what a light model could do with this render layer at this spp if the probes were exact; coarse, noisy
probes score below it, see README). The model is also scored at those probe pixels so the gap reads off
directly.

Two oracle references read the light errors' scale: each probe's own mean and median radiance over its
texels, from the ground truth. They know more than any model, except where in the probe the light
comes from; a model trained to the light loss's fixed point (the conditional mean) that cannot place
sources within a probe scores about like `probe_mean_oracle`, and the gap to `probe_median_oracle`
shows how much relMSE and log-L1 reward a low, median-like prediction rather than the light's energy.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from pipeline.data.datamodules import InteriorVerseDataModule
from pipeline.data.datasets import read_manifest
from pipeline.models.light_net.branches import image_scale
from pipeline.ops.frames import orthonormal_basis, to_local
from pipeline.systems.lighting import (
    LightingSystem,
    grid_pixels,
    log_l1,
    normalised_mse,
    probe_rays,
    psnr_tonemapped,
    relative_mse_metric,
    render_pixels,
)
from pipeline.systems.lighting_figures import lighting_figures
from pipeline.systems.trainer import stage_trainer
from pipeline.tracking import stage_run, write_metrics


def mean_training_radiance(loader) -> tuple[torch.Tensor, torch.Tensor]:
    """Over every training probe texel: the mean radiance (3,), and the mean radiance in units of its
    image's mean (3,), the constant of the exposure-scaled baseline."""
    total, ratio, n = torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), 0
    for batch in loader:
        scale = image_scale(batch["im"]).double()
        for b, light in enumerate(batch.get("light", [])):
            for kind in ("surf", "free"):
                r = torch.as_tensor(light[f"{kind}_radiance"], dtype=torch.float64).reshape(-1, 3)
                total += r.sum(0)
                ratio += r.sum(0) / scale[b]
                n += len(r)
    if n == 0:
        raise ValueError("the training split has no lighting ground truth (run synthesize with lighting)")
    return (total / n).float(), (ratio / n).float()


def hemisphere_lookup(
    radiance: torch.Tensor, probe: torch.Tensor, normal: torch.Tensor, wi: torch.Tensor
) -> torch.Tensor:
    """Bilinear lookup in hemisphere probes laid out as the synthesize stage writes them
    (`data.synth.views.hemisphere_directions`: texel centres at theta = (a + .5)/rows * pi/2 from the
    normal, phi = (b + .5)/cols * 2 pi from the tangent of `orthonormal_basis`).

    radiance (P, rows, cols, 3) probes; probe (K,) long, the probe of each query; normal (K, 3) its unit
    normal; wi (K, 3) unit query directions. Returns (K, 3): exact at texel centres, bilinear between
    them, periodic in phi, clamped in theta (directions below the horizon read the last row)."""
    _, rows, cols, _ = radiance.shape
    flat = radiance.reshape(-1, 3)
    t, bt = orthonormal_basis(normal)
    x, y, z = to_local(wi, t, bt, normal).unbind(-1)
    theta = torch.atan2(torch.sqrt(x * x + y * y), z).clamp(0, math.pi / 2)
    phi = torch.atan2(y, x) % (2 * math.pi)
    a = (theta / (math.pi / 2) * rows - 0.5).clamp(0, rows - 1)
    b = phi / (2 * math.pi) * cols - 0.5
    a0, b0 = a.floor(), b.floor()
    fa, fb = (a - a0)[:, None], (b - b0)[:, None]
    a0 = a0.long()
    a1 = (a0 + 1).clamp(max=rows - 1)
    b0l = b0.long() % cols
    b1l = (b0l + 1) % cols
    base = probe * rows

    def at(r, c):
        return flat[(base + r) * cols + c]

    return (1 - fa) * ((1 - fb) * at(a0, b0l) + fb * at(a0, b1l)) + fa * ((1 - fb) * at(a1, b0l) + fb * at(a1, b1l))


@torch.no_grad()
def probe_oracle_light(lights: list[dict], kind: str, scale: torch.Tensor) -> dict[str, tuple] | None:
    """Each probe's ground-truth mean and (lower) median radiance over its texels, per channel, as the
    prediction for each of its texels:
    {"probe_mean_oracle" | "probe_median_oracle": (pred (M, 3), target (M, 3), scale (M,))} over the batch's
    probes of `kind`, with scale (B,) the image means. None when the batch has no such probes."""
    preds, targets, scales = {"probe_mean_oracle": [], "probe_median_oracle": []}, [], []
    for b, light in enumerate(lights):
        r = torch.as_tensor(light[f"{kind}_radiance"], dtype=torch.float32).flatten(1, 2)  # (P, T, 3)
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
def baseline_metrics(
    batch: dict, constant: torch.Tensor, ratio: torch.Tensor, spp: int, stride: int, system: LightingSystem
) -> dict:
    """Constant-light errors (probes, stride-grid re-render) for the mean training radiance `constant` and
    for `ratio` times each image's mean (the same light at the photo's exposure), and the
    ground-truth-probe re-render at probe pixels, with the model's re-render at the same pixels; the light
    errors of the probe-mean and probe-median oracles."""
    gen = torch.Generator().manual_seed(1234)
    fov = LightingSystem.fov(batch)
    out = {}
    scale = image_scale(batch["im"])
    for kind in ("surf", "free"):
        r = probe_rays(batch["light"], kind, None, None, gen, "cpu")
        if r is None:
            continue
        preds = {"constant": constant.expand_as(r[2]), "scaled_constant": ratio * scale[r[3], None]}
        cases = {name: (pred, r[2], scale[r[3]]) for name, pred in preds.items()}
        cases.update(probe_oracle_light(batch["light"], kind, scale))
        for name, (pred, target, s) in cases.items():
            out[f"{name}/{kind}_light_relmse"] = float(relative_mse_metric(pred, target, s))
            out[f"{name}/{kind}_light_nmse"] = float(normalised_mse(pred, target))
            out[f"{name}/{kind}_light_log_l1"] = float(log_l1(pred, target, s))
    B, _, H, W = batch["im"].shape
    gt = {k: batch[k] for k in ("albedo", "normal", "material")}
    gt["depth"] = torch.where(batch["mask"][:, 0], batch["depth"][:, 0], torch.zeros_like(batch["depth"][:, 0]))

    def shade(pixels, radiance, gbuf):  # each baseline render draws the same directions
        return render_pixels(gbuf, batch["im"], fov, pixels, radiance, spp, torch.Generator().manual_seed(1234))

    pix = grid_pixels(batch["mask"][:, 0], stride)
    model_gb = system.gbuffers(batch)  # what the model sees (predicted or ground truth, per config)
    rgb, target, b = shade(pix, lambda idx, o, wi, b: constant.expand(len(wi), 3), model_gb)
    out["constant/render_psnr"] = float(psnr_tonemapped(rgb, target, scale[b]))
    rgb, target, b = shade(pix, lambda idx, o, wi, b: ratio * scale[b, None], model_gb)
    out["scaled_constant/render_psnr"] = float(psnr_tonemapped(rgb, target, scale[b]))
    # ground-truth probes, interpolated bilinearly between their texel centres
    probe_pix, probe_n, probe_rad = [], [], []
    for bi, light in enumerate(batch["light"]):
        px = torch.as_tensor(light["surf_pixel"]).long()
        probe_pix.append(bi * H * W + px[:, 0] * W + px[:, 1])
        probe_n.append(torch.as_tensor(light["surf_normal"]).float())
        probe_rad.append(torch.as_tensor(light["surf_radiance"]).float())
    pp = torch.cat(probe_pix)
    normals, rads = torch.cat(probe_n), torch.cat(probe_rad)
    keep = batch["mask"][:, 0].reshape(-1)[pp]
    pp, normals, rads = pp[keep], normals[keep], rads[keep]

    def probe_light(idx, o, wi, b):
        return hemisphere_lookup(rads, idx, normals[idx], wi)

    rgb, target, b = shade(pp, probe_light, gt)
    out["gt_probes/render_psnr_at_probes"] = float(psnr_tonemapped(rgb, target, scale[b]))
    ctx = system.net.encode(batch["im"], model_gb["depth"], fov)
    model_rgb, target, b = system.render(ctx, model_gb, batch, fov, pp, spp, gen)
    out["model/render_psnr_at_probes"] = float(psnr_tonemapped(model_rgb, target, scale[b]))
    return out


def run_train_lighting(cfg: DictConfig) -> dict[str, float]:
    import lightning as L
    import mlflow
    from lightning.pytorch.callbacks import ModelCheckpoint

    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    material = None
    if cfg.gbuffers == "predicted":
        path = Path(cfg.material_path)
        if not path.is_file():
            raise FileNotFoundError(f"material_path={path}: no MaterialNet export (run train_material first)")
        material = torch.load(path, map_location="cpu", weights_only=True)
    dm = InteriorVerseDataModule(cfg.data_dir, batch_size=int(cfg.batch_size), seed=int(cfg.seed), lighting=True)
    dm.setup("fit")
    dm.setup("test")
    constant, ratio = mean_training_radiance(dm.plain_loader("train"))
    lt = cfg.lighting
    system = LightingSystem(
        light_net=OmegaConf.to_container(cfg.model.light_net, resolve=True),
        material=material,
        gbuffers=str(cfg.gbuffers),
        pixels=int(lt.pixels),
        spp=int(lt.spp),
        probes=int(lt.probes),
        texels=int(lt.texels),
        free_probes=int(lt.free_probes),
        render_weight=float(lt.render_weight),
        eval_spp=int(lt.eval_spp),
        eval_stride=int(lt.eval_stride),
        optimizer=lambda params: torch.optim.AdamW(params, lr=float(lt.lr), weight_decay=1e-4),
        seed=int(cfg.seed),
    )
    out, report = Path(cfg.out_dir), Path(cfg.report_dir)
    source = read_manifest(cfg.data_dir).get("source", "unspecified")
    mode = str(cfg.model.light_net.mode)
    with stage_run("train_lighting", cfg, tags={"data_source": source, "mode": mode}) as run:
        ckpt = ModelCheckpoint(
            dirpath=out / "checkpoints", filename="best", monitor="val/render_psnr", mode="max", save_last=True
        )
        trainer = stage_trainer(run, OmegaConf.to_container(cfg.trainer, resolve=True), out, [ckpt], bool(cfg.progress))
        # the first validation pass (before any training step) records the starting re-render PSNR
        start = trainer.validate(system, datamodule=dm, verbose=False)[0]
        trainer.fit(system, datamodule=dm)
        if system.validated_at_step == trainer.global_step:  # the last epoch was validated: same weights
            last = float(trainer.callback_metrics["val/render_psnr"])
        else:
            last = float(trainer.validate(system, datamodule=dm, verbose=False)[0]["val/render_psnr"])
        # model selection on validation: the light loss's rare huge terms make late steps jumpy, so the
        # test split, the baselines' model row and model.pt use the best validated weights
        chosen, after = "last", last
        if ckpt.best_model_path and ckpt.best_model_score is not None and float(ckpt.best_model_score) > last:
            best = torch.load(ckpt.best_model_path, map_location="cpu", weights_only=True)
            system.load_state_dict(best["state_dict"])
            chosen, after = f"best (epoch {best['epoch']})", float(ckpt.best_model_score)
        mlflow.set_tag("test_weights", chosen)
        trainer.test(system, datamodule=dm, verbose=False)
        metrics = {f"{mode}/{k}": float(v) for k, v in trainer.callback_metrics.items() if k.startswith("test/")}
        metrics[f"{mode}/val/render_psnr_before_training"] = float(start["val/render_psnr"])
        metrics[f"{mode}/val/render_psnr_after_training"] = after
        metrics[f"{mode}/val/render_psnr_last_epoch"] = last
        system.eval()
        rows = [
            baseline_metrics(b, constant, ratio, int(lt.eval_spp), int(lt.eval_stride), system)
            for b in dm.plain_loader("test")
        ]
        for key in rows[0]:
            metrics[f"baseline/{key}"] = float(sum(r[key] for r in rows) / len(rows))
        metrics["global_step"] = float(trainer.global_step)
        torch.save(
            {
                "format": "invrender.light_net/1",
                "light_net": dict(system.hparams["light_net"]),
                "state_dict": {k: v.cpu() for k, v in system.net.state_dict().items()},
            },
            out / "model.pt",
        )
        write_metrics(report / "metrics.json", metrics)
        mlflow.log_metrics({k.replace("/", "."): v for k, v in metrics.items()})
        if int(lt.figure_views) > 0:
            batch = next(iter(dm.plain_loader("test", batch_size=int(lt.figure_views))))
            for figure in lighting_figures(system, batch, ratio, int(lt.eval_spp), report):
                mlflow.log_artifact(str(figure), "figures")
    return metrics
