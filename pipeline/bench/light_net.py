"""`python -m pipeline.bench.light_net`: LightNet speed per branch and mode, and what the out-of-view
query threshold saves.

1. Queries per second of the local branch, the out-of-view branch and each mode (SSRT included) of the
   profile's LightNet (`--profile`, default tiny: its branches, volume samples and bounds) on the
   analytic box room with random G-buffers, and the full-frame re-render time (MC layer, 16 spp, every
   valid pixel) at 160x120 and 320x240 per setting (`RERENDER_SETTINGS`: unchunked branches, the default,
   a compiled SSRT kernel, out-of-view thresholds), side by side on the same scene and samples.
2. With the trained model (outputs/train_lighting/model.pt, when present) on the test views: re-render
   PSNR, light errors and the fraction of out-of-view queries for several thresholds (0 = the paper's
   evaluate-everything).
3. The generated (hypernetwork) MLP evaluated per scene as dense matrix products (`HyperMLP.run_generated`)
   against gathering a weight matrix per point, forward + backward, side by side.
Writes reports/bench/light_net.json and a PNG.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from matplotlib.figure import Figure
from tqdm import tqdm

from pipeline.bench.common import median_seconds, publish
from pipeline.bench.scenes import BoxRoom, ssrt_rays
from pipeline.models.light_net import MODES, LightNet
from pipeline.models.light_net.hyper import HyperMLP
from pipeline.models.render_layer import MCRenderLayer
from pipeline.ops.encodings import fourier_dim

SETTING_KEYS = ("mode", "ssrt_compiled", "out_threshold")  # what each timed setting chooses itself


def profile_sizes(profile: str = "tiny") -> dict:
    """The profile's LightNet options (`train_lighting`'s `model.light_net`: branches, volume samples and
    bounds) without the keys each timed setting sets (`SETTING_KEYS`)."""
    from omegaconf import OmegaConf

    from pipeline.bench.common import compose

    options = OmegaConf.to_container(compose("train_lighting", [f"profile={profile}"]).model.light_net, resolve=True)
    return {k: v for k, v in options.items() if k not in SETTING_KEYS}


def _scene(H: int, W: int, fov: float = 85.0, rays_per_pixel: int = 1):
    room = BoxRoom.default(torch.float32)
    depth, normal = room.render(H, W, fov)
    g = torch.Generator().manual_seed(0)
    gb = {
        "depth": depth.float(),
        "normal": normal.float(),
        "albedo": torch.rand(1, 3, H, W, generator=g),
        "material": torch.rand(1, 2, H, W, generator=g),
    }
    o, wi = ssrt_rays(depth, normal, fov, rays_per_pixel, g)
    return gb, torch.rand(1, 3, H, W, generator=g) * 3, fov, o.float(), wi.float()


@torch.no_grad()
def speed(resolutions, repeats: int, sizes: dict) -> list[dict]:
    rows = tqdm(resolutions, desc="light_net speed")
    return [_mode_row(mode, H, W, repeats, sizes) for H, W in rows for mode in MODES]


def _mode_row(mode: str, H: int, W: int, repeats: int, sizes: dict) -> dict:
    from pipeline.models.light_net import _gbuffer_at, trace_views

    gb, im, fov, o, wi = _scene(H, W)
    bidx = torch.zeros(len(o), dtype=torch.long)
    torch.manual_seed(0)
    net = LightNet(mode=mode, **sizes).eval()
    ctx = net.encode(im, gb["depth"], fov, normal=gb["normal"])
    sec = median_seconds(lambda: net(ctx, gb, fov, o, wi, bidx), repeats)
    row = {"height": H, "width": W, "mode": mode, "rays": len(o), "queries_per_second": len(o) / sec}
    if mode != "mixed":
        return row
    # per branch, on the same rays
    pixel, hit, _ = trace_views(gb, fov, o, wi, bidx)
    h = torch.nonzero(hit).squeeze(-1)
    gbh = _gbuffer_at(gb, bidx[h], pixel[h])
    t_local = median_seconds(
        lambda: net.local.query(ctx["local"], ctx["unit"], bidx[h], pixel[h], (H, W), wi[h], gbh, ctx["image"]),
        repeats,
    )
    t_out = median_seconds(
        lambda: net.out_of_view_radiance(ctx, bidx, o, wi),
        repeats,
    )
    row["local_queries_per_second"] = len(h) / t_local
    row["out_of_view_queries_per_second"] = len(o) / t_out
    return row


# Full-frame re-render settings, timed side by side: `unchunked` runs each branch over all rays at once
# (as before the branches were chunked), `default` chunked as the stages run them (eager SSRT, every ray
# queried out of view, as the paper); `compiled_ssrt+threshold_0.9` is what `tiny` runs.
RERENDER_SETTINGS = (
    {"name": "unchunked", "chunked": False},
    {"name": "default"},
    {"name": "compiled_ssrt", "ssrt_compiled": True},
    {"name": "threshold_0.5", "out_threshold": 0.5},
    {"name": "threshold_0.9", "out_threshold": 0.9},
    {"name": "compiled_ssrt+threshold_0.5", "ssrt_compiled": True, "out_threshold": 0.5},
    {"name": "compiled_ssrt+threshold_0.9", "ssrt_compiled": True, "out_threshold": 0.9},
)


@torch.no_grad()
def rerender(H: int, W: int, repeats: int, sizes: dict, spp: int = 16) -> list[dict]:
    """Seconds of the full-frame re-render (every valid pixel, `spp` importance samples through the MC
    layer, LightNet `mixed` as the incident radiance) per setting, on the same scene, weights and sample
    directions. The change each setting makes to the image is its relMSE against `default` (the
    network is untrained here: the trained model's accuracy per threshold is in `thresholds`); the SSRT
    compile time is reported apart (once per process)."""
    from pipeline.models.light_net import branches

    gb, im, fov, _, _ = _scene(H, W)
    pixels = torch.nonzero((gb["depth"] > 0).reshape(-1)).squeeze(-1)
    layer = MCRenderLayer("importance", spp=spp)
    rows, images = [], {}
    for setting in tqdm(RERENDER_SETTINGS, desc=f"re-render {W}x{H}"):
        torch.manual_seed(0)
        net = LightNet(
            mode="mixed",
            ssrt_compiled=setting.get("ssrt_compiled", False),
            out_threshold=setting.get("out_threshold", 0.0),
            **sizes,
        ).eval()
        ctx = net.encode(im, gb["depth"], fov, normal=gb["normal"])
        counting = {"out": 0, "rays": 0}

        def radiance(k, o, d, b, net=net, ctx=ctx, counting=counting):
            out = net(ctx, gb, fov, o, d, b)
            counting["out"] += out["out_queries"]
            counting["rays"] += len(d)
            return out["radiance"]

        def render(layer=layer, radiance=radiance):
            return layer.render_pixels(gb, fov, pixels, radiance, torch.Generator().manual_seed(0))[0]

        chunks = (branches.RAY_CHUNK, branches.POINT_CHUNK)
        if not setting.get("chunked", True):
            branches.RAY_CHUNK = branches.POINT_CHUNK = 1 << 62
        try:
            t0 = time.perf_counter()
            images[setting["name"]] = render()  # warm-up (and the compile, where asked)
            first = time.perf_counter() - t0
            counting.update(out=0, rays=0)
            seconds = median_seconds(render, repeats, warmup=0)
        finally:
            branches.RAY_CHUNK, branches.POINT_CHUNK = chunks
        rows.append(
            {
                "height": H,
                "width": W,
                "setting": setting["name"],
                "spp": spp,
                "pixels": len(pixels),
                "seconds": seconds,
                "first_call_seconds": first,
                "out_of_view_query_fraction": counting["out"] / max(counting["rays"], 1),
            }
        )
    ref = images["default"]
    for r in rows:
        img = images[r["setting"]]
        r["relmse_vs_default"] = float(((img - ref) ** 2 / (ref**2 + 1e-2)).mean())
        r["max_abs_diff_vs_default"] = float((img - ref).abs().max())
        r["speedup_vs_unchunked"] = rows[0]["seconds"] / r["seconds"]
    return rows


def _gathered_apply(params, x, scene):
    """Reference evaluation: every point gathers its scene's weight matrices (N, out, in)."""
    for k, (w, b) in enumerate(params):
        x = torch.einsum("noi,ni->no", w[scene], x) + b[scene]
        x = torch.relu(x) if k < len(params) - 1 else x
    return x


def hyper_apply(out_of_view: dict, points: int = 65536, scenes: int = 4, repeats: int = 3) -> dict:
    """Forward + backward seconds of the generated NeRF MLP (the sizes of `out_of_view`, a LightNet's
    `out_of_view` options) on `points` samples of `scenes` scenes: grouped (HyperMLP.run_generated) vs
    per-point weight gather, and their ratio."""
    o = out_of_view
    sizes = [fourier_dim(3, o["frequencies"])] + [o["nerf_hidden"]] * o["nerf_layers"] + [4]
    torch.manual_seed(0)
    hyper = HyperMLP(o["feature_dim"], sizes, **o.get("hyper", {}))
    feature = torch.randn(scenes, o["feature_dim"])
    x = torch.randn(points, sizes[0])
    scene = torch.randint(0, scenes, (points,))

    def step(fn):
        fn(hyper(feature), x, scene).square().sum().backward()

    grouped = median_seconds(lambda: step(HyperMLP.run_generated), repeats)
    gathered = median_seconds(lambda: step(_gathered_apply), repeats)
    return {
        "points": points,
        "scenes": scenes,
        "grouped_seconds": grouped,
        "gathered_seconds": gathered,
        "gathered_over_grouped": gathered / grouped,
    }


@torch.no_grad()
def thresholds(model_path: Path, data_dir: str, material_path: Path, values=(0.0, 0.25, 0.5, 0.9)) -> list[dict]:
    """Re-render PSNR, light errors and out-of-view query fraction of the trained model per threshold, on
    the G-buffers it was trained on: the frozen MaterialNet's predictions (`material_path`), as in
    `train_lighting` with gbuffers=predicted."""
    from pipeline.data.datamodules import InteriorVerseDataModule
    from pipeline.models.export import LIGHT_FORMAT, read_export
    from pipeline.models.material_net import load_material_export

    blob = read_export(model_path, LIGHT_FORMAT)
    _, material = load_material_export(material_path)
    dm = InteriorVerseDataModule(data_dir, batch_size=4, lighting=True)
    dm.setup("test")
    return [_threshold_row(t, model_path, blob, material, dm) for t in tqdm(values, desc="out-of-view threshold")]


class _CountingLightNet(LightNet):
    """LightNet that adds up how many rays it saw and how many went to the out-of-view branch."""

    queries = total = 0

    def forward(self, *args, **kwargs):
        out = super().forward(*args, **kwargs)
        self.queries += out["out_queries"]
        self.total += len(out["u"])
        return out


def system_from_export(path, blob: dict, material: dict | None, net_cls=LightNet, **overrides):
    """A LightingSystem in eval mode holding the LightNet exported at `path` (its export dict `blob`, its
    options updated by `overrides`, built as `net_cls`; a mismatch is refused naming the file) on the
    frozen MaterialNet's G-buffers (`material`; None: the views' ground-truth G-buffers), with the render
    settings of conf/render/importance.yaml: the model as `train_lighting` tests it."""
    from pipeline.models.export import build_from_export
    from pipeline.systems.lighting import LightingSystem

    cfg = {**blob["light_net"], **overrides}
    render = {"estimator": "importance", "spp": 8, "eval_spp": 16, "seed": 0}  # conf/render/importance.yaml
    gbuffers = "ground_truth" if material is None else "predicted"
    system = LightingSystem(light_net=cfg, material=material, render=render, gbuffers=gbuffers)
    system.net = build_from_export(path, net_cls, cfg, blob["state_dict"])
    return system.eval()


def evaluation_system(model_path, material_path):
    """`system_from_export` of the LightNet export at model_path and the MaterialNet export at material_path."""
    from pipeline.models.export import LIGHT_FORMAT, read_export
    from pipeline.models.material_net import load_material_export

    _, material = load_material_export(material_path)
    return system_from_export(model_path, read_export(model_path, LIGHT_FORMAT), material)


def _threshold_row(t: float, model_path, blob: dict, material: dict, dm) -> dict:
    system = system_from_export(model_path, blob, material, _CountingLightNet, mode="mixed", out_threshold=t)
    acc = [system.evaluate_batch(batch) for batch in dm.plain_loader("test")]
    row = {k: sum(r[k] for r in acc) / len(acc) for k in acc[0]}
    row.update({"out_threshold": t, "out_of_view_query_fraction": system.net.queries / max(system.net.total, 1)})
    return row


def run(
    resolutions=((120, 160), (240, 320)),
    repeats: int = 3,
    model_path="outputs/train_lighting/model.pt",
    data_dir="outputs/preprocess",
    hyper_points: int = 65536,
    material_path="outputs/train_material/model.pt",
    profile: str = "tiny",
) -> dict:
    sizes = profile_sizes(profile)
    report = {"threads": torch.get_num_threads(), "profile": profile, "sizes": sizes}
    report["speed"] = speed(resolutions, repeats, sizes)
    report["rerender"] = [row for H, W in resolutions for row in rerender(H, W, repeats, sizes)]
    report["hyper_apply"] = hyper_apply(sizes["out_of_view"], hyper_points, repeats=repeats)
    missing = [str(p) for p in (model_path, material_path) if not Path(p).is_file()]
    if not missing:
        report["thresholds"] = thresholds(Path(model_path), data_dir, Path(material_path))
        report["thresholds_model"] = str(model_path)
        report["thresholds_gbuffers"] = f"predicted by {material_path}"
    else:
        report["thresholds"] = []
        report["thresholds_note"] = (
            f"{', '.join(missing)} not found: run `dvc repro train_lighting` for the threshold sweep"
        )
    return report


def plot(report: dict, path) -> None:
    """Three panels: queries/s per mode and resolution; re-render PSNR (dB) against the out-of-view query
    fraction per threshold; full-frame re-render seconds against relMSE to the default setting."""
    fig = Figure(figsize=(14, 3.6))
    axes = fig.subplots(1, 3)
    for H, W in sorted({(r["height"], r["width"]) for r in report["speed"]}):
        rs = [r for r in report["speed"] if r["height"] == H]
        axes[0].bar([f"{r['mode']}\n{W}x{H}" for r in rs], [r["queries_per_second"] / 1e3 for r in rs])
    axes[0].set_ylabel("thousand queries / s")
    axes[0].tick_params(axis="x", labelsize=6)
    th = report.get("thresholds") or []
    if th:
        ax = axes[1]
        ax.plot([r["out_of_view_query_fraction"] for r in th], [r["render_psnr"] for r in th], "o-")
        for r in th:
            ax.annotate(f"t={r['out_threshold']}", (r["out_of_view_query_fraction"], r["render_psnr"]), fontsize=7)
        ax.set_xlabel("fraction of rays sent to the out-of-view branch")
        ax.set_ylabel("re-render PSNR (dB)")
    else:
        axes[1].axis("off")
        axes[1].text(
            0.5,
            0.5,
            report.get("thresholds_note", "no threshold sweep"),
            ha="center",
            va="center",
            wrap=True,
            fontsize=8,
        )
    ax = axes[2]
    rr = report.get("rerender") or []
    for H, W in sorted({(r["height"], r["width"]) for r in rr}):
        rs = [r for r in rr if r["height"] == H]
        ax.plot([r["seconds"] for r in rs], [r["relmse_vs_default"] for r in rs], "o", label=f"{W}x{H}")
        for r in rs:
            ax.annotate(r["setting"], (r["seconds"], r["relmse_vs_default"]), fontsize=6, rotation=20)
    if rr:
        ax.set_xscale("log")
        ax.set_xlabel("full-frame re-render, 16 spp (s, median)")
        ax.set_ylabel("relMSE against default (untrained net)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--model", default="outputs/train_lighting/model.pt")
    p.add_argument("--data-dir", default="outputs/preprocess")
    p.add_argument("--material", default="outputs/train_material/model.pt", help="MaterialNet export (G-buffers)")
    p.add_argument("--profile", default="tiny", help="whose LightNet options are timed")
    a = p.parse_args(argv)
    report = run(
        repeats=a.repeats, model_path=a.model, data_dir=a.data_dir, material_path=a.material, profile=a.profile
    )
    print(publish("light_net", report, plot))


if __name__ == "__main__":
    main()
