"""`python -m pipeline.bench.render_layer`: speed vs accuracy of every render-layer estimator.

A 160x120 view of the analytic box room (exact normals) with a material pattern of glossy (roughness
0.05-0.25, half of them metal) and rough (0.5-1) blocks, lit by an analytic HDR environment (sky gradient
plus a sharp sun lobe, no occlusion). Each estimator and budget renders the frame; its time is the median
of repeated frames without gradients, its error the relative MSE (`metrics.lighting.relmse_terms`)
against a reference image, on glossy and on rough pixels separately.

The reference comes from an estimator none of the tested ones uses, with its own code and random
numbers (`reference_image`): multiple importance sampling (balance heuristic) of four strategies, one
sample each per round: uniform hemisphere, cosine hemisphere, classic GGX normal-distribution sampling
(not the visible-normal sampling of `importance`) and a von Mises-Fisher lobe around the sun. It shares
only the integrand with them (`ops.brdf.evaluate` and the environment). Its noise is estimated from the
spread of its rounds and reported as the relMSE floor it adds to every error (the tested estimators'
noise is independent of it, so an error near the floor is not resolved).

Writes reports/bench/render_layer.json (`measured`: everything timed or computed in this run; `quoted`:
figures from elsewhere, with their source, from which nothing is derived) and a log-log chart of error
against time per pixel class, reports/bench/render_layer.png.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch
from matplotlib.figure import Figure
from tqdm import tqdm

from pipeline.bench.common import add_threads_option, apply_threads, median_seconds, publish, quoted, threads
from pipeline.bench.scenes import BoxRoom
from pipeline.metrics.lighting import RELMSE_EPS, relmse_terms
from pipeline.models.render_layer import MCRenderLayer
from pipeline.ops import brdf
from pipeline.ops.camera import pixel_directions

SUN = torch.nn.functional.normalize(torch.tensor([0.4, 0.6, 0.3]), dim=0)
SUN_KAPPA = 100.0  # sharpness of the sun lobe, 1 / rad^2 near its centre
SUN_PEAK = 60.0  # radiance at the sun's centre (the sky is ~1)


def environment(wi: torch.Tensor) -> torch.Tensor:
    """Analytic HDR incident radiance (M, 3) for unit view-space directions wi (M, 3): a sky gradient
    (~0.4-1) and a sun lobe SUN_PEAK exp(SUN_KAPPA (cos - 1)) peaking at 60 (dynamic range ~100:1)."""
    up = wi[:, 1:2]
    sky = torch.tensor([0.6, 0.7, 1.0]) * (0.6 + 0.4 * up) + torch.tensor([0.25, 0.2, 0.15]) * (up < 0)
    lobe = torch.exp(SUN_KAPPA * ((wi @ SUN.to(wi.dtype))[:, None] - 1))
    sun = SUN_PEAK * lobe * torch.tensor([1.0, 0.9, 0.75])
    return sky.to(wi.dtype) + sun.to(wi.dtype)


def bench_view(height=120, width=160, fov=85.0):
    """The bench's G-buffers at (height, width), fov degrees: normal (1, 3, H, W), albedo (1, 3, H, W),
    roughness, metallic, mask (1, 1, H, W) and fov."""
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
    """The frame (1, 3, H, W) `layer` renders of `view` under `environment`, without gradients."""
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


# ---- the reference: an estimator none of the tested ones uses ------------------------------------------

REFERENCE_STRATEGIES = ("uniform hemisphere", "cosine hemisphere", "GGX NDF (h ~ D(h) cos)", "sun vMF lobe")


def _frame(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Tangent and bitangent (N, 3) completing unit normals n (N, 3): cross products with the axis least
    aligned with n."""
    axis = torch.zeros_like(n)
    axis[torch.arange(len(n)), n.abs().argmin(-1)] = 1.0
    t = torch.nn.functional.normalize(torch.linalg.cross(n, axis), dim=-1)
    return t, torch.linalg.cross(n, t)


def _around(x, y, z, t, b, n):
    """Local coordinates x, y, z (..., N) in the frames (t, b, n) (N, 3) -> directions (..., N, 3)."""
    return x[..., None] * t + y[..., None] * b + z[..., None] * n


def _reference_round_samples(u, n, t, b, wo, alpha, sun, st, sb):
    """One direction per strategy (S, k, N, 3) from uniform numbers u (k, N, 8) and every strategy's
    solid-angle density at every one of them, summed (S, k, N) (the balance heuristic's denominator)."""
    phi = 2 * math.pi * u[..., 1::2]  # an azimuth per strategy
    cphi, sphi = phi.cos(), phi.sin()
    # uniform hemisphere: z uniform in [0, 1)
    z = u[..., 0]
    s = (1 - z * z).clamp(min=0).sqrt()
    wi_u = _around(s * cphi[..., 0], s * sphi[..., 0], z, t, b, n)
    # cosine hemisphere: radius sqrt(u) on the disc, lifted
    r = u[..., 2].sqrt()
    wi_c = _around(r * cphi[..., 1], r * sphi[..., 1], (1 - u[..., 2]).clamp(min=0).sqrt(), t, b, n)
    # GGX normal distribution: cos^2(theta_h) = (1 - u) / (1 + (alpha^2 - 1) u), then reflect wo about h
    a2 = alpha * alpha
    c2 = ((1 - u[..., 4]) / (1 + (a2 - 1) * u[..., 4])).clamp(0, 1)
    sh = (1 - c2).sqrt()
    h = _around(sh * cphi[..., 2], sh * sphi[..., 2], c2.sqrt(), t, b, n)
    wi_g = 2 * (wo * h).sum(-1, keepdim=True) * h - wo
    # von Mises-Fisher lobe around the sun: cos = 1 + log(u + (1 - u) e^(-2 kappa)) / kappa
    k = SUN_KAPPA
    w = 1 + torch.log(u[..., 6] + (1 - u[..., 6]) * math.exp(-2 * k)) / k
    sw = (1 - w * w).clamp(min=0).sqrt()
    wi_s = _around(sw * cphi[..., 3], sw * sphi[..., 3], w, st, sb, sun.expand_as(st))
    wi = torch.nn.functional.normalize(torch.stack([wi_u, wi_c, wi_g, wi_s]), dim=-1)
    cos_i = (wi * n).sum(-1)
    p_uniform = torch.where(cos_i > 0, 1 / (2 * math.pi), 0.0)
    p_cosine = cos_i.clamp(min=0) / math.pi
    hv = torch.nn.functional.normalize(wi + wo, dim=-1)
    cos_h, cos_oh = (hv * n).sum(-1), (hv * wo).sum(-1)
    ch2 = cos_h.clamp(0, 1) ** 2
    d = a2 / (math.pi * ((1 - ch2) + a2 * ch2) ** 2)
    p_ndf = torch.where((cos_h > 0) & (cos_oh > 0), d * cos_h / (4 * cos_oh.clamp(min=1e-300)), 0.0)
    p_sun = k * torch.exp(k * ((wi * sun).sum(-1) - 1)) / (2 * math.pi * (1 - math.exp(-2 * k)))
    return wi, cos_i, p_uniform + p_cosine + p_ndf + p_sun


@torch.no_grad()
def reference_image(view, rounds: int, seed: int = 7, batch: int = 8, dtype=torch.float64):
    """Reflected radiance of `view` under `environment` by the reference estimator (module docstring):
    `rounds` rounds of one sample per strategy (4 samples per pixel per round), in `dtype`. Returns the
    image (1, 3, H, W) and the variance of its mean per pixel and channel (1, 3, H, W), from the spread
    of the rounds' estimates."""
    if rounds < 2:
        raise ValueError(f"rounds={rounds}: the reference needs at least 2 rounds to estimate its noise")
    H, W = view["normal"].shape[-2:]
    flat = lambda x: x[0].permute(1, 2, 0).reshape(H * W, -1).to(dtype)  # noqa: E731
    keep = flat(view["mask"])[:, 0] > 0.5
    n = torch.nn.functional.normalize(flat(view["normal"]), dim=-1)[keep]
    wo = -torch.nn.functional.normalize(pixel_directions(H, W, view["fov"], dtype=dtype).reshape(-1, 3), dim=-1)[keep]
    albedo = flat(view["albedo"])[keep]
    rough, metal = flat(view["roughness"])[keep, 0], flat(view["metallic"])[keep, 0]
    alpha = brdf.alpha_from_roughness(rough)
    t, b = _frame(n)
    sun = SUN.to(dtype)
    st, sb = (x.expand_as(n) for x in _frame(sun[None]))
    N = len(n)
    gen = torch.Generator().manual_seed(seed)
    total = torch.zeros(N, 3, dtype=dtype)
    total_sq = torch.zeros(N, 3, dtype=dtype)
    for start in range(0, rounds, batch):
        k = min(batch, rounds - start)
        u = torch.rand(k, N, 8, generator=gen, dtype=dtype)
        wi, cos_i, p_sum = _reference_round_samples(u, n, t, b, wo, alpha, sun, st, sb)
        S = wi.shape[0]
        M = S * k * N
        n_, wo_, a_, r_, m_ = (x.expand(S, k, *x.shape).reshape(M, *x.shape[1:]) for x in (n, wo, albedo, rough, metal))
        f_d, f_s = brdf.evaluate(n_, wo_, wi.reshape(M, 3), a_, r_, m_)
        weight = torch.where(p_sum > 0, cos_i.clamp(min=0) / p_sum.clamp(min=1e-300), 0.0).reshape(M, 1)
        per_round = ((f_d + f_s) * environment(wi.reshape(M, 3)) * weight).reshape(S, k, N, 3).sum(0)
        total += per_round.sum(0)
        total_sq += (per_round**2).sum(0)
    mean = total / rounds
    var_of_mean = (total_sq / rounds - mean**2).clamp(min=0) / (rounds - 1)
    image = torch.zeros(H * W, 3, dtype=dtype)
    var = torch.zeros(H * W, 3, dtype=dtype)
    image[keep], var[keep] = mean, var_of_mean
    to_image = lambda x: x.T.reshape(1, 3, H, W)  # noqa: E731
    return to_image(image), to_image(var)


def noise_floor(reference: torch.Tensor, var_of_mean: torch.Tensor, sel: torch.Tensor) -> float:
    """The relMSE the reference's own noise adds to any independent estimate's error over the pixels sel
    (H, W): the mean over sel of var / (ref^2 + eps), averaged over channels as `rel_mse` does."""
    return float((var_of_mean / (reference**2 + RELMSE_EPS)).mean(1)[0][sel].mean())


ADAPTIVE_NOTE = (
    "Lobe-driven allocation (mc.allocate_samples) gives glossy pixels up to 8x the samples of rough ones. With "
    "BRDF importance sampling the samples already follow the lobe, so a glossy pixel's per-sample variance is "
    "not larger than a rough one's (here it is smaller: a narrow lobe sees little of the sky's variation), and "
    "the moved samples only starve rough pixels: ratios > 1 for importance. With uniform sampling, which "
    "ignores the lobe, the same allocation lowers the glossy error (ratios < 1 from 16 spp). Hence "
    "render.adaptive=false by default."
)


GROUPS = ("glossy", "rough")
FLOOR_LIMITED = 2.0  # an error below this many times the reference's noise floor is not resolved


def rel_mse(x, ref, sel) -> float:
    """relMSE (`metrics.lighting.relmse_terms`, absolute units: the environment is ~1) over the pixels sel."""
    e = relmse_terms(x, ref).mean(1)[0]
    return float(e[sel].mean())


def configs(quick: bool):
    """(name, spp, adaptive, li_size) per timed setting; importance also at 1024 spp unless quick, so that
    its times span those of the li2020 grids."""
    spps = (1, 4, 16, 64) if quick else (1, 4, 16, 64, 256)
    li = ((8, 16), (16, 32)) if quick else ((8, 16), (16, 32), (32, 64))
    out = [("importance", s, False, None) for s in spps + (() if quick else (1024,))]
    out += [("uniform", s, False, None) for s in spps]
    out += [("adaptive", s, True, None) for s in spps if s >= 4]
    out += [("adaptive_uniform", s, True, None) for s in spps if s >= 4]
    out += [("li2020", n_th * n_ph, False, (n_th, n_ph)) for n_th, n_ph in li]
    return out


def equal_time_ratio(rows, group: str, estimators=("li2020", "uniform")) -> list[dict]:
    """Error of each row of `estimators` over the importance error at the same time (log-log
    interpolation between the measured importance budgets), on pixel class `group`. Outside the
    measured importance times there is nothing to interpolate: the importance error and the ratio are
    None. `floor_limited` marks a row whose error, or the interpolated importance error, is below
    FLOOR_LIMITED times the reference's noise floor (rows carry it as floor_limited_<group>)."""
    imp = sorted((r for r in rows if r["estimator"] == "importance"), key=lambda r: r["seconds"])
    t = np.log([r["seconds"] for r in imp])
    e = np.log([r[f"relmse_{group}"] for r in imp])
    limited = [bool(r.get(f"floor_limited_{group}", False)) for r in imp]
    out = []
    for r in rows:
        if r["estimator"] not in estimators:
            continue
        lt = math.log(r["seconds"])
        inside = bool(len(t) and t[0] <= lt <= t[-1])
        e_imp, near = None, False
        if inside:
            e_imp = float(np.exp(np.interp(lt, t, e)))
            k = int(np.searchsorted(t, lt))  # imp[k - 1] and imp[k] bracket the time
            near = limited[k] or (k > 0 and limited[k - 1])
        out.append(
            {
                "estimator": r["estimator"],
                "samples_per_pixel": r["samples_per_pixel"],
                "li_size": r["li_size"],
                "seconds": r["seconds"],
                "error": r[f"relmse_{group}"],
                "importance_error_at_equal_time": e_imp,
                "ratio": r[f"relmse_{group}"] / e_imp if inside else None,
                "floor_limited": bool(r.get(f"floor_limited_{group}", False) or near),
            }
        )
    return out


_MEMORY_PROBE = """
import sys, torch
from pipeline.bench.render_layer import bench_view, environment
from pipeline.models.render_layer import MCRenderLayer
def peak_kib():  # this process's own peak RSS: VmHWM, unlike ru_maxrss, does not carry the parent's over exec
    return next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM:"))
spp, chunk = int(sys.argv[1]), int(sys.argv[2])
view = bench_view()
rough = view["roughness"].clone().requires_grad_()
albedo = view["albedo"].clone().requires_grad_()
before = peak_kib()
out = MCRenderLayer("importance", spp=spp, chunk=chunk)(view["normal"], albedo, rough, view["metallic"],
    view["mask"], view["fov"], lambda k, wi: environment(wi), torch.Generator().manual_seed(0))
out["rgb"].sum().backward()
print(peak_kib() - before)
"""


def memory_with_gradients(spps=(16, 64, 256), chunk: int = 1 << 16) -> list[dict]:
    """Peak resident memory (MiB) added by one forward + backward pass (with gradients to roughness and
    albedo) per spp, each in a fresh process (Linux: it reads /proc/self/status): flat in spp when
    chunking + checkpointing bound it. Large blocks are mmap-backed in the probe so freed chunks go back
    to the OS; otherwise glibc's heap keeps them and peak RSS creeps up with the number of chunks
    although no tensor outlives its chunk."""
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


REFERENCE_CODE_SOURCE = (
    "a 160x120 frame at 16 spp by the paper's released render layer (jingsenzhu/IndoorInverseRendering, "
    "lightnet/models/render/layer.py), as written into this bench's source; no script or log of that "
    "timing is in this repository and this bench did not re-run it"
)
QUOTED = {"reference_code_frame_seconds_at_16spp": quoted(6.9, "s", REFERENCE_CODE_SOURCE)}


def run(
    quick: bool = False,
    repeats: int = 3,
    ref_rounds: int = 512,
    size: tuple[int, int] = (120, 160),
    memory: bool | None = None,
) -> dict:
    """Time every configured estimator on the bench view of `size` (H, W) (medians of `repeats` frames) and
    score one frame of each against the reference (`ref_rounds` rounds, 4 samples per pixel each), per
    pixel class; `memory` (default: not quick) adds the peak memory with gradients per spp.
    Returns {"measured": ..., "quoted": QUOTED}."""
    view = bench_view(*size)
    t0 = time.perf_counter()
    ref, ref_var = reference_image(view, ref_rounds)
    ref_seconds = time.perf_counter() - t0
    sel = {
        "glossy": (view["roughness"][0, 0] < 0.3) & (view["mask"][0, 0] > 0),
        "rough": (view["roughness"][0, 0] >= 0.3) & (view["mask"][0, 0] > 0),
    }
    floor = {g: noise_floor(ref, ref_var, sel[g]) for g in GROUPS}
    rows = []
    for name, spp, adaptive, li in tqdm(configs(quick), desc="render-layer bench"):
        est = "li2020" if li else {"adaptive": "importance", "adaptive_uniform": "uniform"}.get(name, name)
        layer = MCRenderLayer(est, spp=spp if not li else 1, adaptive=adaptive, li_size=li or (8, 16))
        sec = median_seconds(lambda layer=layer: render(view, layer), repeats, warmup=1 if spp <= 64 else 0)
        img = render(view, layer, seed=1)
        row = {"estimator": name, "samples_per_pixel": spp, "li_size": list(li) if li else None, "seconds": sec}
        for g in GROUPS:
            row[f"relmse_{g}"] = rel_mse(img, ref, sel[g])
        for g in GROUPS:
            row[f"floor_limited_{g}"] = row[f"relmse_{g}"] < FLOOR_LIMITED * floor[g]
        rows.append(row)
    frame16 = next(r["seconds"] for r in rows if r["estimator"] == "importance" and r["samples_per_pixel"] == 16)
    measured = {
        "device": "cpu",
        "torch_threads": torch.get_num_threads(),
        "resolution": list(size),
        "repeats": repeats,
        "glossy_pixels": int(sel["glossy"].sum()),
        "rough_pixels": int(sel["rough"].sum()),
        "reference_estimator": "multiple importance sampling (balance heuristic), one sample per strategy per "
        "round: " + ", ".join(REFERENCE_STRATEGIES),
        "reference_rounds": ref_rounds,
        "reference_samples_per_pixel": len(REFERENCE_STRATEGIES) * ref_rounds,
        "reference_seconds": ref_seconds,
        "reference_noise_floor_relmse": floor,
        "results": rows,
        "equal_time_vs_importance_glossy": equal_time_ratio(rows, "glossy"),
        "equal_time_vs_importance_rough": equal_time_ratio(rows, "rough"),
        "importance_frame_seconds_at_16spp": frame16,
        "adaptive_over_even_error_at_equal_budget": adaptive_gain(rows),
        "adaptive_note": ADAPTIVE_NOTE,
    }
    if memory if memory is not None else not quick:
        measured["memory_with_gradients"] = memory_with_gradients()
    return {"measured": measured, "quoted": QUOTED}


STYLE = {"importance": "o-", "uniform": "s--", "adaptive": "^-", "adaptive_uniform": "v--", "li2020": "D:"}


def plot(report, path) -> None:
    """Error against time per estimator, glossy and rough pixels side by side (log-log), with the
    reference's noise floor as a dashed line."""
    m = report["measured"]
    H, W = m["resolution"]
    fig = Figure(figsize=(10, 4.2))
    axes = fig.subplots(1, 2)
    for ax, group in zip(axes, GROUPS, strict=True):
        for name, style in STYLE.items():
            rs = sorted((r for r in m["results"] if r["estimator"] == name), key=lambda r: r["seconds"])
            if rs:
                ax.plot([r["seconds"] for r in rs], [r[f"relmse_{group}"] for r in rs], style, label=name)
        floor = m["reference_noise_floor_relmse"][group]
        ax.axhline(floor, color="gray", ls="--", lw=1, label="reference noise floor")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(f"seconds per {W}x{H} frame (median, {m['device']}, {threads(m['torch_threads'])})")
        ax.set_ylabel("relative MSE vs reference (dimensionless)")
        ax.set_title(f"{group} pixels ({m[f'{group}_pixels']})", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(
        f"Render-layer estimators; reference: MIS of 4 strategies, {m['reference_samples_per_pixel']} samples/px",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="fewer budgets, no memory probe (for a smoke run)")
    p.add_argument("--repeats", type=int, default=3)
    add_threads_option(p)
    p.add_argument("--ref-rounds", type=int, default=512, help="reference rounds (4 samples per pixel each)")
    a = p.parse_args(argv)
    apply_threads(a.threads)
    t0 = time.perf_counter()
    report = run(a.quick, a.repeats, a.ref_rounds)
    path = publish("render_layer", report, plot)
    m = report["measured"]
    print(
        f"reference: {m['reference_samples_per_pixel']} samples/px in {m['reference_seconds']:.1f} s, noise floor "
        + ", ".join(f"{g} {v:.2e}" for g, v in m["reference_noise_floor_relmse"].items())
    )
    for r in m["results"]:
        print(
            f"{r['estimator']:>16} spp={r['samples_per_pixel']:>4} {r['seconds']:.3f}s "
            f"glossy {r['relmse_glossy']:.2e} rough {r['relmse_rough']:.2e}"
        )
    for g in GROUPS:
        for r in m[f"equal_time_vs_importance_{g}"]:
            if r["ratio"] is not None:
                print(
                    f"{g}: {r['estimator']} {r['li_size'] or r['samples_per_pixel']}: {r['ratio']:.3g}x the "
                    f"importance error at equal time{' (at the reference floor)' if r['floor_limited'] else ''}"
                )
    print(f"{path} ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
