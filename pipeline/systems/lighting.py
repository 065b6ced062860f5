"""LightningModule for LightNet: HDR light supervision at ground-truth probes + Monte Carlo re-rendering.

Per training step, for a batch of views: G-buffers (the frozen MaterialNet's predictions, its depth in
metres through the exported depth scale, or the ground truth), random probes and texels of the lighting
ground truth (`light_losses.LIGHT_LOSSES`, chosen by `lighting.light_loss`), and K random valid pixels
re-rendered through the render layer with LightNet as the incident-radiance callback (L2 against the
input, in units of the image mean; `RENDER_LOSSES` for the two estimators of that L2).
Validation and test score every probe texel and a stride grid of pixels at the evaluation spp, with a
generator seeded from `render.seed`; the test step also scores the content-blind baselines
(`lighting_baselines`) on the same views and directions.
"""

from __future__ import annotations

from collections.abc import Callable

import lightning as L
import torch

from pipeline.data.lighting import ProbeRays, probe_rays
from pipeline.metrics.image import psnr_tonemapped
from pipeline.metrics.lighting import light_errors, ray_classes, relmse
from pipeline.models.light_net import LightNet
from pipeline.models.material_net import MaterialNet
from pipeline.models.render_layer import MCRenderLayer
from pipeline.ops.camera import grid_pixels, pixel_values
from pipeline.systems.light_losses import LIGHT_LOSSES, light_nmse_loss
from pipeline.systems.lighting_baselines import baseline_metrics
from pipeline.systems.per_view import split_views

QUERY_CHUNK = 8192  # LightNet queries per forward at evaluation (bounds memory)
MATERIAL_MAPS = ("albedo", "normal", "material", "depth")  # what LightNet reads of MaterialNet's output
# lighting.ssrt_depth: the depth SSRT marches against. valid: the masked pixels only (lamps and sky left
# out, as the ground truth has no material there); every_pixel: MaterialNet's depth on every pixel, so a
# ray towards a visible lamp or window hits it in screen space, and the local branch reads its radiance
SSRT_DEPTHS = ("valid", "every_pixel")
# lighting.render_loss: how the re-render L2 is estimated from a Monte Carlo render r of a pixel with target t.
# squared: (r - t)^2, whose expectation is (E[r] - t)^2 + Var[r]: the estimator's variance is part of the
# loss, and a sharp light (a lamp, a window, a room's edges seen by a glossy lobe) has more variance than a
# blurred one of the same mean, so the loss pulls the light towards a blur. decorrelated: two independent
# estimates r1, r2 with half the samples each, (r1 - t)(r2 - t), whose expectation is (E[r] - t)^2 alone
# (and its gradient that of the squared bias): the same samples, no pull towards blur; a step's value can be
# negative. docs/method.md, 'The re-render loss'.
RENDER_LOSSES = ("squared", "decorrelated")


class LightingSystem(L.LightningModule):
    """light_net: LightNet kwargs; material: a MaterialNet export ({"model", "state_dict", "depth_scale"},
    `models.export.load_material_export`), used when gbuffers == "predicted"; render: the `conf/render/`
    group (estimator, spp, eval_spp, adaptive, li_size, chunk, seed); baselines: the constants of
    `lighting_baselines` (set before `Trainer.test` to score them beside the model); cache_gbuffers: the
    frozen MaterialNet runs once per view, not once per step (`material_maps`)."""

    def __init__(
        self,
        light_net: dict,
        material: dict | None,
        render: dict,
        gbuffers: str = "predicted",
        pixels: int = 64,
        probes: int = 8,
        texels: int = 16,
        free_probes: int = 2,
        render_weight: float = 1.0,
        light_weight: float = 1.0,
        light_loss: str = "relative_mse",
        nmse_weight: float = 0.0,
        eval_stride: int = 4,
        optimizer: Callable | None = None,
        scheduler: Callable | None = None,
        seed: int = 0,
        cache_gbuffers: bool = True,
        ssrt_depth: str = "valid",
        render_loss: str = "squared",
    ):
        super().__init__()
        if gbuffers not in ("predicted", "ground_truth"):
            raise ValueError(f"gbuffers={gbuffers!r}: choose predicted or ground_truth")
        if gbuffers == "predicted" and material is None:
            raise ValueError("gbuffers=predicted needs the trained MaterialNet (material_path)")
        self.save_hyperparameters({"light_net": dict(light_net), "gbuffers": gbuffers, "render": dict(render)})
        self.net = LightNet(**light_net)
        self.material = None
        if gbuffers == "predicted":
            self.material = MaterialNet(**material["model"]).eval().requires_grad_(False)
            self.material.load_state_dict(material["state_dict"])
            self.depth_scale = float(material["depth_scale"])
        if render_loss not in RENDER_LOSSES:
            raise ValueError(f"lighting.render_loss={render_loss!r}: choose one of {RENDER_LOSSES}")
        self.render_loss = render_loss
        train_render = dict(render)
        if render_loss == "decorrelated":  # two estimates of half the samples each: the step's cost unchanged
            if int(render["spp"]) < 2:
                raise ValueError(f"render.spp={render['spp']}: lighting.render_loss=decorrelated needs at least 2")
            train_render["spp"] = int(render["spp"]) // 2
        self.train_layer = MCRenderLayer.from_config(train_render, "spp")
        self.eval_layer = MCRenderLayer.from_config(render, "eval_spp")
        self.eval_seed = int(render["seed"])
        self.pixels, self.probes, self.texels, self.free_probes = pixels, probes, texels, free_probes
        self.render_weight, self.eval_stride = float(render_weight), int(eval_stride)
        self.light_weight = float(light_weight)  # 0: no direct light supervision (the re-render loss alone)
        if light_loss not in LIGHT_LOSSES:
            raise ValueError(f"lighting.light_loss={light_loss!r}: choose one of {tuple(LIGHT_LOSSES)}")
        self.light_loss = LIGHT_LOSSES[light_loss]
        if not nmse_weight >= 0:
            raise ValueError(f"lighting.nmse_weight={nmse_weight}: must be >= 0")
        self.nmse_weight = float(nmse_weight)  # the normalised-MSE term beside the light loss (0: off)
        self.optimizer_fn, self.scheduler_fn = optimizer, scheduler
        self.generator = torch.Generator().manual_seed(int(seed))
        self.baselines = None  # lighting_baselines.Constants, set by the stage before testing
        self.eval_rows: list[dict] = []
        self.test_views: list[dict] = []  # one row per test view: its id and its own scores (test_step)
        self.validated_at_step = -1
        self.cache_gbuffers = bool(cache_gbuffers)  # the frozen MaterialNet's maps once per view (`material_maps`)
        self._material_cache: dict[tuple, dict[str, torch.Tensor]] = {}
        if ssrt_depth not in SSRT_DEPTHS:
            raise ValueError(f"lighting.ssrt_depth={ssrt_depth!r}: choose one of {SSRT_DEPTHS}")
        if ssrt_depth == "every_pixel" and gbuffers != "predicted":
            raise ValueError(
                "lighting.ssrt_depth=every_pixel needs gbuffers=predicted (the ground truth has no depth there)"
            )
        self.ssrt_depth = ssrt_depth

    # ------------------------------------------------------------------ pieces
    def eval_generator(self) -> torch.Generator:
        """A fresh generator for one evaluation batch: every method scored on a batch draws the same
        directions, and the same `render.seed` gives the same numbers."""
        return torch.Generator().manual_seed(self.eval_seed)

    @torch.no_grad()
    def gbuffers(self, batch: dict) -> dict:
        """depth (B, H, W) z-depth metres (0 where masked, or only where none with ssrt_depth=every_pixel),
        albedo/normal (B, 3, H, W), material (B, 2, H, W)."""
        if self.material is None:
            gb = {k: batch[k] for k in ("albedo", "normal", "material")}
            depth = batch["depth"][:, 0]
        else:
            pred = self.material_maps(batch)
            gb = {k: pred[k] for k in ("albedo", "normal", "material")}
            depth = pred["depth"][:, 0] * self.depth_scale
        keep = batch["mask"][:, 0]
        if self.ssrt_depth == "every_pixel":  # lamps and windows too: SSRT can hit what the camera sees
            keep = torch.isfinite(depth) & (depth > 0)
        gb["depth"] = torch.where(keep, depth, torch.zeros_like(depth))
        return gb

    @torch.no_grad()
    def material_maps(self, batch: dict) -> dict[str, torch.Tensor]:
        """The frozen MaterialNet's albedo, normal, material and depth (B, C, H, W) for the batch's views.

        MaterialNet is frozen, so a view's maps never change: each view's are computed once and kept,
        keyed by its id and a fingerprint of its input image (an augmented or edited image is a new key),
        and every later epoch reads them instead of running the network again (`cache_gbuffers`)."""
        self.material.eval()
        im = batch["im"]
        if not self.cache_gbuffers or "id" not in batch:
            return self.material(im)
        keys = [(str(v), tuple(im.shape[1:]), float(im[i].double().sum())) for i, v in enumerate(batch["id"])]
        missing = [i for i, k in enumerate(keys) if k not in self._material_cache]
        if missing:
            pred = self.material(im[missing])
            for j, i in enumerate(missing):
                self._material_cache[keys[i]] = {k: pred[k][j] for k in MATERIAL_MAPS}
        return {k: torch.stack([self._material_cache[key][k] for key in keys]) for k in MATERIAL_MAPS}

    @staticmethod
    def fov(batch: dict) -> torch.Tensor:
        """(B,) horizontal FOV of each view, degrees (views of a batch may differ)."""
        return batch["fov_x_deg"].float()

    def light_fn(self, ctx, gb, fov, generator):
        """LightNet as the render layer's radiance callback."""

        def radiance(idx, origin, wi, image):
            return self.net(ctx, gb, fov, origin, wi, image, generator)["radiance"]

        return radiance

    def query(self, ctx, gb, fov, rays, generator) -> dict[str, torch.Tensor]:
        """LightNet's texel values at the M rays of a `ProbeRays`, in chunks: radiance (M, 3) the mean over
        each texel's S directions; hit (M,) whether most of them hit in SSRT; u (M,) their mean confidence."""
        M, S = rays.direction.shape[:2]
        origin = rays.origin.repeat_interleave(S, 0)
        image = rays.image.repeat_interleave(S, 0)
        direction = rays.direction.reshape(-1, 3)
        chunks = [
            self.net(
                ctx,
                gb,
                fov,
                origin[i : i + QUERY_CHUNK],
                direction[i : i + QUERY_CHUNK],
                image[i : i + QUERY_CHUNK],
                generator,
            )
            for i in range(0, len(direction), QUERY_CHUNK)
        ]
        out = {k: torch.cat([c[k] for c in chunks]) for k in ("radiance", "hit", "u")}
        return {
            "radiance": out["radiance"].view(M, S, 3).mean(1),
            "hit": out["hit"].view(M, S).float().mean(1) > 0.5,
            "u": out["u"].view(M, S).mean(1),
        }

    def sample_pixels(self, mask: torch.Tensor, per_image: int) -> torch.Tensor:
        """Random valid flat pixel indices, per_image from each image (fewer if it has fewer)."""
        B = mask.shape[0]
        flat = mask.reshape(B, -1)
        out = []
        for bi in range(B):
            valid = torch.nonzero(flat[bi]).squeeze(-1)
            pick = valid[torch.randperm(len(valid), generator=self.generator)[:per_image].to(valid.device)]
            out.append(pick + bi * flat.shape[1])
        return torch.cat(out)

    def render_term(self, ctx, gb, fov, pix, target, scale) -> torch.Tensor:
        """The re-render loss of flat pixels pix (M,) against target (M, 3), in units of each view's scale
        (B,), by `self.render_loss` (`RENDER_LOSSES`). One render of 2M pixels for `decorrelated`: every
        sample has its own random numbers, so the two halves are independent estimates."""
        light = self.light_fn(ctx, gb, fov, self.generator)
        if self.render_loss == "squared":
            rgb, b = self.train_layer.render_pixels(gb, fov, pix, light, self.generator)
            return (((rgb - target) / scale[b, None]) ** 2).mean()
        rgb, b = self.train_layer.render_pixels(gb, fov, torch.cat([pix, pix]), light, self.generator)
        M = len(pix)
        first, second = (rgb[:M] - target) / scale[b[:M], None], (rgb[M:] - target) / scale[b[M:], None]
        return (first * second).mean()

    # ------------------------------------------------------------------ Lightning
    def training_step(self, batch, batch_idx):
        fov = self.fov(batch)
        gb = self.gbuffers(batch)
        ctx = self.net.encode(batch["im"], gb["depth"], fov, normal=gb["normal"])
        scale = ctx["scale"]
        losses = {}
        parts = [
            probe_rays(batch["light"], kind, n, self.texels, self.generator)
            for kind, n in (("surf", self.probes), ("free", self.free_probes))
        ]
        rays = ProbeRays.cat([p for p in parts if p is not None])
        if rays is not None and (self.light_weight > 0 or self.nmse_weight > 0):
            rays = rays.to(self.device)
            pred = self.query(ctx, gb, fov, rays, self.generator)["radiance"]
            losses["light"] = self.light_loss(pred, rays.radiance, scale[rays.image])
            if self.nmse_weight > 0:
                losses["light_nmse"] = light_nmse_loss(pred, rays.radiance, scale[rays.image])
        pix = self.sample_pixels(batch["mask"][:, 0], self.pixels)
        losses["render"] = self.render_term(ctx, gb, fov, pix, pixel_values(batch["im"], pix), scale)
        total = (
            self.light_weight * losses.get("light", 0.0)
            + self.nmse_weight * losses.get("light_nmse", 0.0)
            + self.render_weight * losses["render"]
        )
        bs = batch["im"].shape[0]
        self.log("train/loss", total, prog_bar=True, on_step=True, on_epoch=True, batch_size=bs, sync_dist=True)
        for k, v in losses.items():
            self.log(f"train/loss_{k}", v, on_step=False, on_epoch=True, batch_size=bs, sync_dist=True)
        return total

    @torch.no_grad()
    def evaluate_batch(self, batch, views: list[dict] | None = None) -> dict[str, float]:
        """Light errors at every probe texel (surface and free separately, and per ray class) and the
        re-render PSNR / relMSE on the stride grid of valid pixels at eval_spp. views (one dict per view of
        the batch): also each view's own light errors and re-render scores (`per_view.split_views`)."""
        gen = self.eval_generator()
        fov = self.fov(batch)
        gb = self.gbuffers(batch)
        ctx = self.net.encode(batch["im"], gb["depth"], fov, normal=gb["normal"])
        out = {}
        for kind in ("surf", "free"):
            rays = probe_rays(batch["light"], kind)
            if rays is None:
                continue
            rays = rays.to(self.device)
            q = self.query(ctx, gb, fov, rays, gen)
            pred, target, s = q["radiance"], rays.radiance, ctx["scale"][rays.image]
            out.update({f"{kind}_{k}": v for k, v in light_errors(pred, target, s).items()})
            split_views(views, rays.image, light_errors, pred, target, s, prefix=f"{kind}_")
            for name, sel in ray_classes(q["hit"], q["u"]).items():
                out[f"{kind}_rays_{name}"] = float(sel.float().mean())
                if sel.any():  # a batch without such rays adds nothing to that class's mean
                    errs = light_errors(pred[sel], target[sel], s[sel])
                    out[f"{kind}_light_relmse_{name}"] = errs["light_relmse"]
                    out[f"{kind}_light_log_l1_{name}"] = errs["light_log_l1"]
        pix = grid_pixels(batch["mask"][:, 0], self.eval_stride)
        gen = self.eval_generator()  # afresh: the re-render draws the directions every baseline draws
        rgb, b = self.eval_layer.render_pixels(gb, fov, pix, self.light_fn(ctx, gb, fov, gen), gen)
        target = pixel_values(batch["im"], pix)
        out["render_psnr"] = float(psnr_tonemapped(rgb, target, ctx["scale"][b]))
        out["render_relmse"] = float(relmse(rgb, target, ctx["scale"][b]))
        split_views(
            views,
            b,
            lambda r, t, sc: {"render_psnr": psnr_tonemapped(r, t, sc), "render_relmse": relmse(r, t, sc)},
            rgb,
            target,
            ctx["scale"][b],
        )
        return out

    def validation_step(self, batch, batch_idx):
        for k, v in self.evaluate_batch(batch).items():
            self.log(f"val/{k}", v, batch_size=batch["im"].shape[0], sync_dist=True)

    def on_validation_epoch_end(self):
        if not self.trainer.sanity_checking:
            self.validated_at_step = self.global_step  # lets the stage reuse the final epoch's validation

    def test_step(self, batch, batch_idx):
        views = [{"id": view} for view in batch["id"]]
        row = self.evaluate_batch(batch, views)
        if self.baselines is not None:
            row.update(baseline_metrics(batch, self.baselines, self, views))
        self.eval_rows.append(row)
        self.test_views.extend(views)
        for k, v in row.items():
            self.log(f"test/{k}", v, batch_size=batch["im"].shape[0], sync_dist=True)

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        # the sampler of pixels, probes and directions: a resumed run continues its draws, not restarts them
        checkpoint["sampling_generator"] = self.generator.get_state()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        if "sampling_generator" in checkpoint:
            self.generator.set_state(checkpoint["sampling_generator"])

    def configure_optimizers(self):
        opt = self.optimizer_fn(self.net.parameters())
        if self.scheduler_fn is None:
            return opt
        return {"optimizer": opt, "lr_scheduler": {"scheduler": self.scheduler_fn(opt), "interval": "epoch"}}
