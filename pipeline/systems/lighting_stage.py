"""Stage `train_lighting`: LightNet training, test metrics per mode, and the two baselines.

Baselines on the same test views: a constant light (the mean incident radiance of the training probes)
and the ground-truth G-buffers re-rendered under the ground-truth probe light at the surface-probe pixels
(the best any light model can do with this render layer at this spp). The model is also scored at those
probe pixels so the gap reads off directly.
"""

from __future__ import annotations

from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from pipeline.data.datamodules import InteriorVerseDataModule
from pipeline.data.datasets import read_manifest
from pipeline.models.light_net.branches import image_scale
from pipeline.systems.lighting import (
    LightingSystem,
    grid_pixels,
    log_l1,
    probe_rays,
    psnr_tonemapped,
    relative_mse_metric,
    render_pixels,
)
from pipeline.systems.trainer import stage_trainer
from pipeline.tracking import stage_run, write_metrics


def mean_training_radiance(loader) -> torch.Tensor:
    total, n = torch.zeros(3, dtype=torch.float64), 0
    for batch in loader:
        for light in batch.get("light", []):
            for kind in ("surf", "free"):
                r = torch.as_tensor(light[f"{kind}_radiance"], dtype=torch.float64).reshape(-1, 3)
                total += r.sum(0)
                n += len(r)
    if n == 0:
        raise ValueError("the training split has no lighting ground truth (run synthesize with lighting)")
    return (total / n).float()


@torch.no_grad()
def baseline_metrics(batch: dict, constant: torch.Tensor, spp: int, stride: int, system: LightingSystem) -> dict:
    """Constant-light errors (probes, stride-grid re-render) and the ground-truth-probe re-render at probe
    pixels, with the model's re-render at the same pixels."""
    gen = torch.Generator().manual_seed(1234)
    fov = LightingSystem.fov(batch)
    out = {}
    for kind in ("surf", "free"):
        r = probe_rays(batch["light"], kind, None, None, gen, "cpu")
        if r is not None:
            pred = constant.expand_as(r[2])
            out[f"constant/{kind}_light_relmse"] = float(relative_mse_metric(pred, r[2]))
            out[f"constant/{kind}_light_log_l1"] = float(log_l1(pred, r[2]))
    B, _, H, W = batch["im"].shape
    scale = image_scale(batch["im"])
    gt = {k: batch[k] for k in ("albedo", "normal", "material")}
    gt["depth"] = torch.where(batch["mask"][:, 0], batch["depth"][:, 0], torch.zeros_like(batch["depth"][:, 0]))

    def shade(pixels, radiance, gbuf):  # each baseline render draws the same directions
        return render_pixels(gbuf, batch["im"], fov, pixels, radiance, spp, torch.Generator().manual_seed(1234))

    pix = grid_pixels(batch["mask"][:, 0], stride)
    model_gb = system.gbuffers(batch)  # what the model sees (predicted or ground truth, per config)
    rgb, target, b = shade(pix, lambda idx, o, wi, b: constant.expand(len(wi), 3), model_gb)
    out["constant/render_psnr"] = float(psnr_tonemapped(rgb, target, scale[b]))
    # ground-truth probes: the texel of each probe's hemisphere nearest to the direction
    probe_pix, probe_dirs, probe_rad = [], [], []
    for bi, light in enumerate(batch["light"]):
        px = torch.as_tensor(light["surf_pixel"]).long()
        probe_pix.append(bi * H * W + px[:, 0] * W + px[:, 1])
        probe_dirs.append(torch.as_tensor(light["surf_directions"]).float().flatten(1, 2))
        probe_rad.append(torch.as_tensor(light["surf_radiance"]).float().flatten(1, 2))
    pp = torch.cat(probe_pix)
    dirs, rads = torch.cat(probe_dirs), torch.cat(probe_rad)
    keep = batch["mask"][:, 0].reshape(-1)[pp]
    pp, dirs, rads = pp[keep], dirs[keep], rads[keep]

    def probe_light(idx, o, wi, b):
        texel = torch.einsum("mtc,mc->mt", dirs[idx], wi).argmax(-1)
        return rads[idx, texel]

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
    constant = mean_training_radiance(dm.plain_loader("train"))
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
        # validation may not fall on the last epoch (check_val_every_n_epoch): measure the end state
        after = float(trainer.validate(system, datamodule=dm, verbose=False)[0]["val/render_psnr"])
        trainer.test(system, datamodule=dm, verbose=False)
        metrics = {f"{mode}/{k}": float(v) for k, v in trainer.callback_metrics.items() if k.startswith("test/")}
        metrics[f"{mode}/val/render_psnr_before_training"] = float(start["val/render_psnr"])
        metrics[f"{mode}/val/render_psnr_after_training"] = after
        system.eval()
        rows = [
            baseline_metrics(b, constant, int(lt.eval_spp), int(lt.eval_stride), system)
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
    return metrics
