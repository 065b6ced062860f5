"""`python -m pipeline.bench.probe_rerender`: does the render layer, given the true light, give back the image,
and what does the training's re-render loss charge for a sharp light?

At every surface probe of the first `--views` training views (ground-truth G-buffers), with the probe's true
hemisphere of incident light (Mitsuba's, `data.lighting.Probes`):
- quadrature: the reflected radiance of the render layer's BRDF (`ops.brdf.evaluate`: Lambert + GGX)
  summed over the probe's texels, each texel integrated at k x k stratified directions (each texel's
  radiance is its solid-angle mean), over the image's pixel. Also with Burley's diffuse (Mitsuba's
  `principled`) in place of Lambert, to see what the diffuse model costs. Ratios near 1 mean the re-render
  term and the probe term agree on what the light is.
- the training estimator: the render layer at the training samples (`render.spp`, BRDF importance
  sampling) with the probe hemisphere as its light (bilinear lookup), `--renders` independent renders per
  probe. Per probe the squared error (r - pixel)^2 splits in expectation into the squared bias of the
  estimator's mean and its variance; the loss `lighting.render_loss: squared` minimises both, so the
  variance share is what the loss would rather remove by blurring the light (in units of each view's
  image mean, as the loss is).
Writes reports/bench/probe_rerender.json and a PNG (quadrature against pixel; variance against squared
bias per probe).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from matplotlib.figure import Figure
from tqdm import tqdm

from pipeline.bench.common import add_threads_option, apply_threads, publish
from pipeline.data.datasets import ShardDataset
from pipeline.ops import brdf, mc
from pipeline.ops.envmap import hemisphere_lookup, square_centres, texel_solid_angles

ROUGHNESS_BANDS = ((0.0, 0.3), (0.3, 0.6), (0.6, 1.01))


def burley_factor(normal, wo, wi, roughness) -> torch.Tensor:
    """(N,) Burley's retro-reflection factor on the Lambert lobe (Mitsuba's `principled` diffuse, no sheen)."""
    h = torch.nn.functional.normalize(wo + wi, dim=-1)
    cos_d = (wi * h).sum(-1).clamp(0, 1)
    cos_o, cos_i = (normal * wo).sum(-1).clamp(0, 1), (normal * wi).sum(-1).clamp(0, 1)
    fd90 = 0.5 + 2 * roughness * cos_d**2
    return (1 + (fd90 - 1) * (1 - cos_i) ** 5) * (1 + (fd90 - 1) * (1 - cos_o) ** 5)


def view_probes(item: dict) -> dict | None:
    """The G-buffer at each surface probe's pixel (P,): normal (probe's), albedo, roughness, metallic, the
    direction to the camera wo (P, 3), the pixel's radiance (P, 3); None without surface probes."""
    probes = item["light"].surf
    if not len(probes):
        return None
    row, col = probes.pixel[:, 0], probes.pixel[:, 1]
    position = probes.position.double()
    return {
        "probes": probes,
        "normal": torch.nn.functional.normalize(probes.normal.double(), dim=-1),
        "albedo": item["albedo"][:, row, col].T.double(),
        "roughness": item["material"][0, row, col].double(),
        "metallic": item["material"][1, row, col].double(),
        "wo": -position / position.norm(dim=-1, keepdim=True),
        "pixel": item["im"][:, row, col].T.double(),
    }


def quadrature(g: dict, strata: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(Lambert + GGX, Burley + GGX) reflected radiance (P, 3) of the true hemisphere, each texel at strata^2
    stratified directions uniform in its solid angle."""
    probes = g["probes"]
    P, R, C = probes.radiance.shape[:3]
    T = R * C
    probe, texel = torch.arange(P).repeat_interleave(T), torch.arange(T).repeat(P)
    d = probes.texel_directions(probe, texel, square_centres(strata)).double()  # (P T, K, 3)
    K = d.shape[1]
    weight = torch.as_tensor(texel_solid_angles(R, C, True))[texel // C] / K  # (P T,) steradians per direction
    per = lambda x: x[probe].repeat_interleave(K, 0)  # noqa: E731  per probe -> per direction
    n, wo, wi = per(g["normal"]), per(g["wo"]), d.reshape(-1, 3)
    f_d, f_s = brdf.evaluate(n, wo, wi, per(g["albedo"]), per(g["roughness"]), per(g["metallic"]))
    light = probes.radiance.reshape(P * T, 3).double().repeat_interleave(K, 0)
    w = ((n * wi).sum(-1).clamp(min=0) * weight.repeat_interleave(K)).unsqueeze(-1) * light
    total = lambda f: (f * w).reshape(P, T * K, 3).sum(1)  # noqa: E731
    burley = burley_factor(n, wo, wi, per(g["roughness"])).unsqueeze(-1)
    return total(f_d + f_s), total(f_d * burley + f_s)


def estimator_moments(g: dict, spp: int, renders: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and variance (P, 3) over `renders` independent `spp`-sample renders of each probe's pixel under
    its true hemisphere (the training's estimator: `mc.estimate`, BRDF importance sampling, as
    `MCRenderLayer` calls it)."""
    probes = g["probes"]
    P = len(probes)
    normal = g["normal"].float()
    radiance = probes.radiance.float()
    idx = torch.arange(P).repeat(renders)

    def light(k, wi):
        return hemisphere_lookup(radiance, idx[k], normal[idx[k]], wi)

    generator = torch.Generator().manual_seed(seed)
    rep = lambda x: x.float().repeat(renders, *([1] * (x.dim() - 1)))  # noqa: E731
    diffuse, specular = mc.estimate(
        light,
        rep(g["normal"]),
        rep(g["wo"]),
        rep(g["albedo"]),
        rep(g["roughness"]),
        rep(g["metallic"]),
        spp,
        generator,
        "importance",
    )
    r = (diffuse + specular).double().reshape(renders, P, 3)
    return r.mean(0), r.var(0)


def _ratio_summary(pred: np.ndarray, pixel: np.ndarray) -> dict:
    ratio = pred / pixel
    return {
        "ratio_median": float(np.median(ratio)),
        "ratio_p10": float(np.percentile(ratio, 10)),
        "ratio_p90": float(np.percentile(ratio, 90)),
        "pooled_ratio": float(pred.sum() / pixel.sum()),
    }


def run(data_dir: str, views: int, strata: int, spp: int, renders: int, seed: int, min_pixel: float) -> dict:
    data = ShardDataset(data_dir, "train", verify=False)
    if len(data) == 0:
        raise ValueError(f"{data_dir}: the training split has no views")
    rows = []
    for i in tqdm(range(min(views, len(data))), desc="probe re-render", unit="view"):
        item = data[i]
        g = view_probes(item) if "light" in item else None
        if g is None:
            continue
        lambert, burley = quadrature(g, strata)
        mean, var = estimator_moments(g, spp, renders, seed + i)
        scale = float(item["im"].double().mean())  # the loss's unit: the view's image mean
        for p in range(len(g["probes"])):
            rows.append(
                {
                    "view": item["id"],
                    "pixel": float(g["pixel"][p].mean()),
                    "lambert": float(lambert[p].mean()),
                    "burley": float(burley[p].mean()),
                    "roughness": float(g["roughness"][p]),
                    "metallic": float(g["metallic"][p]),
                    "bias2": float((((mean[p] - g["pixel"][p]) / scale) ** 2).mean()),
                    "variance": float((var[p] / scale**2).mean()),
                }
            )
    if not rows:
        raise ValueError(f"{data_dir}: no surface probes in the first {views} training views")
    pixel = np.array([r["pixel"] for r in rows])
    lit = pixel > min_pixel  # a black pixel has no ratio
    out = {"views": len({r["view"] for r in rows}), "probes": len(rows), "probes_scored": int(lit.sum())}
    for name in ("lambert", "burley"):
        pred = np.array([r[name] for r in rows])
        out[name] = _ratio_summary(pred[lit], pixel[lit])
        rough = np.array([r["roughness"] for r in rows])
        out[name]["by_roughness"] = {
            f"[{lo}, {min(hi, 1.0)}]": float(
                np.median(pred[lit & (rough >= lo) & (rough < hi)] / pixel[lit & (rough >= lo) & (rough < hi)])
            )
            for lo, hi in ROUGHNESS_BANDS
            if (lit & (rough >= lo) & (rough < hi)).any()
        }
    bias2, variance = np.array([r["bias2"] for r in rows]), np.array([r["variance"] for r in rows])
    out["estimator"] = {
        "spp": spp,
        "renders": renders,
        "mean_bias2": float(bias2.mean()),
        "mean_variance": float(variance.mean()),
        "median_bias2": float(np.median(bias2)),
        "median_variance": float(np.median(variance)),
        "median_variance_over_bias2": float(np.median(variance / np.maximum(bias2, 1e-12))),
        "variance_share_of_squared_loss": float(variance.sum() / (variance.sum() + bias2.sum())),
        "probes_with_variance_above_bias2": float((variance > bias2).mean()),
    }
    return {
        "settings": {"data_dir": data_dir, "views": views, "strata": strata, "seed": seed, "min_pixel": min_pixel},
        "measured": out,
        "rows": rows,
    }


def plot(report: dict, path) -> None:
    rows = report["rows"]
    fig = Figure(figsize=(10, 4.2))
    ax = fig.add_subplot(1, 2, 1)
    pixel = np.array([r["pixel"] for r in rows])
    for name, colour in (("lambert", "C0"), ("burley", "C1")):
        ax.loglog(pixel, [r[name] for r in rows], ".", ms=2, color=colour, alpha=0.5, label=f"{name} + GGX")
    lo, hi = max(pixel[pixel > 0].min(), 1e-4), pixel.max()
    ax.plot([lo, hi], [lo, hi], "k--", lw=0.8)
    ax.set(xlabel="image pixel (linear)", ylabel="render layer, true probe light", title="quadrature against the image")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(1, 2, 2)
    b2 = np.array([r["bias2"] for r in rows]) + 1e-8
    v = np.array([r["variance"] for r in rows]) + 1e-8
    ax.loglog(b2, v, ".", ms=2, alpha=0.5)
    m = report["measured"]["estimator"]
    ax.plot(
        [min(b2.min(), v.min()), max(b2.max(), v.max())],
        [min(b2.min(), v.min()), max(b2.max(), v.max())],
        "k--",
        lw=0.8,
    )
    ax.set(
        xlabel="squared bias of the estimator's mean",
        ylabel=f"variance of one {m['spp']}-sample render",
        title=f"variance share of the squared loss: {m['variance_share_of_squared_loss']:.2f}",
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data-dir", default="outputs/preprocess")
    p.add_argument("--views", type=int, default=40, help="the first N training views")
    p.add_argument("--strata", type=int, default=4, help="k: k x k directions per texel in the quadrature")
    p.add_argument("--spp", type=int, default=8, help="the training render's samples per pixel (render.spp)")
    p.add_argument("--renders", type=int, default=64, help="independent renders per probe for the moments")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--min-pixel", type=float, default=1e-4, help="pixels at or below this have no ratio")
    p.add_argument("--name", default="probe_rerender")
    add_threads_option(p)
    a = p.parse_args(argv)
    apply_threads(a.threads)
    report = run(a.data_dir, a.views, a.strata, a.spp, a.renders, a.seed, a.min_pixel)
    print(publish(a.name, report, plot))
    m = report["measured"]
    print({k: m[k] for k in ("lambert", "burley", "estimator")})


if __name__ == "__main__":
    main()
