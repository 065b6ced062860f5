"""`python -m pipeline.bench.render_layer`: speed vs accuracy of every render-layer estimator.

A 160x120 view of the analytic box room (exact normals) with a material pattern of glossy (roughness
0.05-0.25, half of them metal) and rough (0.5-1) blocks, lit by an analytic HDR environment (sky gradient
plus a sharp sun lobe). Each estimator and budget renders the frame; its error is the relative MSE
against a 2048-spp importance-sampled reference, separately on glossy and rough pixels; its time is the
median of repeated frames without gradients. Writes reports/bench/render_layer.json and a log-log Pareto
chart reports/bench/render_layer.png.
"""

from __future__ import annotations

import argparse
import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from tqdm import tqdm  # noqa: E402

from pipeline.bench.common import median_seconds, publish  # noqa: E402
from pipeline.bench.scenes import BoxRoom  # noqa: E402
from pipeline.metrics.lighting import relmse_terms  # noqa: E402
from pipeline.models.render_layer import MCRenderLayer  # noqa: E402

SUN = torch.nn.functional.normalize(torch.tensor([0.4, 0.6, 0.3]), dim=0)


def environment(wi: torch.Tensor) -> torch.Tensor:
    """Analytic HDR incident radiance (M, 3) for view-space directions: a sky gradient and a sun lobe
    peaking at ~60 (dynamic range ~100:1), smooth enough for a converged reference."""
    up = wi[:, 1:2]
    sky = torch.tensor([0.6, 0.7, 1.0]) * (0.6 + 0.4 * up) + torch.tensor([0.25, 0.2, 0.15]) * (up < 0)
    sun = 60.0 * torch.exp(((wi @ SUN.to(wi.dtype))[:, None] - 1) / 0.01) * torch.tensor([1.0, 0.9, 0.75])
    return sky.to(wi.dtype) + sun.to(wi.dtype)


def bench_view(height=120, width=160, fov=85.0):
    depth, normal = BoxRoom.default(torch.float32).render(height, width, fov)
    i, j = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    block = ((i // 8) + (j // 8)) % 2 == 0
    g = torch.Generator().manual_seed(0)
    r_glossy = 0.05 + 0.2 * torch.rand(height, width, generator=g)
    r_rough = 0.5 + 0.5 * torch.rand(height, width, generator=g)
    rough = torch.where(block, r_glossy, r_rough)[None, None]
    metal = (block & ((i // 16) % 2 == 0)).float()[None, None]
    albedo = 0.2 + 0.7 * torch.rand(1, 3, height, width, generator=g)
    mask = torch.ones(1, 1, height, width)
    return {"normal": normal.float(), "albedo": albedo, "roughness": rough, "metallic": metal, "mask": mask, "fov": fov}


def render(view, layer, seed=0):
    with torch.no_grad():
        return layer(
            view["normal"],
            view["albedo"],
            view["roughness"],
            view["metallic"],
            view["mask"],
            view["fov"],
            lambda k, wi: environment(wi),
            torch.Generator().manual_seed(seed),
        )["rgb"]


ADAPTIVE_NOTE = (
    "Lobe-driven allocation (mc.allocate_samples) gives glossy pixels up to 8x the samples of rough ones. With "
    "BRDF importance sampling the samples already follow the lobe, so a glossy pixel's per-sample variance is "
    "not larger than a rough one's (here it is smaller: a narrow lobe sees little of the sky's variation), and "
    "the moved samples only starve rough pixels: ratios > 1 for importance. With uniform sampling, which "
    "ignores the lobe, the same allocation lowers the glossy error (ratios < 1 from 16 spp). Hence "
    "render.adaptive=false by default."
)


def rel_mse(x, ref, sel) -> float:
    """relMSE (`metrics.lighting.relmse_terms`, absolute units: the environment is ~1) over the pixels sel."""
    e = relmse_terms(x, ref).mean(1)[0]
    return float(e[sel].mean())


def configs(quick: bool):
    spps = (1, 4, 16, 64) if quick else (1, 4, 16, 64, 256)
    li = ((8, 16), (16, 32)) if quick else ((8, 16), (16, 32), (32, 64))
    out = [("importance", s, False, None) for s in spps] + [("uniform", s, False, None) for s in spps]
    out += [("adaptive", s, True, None) for s in spps if s >= 4]
    out += [("adaptive_uniform", s, True, None) for s in spps if s >= 4]
    out += [("li2020", n_th * n_ph, False, (n_th, n_ph)) for n_th, n_ph in li]
    return out


def equal_time_ratio(rows, group: str) -> list[dict]:
    """Error of each li2020 setting over the importance error at the same time (log-log interpolation)."""
    imp = sorted((r["seconds"], r[f"relmse_{group}"]) for r in rows if r["estimator"] == "importance")
    t, e = np.log([p[0] for p in imp]), np.log([p[1] for p in imp])
    out = []
    for r in rows:
        if r["estimator"] == "li2020":
            e_imp = float(np.exp(np.interp(math.log(r["seconds"]), t, e)))
            out.append(
                {
                    "li_size": r["li_size"],
                    "seconds": r["seconds"],
                    "li2020_error": r[f"relmse_{group}"],
                    "importance_error_at_equal_time": e_imp,
                    "ratio": r[f"relmse_{group}"] / e_imp,
                    "extrapolated": not (t.min() <= math.log(r["seconds"]) <= t.max()),
                }
            )
    return out


_MEMORY_PROBE = """
import resource, sys, torch
from pipeline.bench.render_layer import bench_view, environment
from pipeline.models.render_layer import MCRenderLayer
spp, chunk = int(sys.argv[1]), int(sys.argv[2])
view = bench_view()
rough = view["roughness"].clone().requires_grad_()
albedo = view["albedo"].clone().requires_grad_()
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
out = MCRenderLayer("importance", spp=spp, chunk=chunk)(view["normal"], albedo, rough, view["metallic"],
    view["mask"], view["fov"], lambda k, wi: environment(wi), torch.Generator().manual_seed(0))
out["rgb"].sum().backward()
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before)
"""


def memory_with_gradients(spps=(16, 64, 256), chunk: int = 1 << 16) -> list[dict]:
    """Peak resident memory added by one forward + backward pass (with gradients to roughness and albedo)
    per spp, each in a fresh process: flat in spp when chunking + checkpointing bound it. Large blocks
    are mmap-backed in the probe so freed chunks go back to the OS; otherwise glibc's heap keeps them and
    peak RSS creeps up with the number of chunks although no tensor outlives its chunk."""
    import os
    import subprocess
    import sys

    rows = []
    for spp in spps:
        out = subprocess.run(
            [sys.executable, "-c", _MEMORY_PROBE, str(spp), str(chunk)],
            capture_output=True,
            text=True,
            check=True,
            env={**os.environ, "MALLOC_MMAP_THRESHOLD_": "131072"},
        )
        rows.append(
            {"samples_per_pixel": spp, "chunk": chunk, "peak_rss_increase_mib": int(out.stdout.split()[-1]) / 1024}
        )
    return rows


def adaptive_gain(rows) -> list[dict]:
    """Error of lobe-driven sample allocation over even allocation at the same sample budget."""
    base = {(r["estimator"], r["samples_per_pixel"]): r for r in rows}
    out = []
    for adaptive, even in (("adaptive", "importance"), ("adaptive_uniform", "uniform")):
        for (name, spp), r in base.items():
            if name == adaptive and (even, spp) in base:
                e = base[(even, spp)]
                out.append(
                    {
                        "estimator": even,
                        "samples_per_pixel": spp,
                        **{f"ratio_{g}": r[f"relmse_{g}"] / e[f"relmse_{g}"] for g in ("glossy", "rough")},
                    }
                )
    return out


def run(quick: bool = False, repeats: int = 3, ref_spp: int = 2048, size: tuple[int, int] = (120, 160)) -> dict:
    view = bench_view(*size)
    ref = render(view, MCRenderLayer("importance", spp=ref_spp), seed=123)
    glossy = (view["roughness"][0, 0] < 0.3) & (view["mask"][0, 0] > 0)
    rough = (view["roughness"][0, 0] >= 0.3) & (view["mask"][0, 0] > 0)
    rows = []
    for name, spp, adaptive, li in tqdm(configs(quick), desc="render-layer bench"):
        est = "li2020" if li else {"adaptive": "importance", "adaptive_uniform": "uniform"}.get(name, name)
        layer = MCRenderLayer(est, spp=spp if not li else 1, adaptive=adaptive, li_size=li or (8, 16))
        sec = median_seconds(lambda layer=layer: render(view, layer), repeats, warmup=1 if spp <= 64 else 0)
        img = render(view, layer, seed=1)
        rows.append(
            {
                "estimator": name,
                "samples_per_pixel": spp,
                "li_size": list(li) if li else None,
                "seconds": sec,
                "relmse_glossy": rel_mse(img, ref, glossy),
                "relmse_rough": rel_mse(img, ref, rough),
            }
        )
    ratio = equal_time_ratio(rows, "glossy")
    frame16 = next(r["seconds"] for r in rows if r["estimator"] == "importance" and r["samples_per_pixel"] == 16)
    return {
        "resolution": [120, 160],
        "reference_spp": ref_spp,
        "glossy_pixels": int(glossy.sum()),
        "rough_pixels": int(rough.sum()),
        "results": rows,
        "summary": {
            "li2020_over_importance_glossy_error_at_equal_time": ratio,
            "importance_frame_seconds_at_16spp": frame16,
            "reference_code_frame_seconds_at_16spp": 6.9,
            "adaptive_over_even_error_at_equal_budget": adaptive_gain(rows),
            "adaptive_note": ADAPTIVE_NOTE,
            "memory_with_gradients": memory_with_gradients() if not quick else [],
        },
    }


def plot(report, path) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    style = {"importance": "o-", "uniform": "s--", "adaptive": "^-", "adaptive_uniform": "v--", "li2020": "D:"}
    for ax, group in zip(axes, ("glossy", "rough"), strict=True):
        for name in style:
            rs = sorted((r for r in report["results"] if r["estimator"] == name), key=lambda r: r["seconds"])
            if rs:
                ax.plot([r["seconds"] for r in rs], [r[f"relmse_{group}"] for r in rs], style[name], label=name)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("seconds per 160x120 frame (CPU)")
        ax.set_ylabel("relative MSE vs reference")
        ax.set_title(f"{group} pixels")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--quick", action="store_true", help="fewer budgets (for a smoke run)")
    p.add_argument("--repeats", type=int, default=3)
    a = p.parse_args(argv)
    report = run(a.quick, a.repeats)
    path = publish("render_layer", report, plot)
    for r in report["results"]:
        print(
            f"{r['estimator']:>10} spp={r['samples_per_pixel']:>4} {r['seconds']:.3f}s "
            f"glossy {r['relmse_glossy']:.2e} rough {r['relmse_rough']:.2e}"
        )
    for r in report["summary"]["li2020_over_importance_glossy_error_at_equal_time"]:
        print(f"li2020 {r['li_size']}: {r['ratio']:.1f}x the importance error at equal time")
    print(path)


if __name__ == "__main__":
    main()
