"""LightningModule for LightNet: HDR light supervision at ground-truth probes + Monte Carlo re-rendering.

Per training step, for a batch of views: G-buffers (the frozen MaterialNet's predictions, its depth in
metres through the exported depth scale, or the ground truth), random probes and texels of the lighting
ground truth (relative MSE with a stop-gradient denominator, eps 1e-3, no clipping), and K random valid
pixels re-rendered through the MC estimator with LightNet as the incident-radiance callback (L2 against
the input, in units of the image mean).
"""

from __future__ import annotations

from collections.abc import Callable

import lightning as L
import torch

from pipeline.models.light_net import LightNet
from pipeline.models.light_net.branches import backproject_views
from pipeline.models.material_net import MaterialNet
from pipeline.ops.mc import estimate

PROBE_EPS = 1e-3  # m: probe origins sit this far above their surface, as do re-render ray origins


def relative_mse(pred: torch.Tensor, target: torch.Tensor, eps: float = 1e-3, scale: torch.Tensor | None = None):
    """mean(((L^ - L) / (sg(L^) + eps))^2): RawNeRF's HDR loss (no clipping). With `scale` (M,), the mean
    of each sample's image, radiance is first divided by it: the networks predict in those units, and an
    absolute eps would weigh a dim room's texels (where eps is a large share of the light) unlike a
    bright room's."""
    if scale is not None:
        pred, target = pred / scale[:, None], target / scale[:, None]
    return (((pred - target) / (pred.detach() + eps)) ** 2).mean()


def relative_mse_metric(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor, eps: float = 1e-2):
    """Rendering's relMSE, mean (L^ - L)^2 / (L^2 + eps) over (M, 3) radiances, on exposure-normalised
    radiance L / s (s (M,) the mean of each sample's image), so eps is 1 % of the image's mean squared
    rather than an absolute floor that would swamp dim scenes. The same form as the re-render relMSE and
    the render-layer benchmark's; per texel, so a dark texel lit wrongly counts as much as a lamp."""
    s = scale[:, None]
    p, t = pred / s, target / s
    return ((p - t) ** 2 / (t**2 + eps)).mean()


def normalised_mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """sum((L^ - L)^2) / sum(L^2): the squared error relative to the light's energy. Dominated by the few
    brightest texels (a sun or lamp texel can hold most of a probe's energy), so it mostly asks whether
    the light sources were found; reported beside relMSE."""
    return ((pred - target) ** 2).sum() / (target**2).sum().clamp(min=1e-12)


def log_l1(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """mean |log(1 + L^/s) - log(1 + L/s)| over (M, 3) radiances, with s (M,) the mean of each sample's
    image: exposure-normalised, so that it is a relative (log) error whatever the scene's brightness (on
    absolute radiance of about 0.05, log1p is nearly linear and this would be a plain L1)."""
    s = scale[:, None]
    return (torch.log1p(pred.clamp(min=0) / s) - torch.log1p(target.clamp(min=0) / s)).abs().mean()


def psnr_tonemapped(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """PSNR (dB) of HDR radiances after x / (2 * image mean), then Reinhard x / (1 + x), so values lie in
    [0, 1) whatever the exposure. pred, target (N, 3); scale (N,) image means."""

    def tm(x):
        x = x.clamp(min=0) / (2 * scale[:, None])
        return x / (1 + x)

    mse = ((tm(pred) - tm(target)) ** 2).mean().clamp(min=1e-12)
    return -10 * torch.log10(mse)


def probe_rays(lights: list[dict], kind: str, probes: int | None, texels: int | None, generator, device):
    """Rays of the lighting ground truth of a batch: origin (M, 3), direction (M, 3), radiance (M, 3),
    image index (M,), probe pixel (M, 2) (surface probes; -1 for free points). probes/texels None = all."""
    origins, dirs, rads, bidx, pix = [], [], [], [], []
    for b, light in enumerate(lights):
        pos = torch.as_tensor(light[f"{kind}_position"], dtype=torch.float32)
        if not len(pos):
            continue
        d = torch.as_tensor(light[f"{kind}_directions"], dtype=torch.float32).flatten(1, 2)  # (P, T, 3)
        r = torch.as_tensor(light[f"{kind}_radiance"], dtype=torch.float32).flatten(1, 2)
        P, T = d.shape[:2]
        pi = torch.randperm(P, generator=generator)[: probes or P]
        ti = torch.stack([torch.randperm(T, generator=generator)[: texels or T] for _ in range(len(pi))])
        o = pos[pi]
        if kind == "surf":
            o = o + PROBE_EPS * torch.as_tensor(light["surf_normal"], dtype=torch.float32)[pi]
            px = torch.as_tensor(light["surf_pixel"]).long()[pi]
        else:
            px = torch.full((len(pi), 2), -1, dtype=torch.long)
        n_t = ti.shape[1]
        origins.append(o.repeat_interleave(n_t, 0))
        dirs.append(torch.gather(d[pi], 1, ti[..., None].expand(-1, -1, 3)).flatten(0, 1))
        rads.append(torch.gather(r[pi], 1, ti[..., None].expand(-1, -1, 3)).flatten(0, 1))
        bidx.append(torch.full((len(pi) * n_t,), b, dtype=torch.long))
        pix.append(px.repeat_interleave(n_t, 0))
    if not origins:
        return None
    return tuple(torch.cat(x).to(device) for x in (origins, dirs, rads, bidx, pix))


def ray_classes(hit: torch.Tensor, u: torch.Tensor) -> dict[str, torch.Tensor]:
    """Masks (N,) of the three kinds of LightNet ray: `hit` (SSRT hit, u < 0.5: mostly the local branch),
    `uncertain` (hit, u >= 0.5: mostly the out-of-view branch) and `miss` (left the screen: out-of-view
    only). The light errors are also reported per class, to show which branch an error comes from."""
    return {"hit": hit & (u < 0.5), "uncertain": hit & (u >= 0.5), "miss": ~hit}


def grid_pixels(mask: torch.Tensor, stride: int) -> torch.Tensor:
    """Flat indices (into B*H*W) of the valid pixels of mask (B, H, W) on every `stride`-th row and column."""
    grid = torch.zeros_like(mask)
    grid[:, ::stride, ::stride] = True
    return torch.nonzero((grid & mask).reshape(-1)).squeeze(-1)


def render_pixels(gbuffer: dict, im: torch.Tensor, fov, pixels: torch.Tensor, radiance, spp: int, generator):
    """Re-render flat pixel indices (M,) (into B*H*W) of G-buffers (depth (B, H, W) z-depth m, normal,
    albedo (B, 3, H, W), material (B, 2, H, W)) with the MC estimator. radiance(idx, origin, wi, image)
    -> (K, 3) gives the light for K samples of pixels idx (K,) (origins just above their surface, image
    indices (K,)). Returns rgb (M, 3), the input im at those pixels (M, 3) and their image index (M,)."""
    B, _, H, W = im.shape
    b = pixels // (H * W)
    rc = pixels % (H * W)
    row, col = rc // W, rc % W
    pts = backproject_views(gbuffer["depth"], fov)[b, row, col]
    normal = torch.nn.functional.normalize(gbuffer["normal"][b, :, row, col], dim=-1)
    origin = pts + PROBE_EPS * normal
    mat = gbuffer["material"][b, :, row, col]
    diffuse, specular = estimate(
        lambda idx, wi: radiance(idx, origin[idx], wi, b[idx]),
        normal,
        torch.nn.functional.normalize(-pts, dim=-1),
        gbuffer["albedo"][b, :, row, col],
        mat[:, 0],
        mat[:, 1],
        spp,
        generator,
    )
    return diffuse + specular, im[b, :, row, col], b


class LightingSystem(L.LightningModule):
    """light_net: LightNet kwargs; material: {"model": kwargs, "state_dict": ..., "depth_scale": s} of the
    frozen MaterialNet, used when gbuffers == "predicted"; see the module docstring for the step."""

    def __init__(
        self,
        light_net: dict,
        material: dict | None,
        gbuffers: str = "predicted",
        pixels: int = 64,
        spp: int = 8,
        probes: int = 8,
        texels: int = 16,
        free_probes: int = 2,
        render_weight: float = 1.0,
        eval_spp: int = 16,
        eval_stride: int = 4,
        optimizer: Callable | None = None,
        seed: int = 0,
    ):
        super().__init__()
        if gbuffers not in ("predicted", "ground_truth"):
            raise ValueError(f"gbuffers={gbuffers!r}: choose predicted or ground_truth")
        if gbuffers == "predicted" and material is None:
            raise ValueError("gbuffers=predicted needs the trained MaterialNet (material_path)")
        self.save_hyperparameters({"light_net": dict(light_net), "gbuffers": gbuffers})
        self.net = LightNet(**light_net)
        self.material = None
        if gbuffers == "predicted":
            self.material = MaterialNet(**material["model"]).eval().requires_grad_(False)
            self.material.load_state_dict(material["state_dict"])
            self.depth_scale = float(material.get("depth_scale", 1.0))
        self.gbuffer_source = gbuffers
        self.pixels, self.spp, self.probes, self.texels, self.free_probes = pixels, spp, probes, texels, free_probes
        self.render_weight, self.eval_spp, self.eval_stride = float(render_weight), int(eval_spp), int(eval_stride)
        self.optimizer_fn = optimizer
        self.generator = torch.Generator().manual_seed(int(seed))
        self.eval_rows: list[dict] = []
        self.validated_at_step = -1

    # ------------------------------------------------------------------ pieces
    @torch.no_grad()
    def gbuffers(self, batch: dict) -> dict:
        if self.material is None:
            gb = {k: batch[k] for k in ("albedo", "normal", "material")}
            depth = batch["depth"][:, 0]
        else:
            self.material.eval()
            pred = self.material(batch["im"])
            gb = {k: pred[k] for k in ("albedo", "normal", "material")}
            depth = pred["depth"][:, 0] * self.depth_scale
        gb["depth"] = torch.where(batch["mask"][:, 0], depth, torch.zeros_like(depth))
        return gb

    @staticmethod
    def fov(batch: dict) -> torch.Tensor:
        """(B,) horizontal FOV of each view, degrees (views of a batch may differ)."""
        return batch["fov_x_deg"].float()

    def render(self, ctx, gb, batch, fov, pixels: torch.Tensor, spp: int, generator):
        """Re-render flat pixel indices (M,) with LightNet light -> (rgb (M, 3), input (M, 3), image (M,))."""

        def radiance(idx, origin, wi, image):
            return self.net(ctx, gb, fov, origin, wi, image, generator)["radiance"]

        return render_pixels(gb, batch["im"], fov, pixels, radiance, spp, generator)

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

    # ------------------------------------------------------------------ Lightning
    def training_step(self, batch, batch_idx):
        fov = self.fov(batch)
        gb = self.gbuffers(batch)
        ctx = self.net.encode(batch["im"], gb["depth"], fov)
        scale = ctx["scale"]
        losses = {}
        rays = []
        for kind, n in (("surf", self.probes), ("free", self.free_probes)):
            r = probe_rays(batch["light"], kind, n, self.texels, self.generator, self.device)
            if r is not None:
                rays.append(r)
        if rays:
            o, d, target, bidx, _ = (torch.cat(x) for x in zip(*rays, strict=True))
            pred = self.net(ctx, gb, fov, o, d, bidx, self.generator)["radiance"]
            losses["light"] = relative_mse(pred, target, scale=scale[bidx])
        pix = self.sample_pixels(batch["mask"][:, 0], self.pixels)
        rgb, target, b = self.render(ctx, gb, batch, fov, pix, self.spp, self.generator)
        losses["render"] = (((rgb - target) / scale[b, None]) ** 2).mean()
        total = losses.get("light", 0.0) + self.render_weight * losses["render"]
        bs = batch["im"].shape[0]
        self.log("train/loss", total, prog_bar=True, on_step=True, on_epoch=True, batch_size=bs)
        for k, v in losses.items():
            self.log(f"train/loss_{k}", v, on_step=False, on_epoch=True, batch_size=bs)
        return total

    @torch.no_grad()
    def evaluate_batch(self, batch) -> dict[str, float]:
        """Light errors at every probe texel (surface and free separately) and the re-render PSNR / relative
        MSE on the stride grid of valid pixels at eval_spp (fixed generator: comparable across runs)."""
        gen = torch.Generator().manual_seed(1234)
        fov = self.fov(batch)
        gb = self.gbuffers(batch)
        ctx = self.net.encode(batch["im"], gb["depth"], fov)
        out = {}
        for kind in ("surf", "free"):
            r = probe_rays(batch["light"], kind, None, None, gen, self.device)
            if r is None:
                continue
            o, d, target, bidx, _ = r
            chunks = [
                self.net(ctx, gb, fov, o[i : i + 8192], d[i : i + 8192], bidx[i : i + 8192], gen)
                for i in range(0, len(o), 8192)
            ]
            pred = torch.cat([c["radiance"] for c in chunks])
            s = ctx["scale"][bidx]
            out[f"{kind}_light_relmse"] = float(relative_mse_metric(pred, target, s))
            out[f"{kind}_light_nmse"] = float(normalised_mse(pred, target))
            out[f"{kind}_light_log_l1"] = float(log_l1(pred, target, s))
            hit, u = torch.cat([c["hit"] for c in chunks]), torch.cat([c["u"] for c in chunks])
            for name, sel in ray_classes(hit, u).items():
                out[f"{kind}_rays_{name}"] = float(sel.float().mean())
                if sel.any():  # a batch without such rays adds nothing to that class's mean
                    out[f"{kind}_light_relmse_{name}"] = float(relative_mse_metric(pred[sel], target[sel], s[sel]))
                    out[f"{kind}_light_log_l1_{name}"] = float(log_l1(pred[sel], target[sel], s[sel]))
        pix = grid_pixels(batch["mask"][:, 0], self.eval_stride)
        rgb, target, b = self.render(ctx, gb, batch, fov, pix, self.eval_spp, gen)
        out["render_psnr"] = float(psnr_tonemapped(rgb, target, ctx["scale"][b]))
        out["render_relmse"] = float((((rgb - target) / (target.abs() + 1e-2 * ctx["scale"][b, None])) ** 2).mean())
        return out

    def validation_step(self, batch, batch_idx):
        for k, v in self.evaluate_batch(batch).items():
            self.log(f"val/{k}", v, batch_size=batch["im"].shape[0])

    def on_validation_epoch_end(self):
        if not self.trainer.sanity_checking:
            self.validated_at_step = self.global_step  # lets the stage reuse the final epoch's validation

    def test_step(self, batch, batch_idx):
        row = self.evaluate_batch(batch)
        self.eval_rows.append(row)
        for k, v in row.items():
            self.log(f"test/{k}", v, batch_size=batch["im"].shape[0])

    def configure_optimizers(self):
        return self.optimizer_fn(self.net.parameters())
