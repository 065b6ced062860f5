"""`python -m pipeline.bench.insertion`: what an object insertion costs and what its sample count buys.

1. Seconds per insertion (`invrender insert` without file I/O: MaterialNet, LightNet's encoders, the
   object's G-buffer and its pixels rendered through the MC layer under LightNet) at 160x120 and 320x240
   against spp, with and without its shadows on the room (`models.shadows`, at the same spp), on a test
   photo (upsampled for 320x240, the object covering the same share of the view).
2. Accuracy against spp on the `edit` stage's test insertion cases: LightNet's render of each object
   against the Mitsuba ground truth (PSNR, log-L1 on the object's pixels), every spp on the same cases
   and seed, beside the seconds that spp takes per case.
Needs the trained exports and `synthesize`'s cases (`dvc repro edit`). Writes reports/bench/insertion.json
(or `--out`) and a PNG: seconds against spp, and PSNR against seconds per insertion, one point per spp;
`--only speed` or `--only accuracy` runs one part.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure
from matplotlib.ticker import NullFormatter
from tqdm import tqdm

from pipeline.bench.common import median_seconds, write_report
from pipeline.data import cases as case_io
from pipeline.metrics.insertion import case_scores
from pipeline.models.insertion import (
    InsertedObject,
    composite_gbuffer,
    insert_into,
    light_net_radiance,
    prepare_view,
    render_case,
)
from pipeline.models.light_net import load_light_export
from pipeline.models.material_net import load_material_export
from pipeline.models.render_layer import MCRenderLayer

SPP = (1, 2, 4, 8, 16, 32, 64)
PARTS = ("speed", "accuracy")


def speed(root, material, light, resolutions, spps, repeats: int) -> list[dict]:
    """Seconds per insertion of a mirror sphere at the centre of the first test photo, without and with
    its shadows."""
    scene, view = case_io.case_views(root, "test")[0]
    maps, _, camera = case_io.read_case_view(root, scene, view, "test")
    im, fov = maps["im"], float(camera["fov_x_deg"])
    rows = []
    for H, W in resolutions:
        x = torch.from_numpy(np.ascontiguousarray(im)).permute(2, 0, 1)[None]
        photo = torch.nn.functional.interpolate(x, size=(H, W), mode="bilinear", align_corners=False)[0]
        photo = np.ascontiguousarray(photo.permute(1, 2, 0).numpy())
        for shadows in (False, True):
            for spp in spps:
                pixels = {}

                def insert(photo=photo, H=H, W=W, spp=spp, pixels=pixels, shadows=shadows):
                    prepared = prepare_view(photo, *material, light, fov)
                    _, pix = insert_into(prepared, [InsertedObject("sphere", H // 2, W // 2)], spp, 0, shadows)
                    pixels["n"] = len(pix)

                rows.append(
                    {
                        "height": H,
                        "width": W,
                        "shadows": shadows,
                        "spp": spp,
                        "seconds_per_insertion": median_seconds(insert, repeats),
                        "object_pixels": pixels["n"],
                    }
                )
    return rows


def accuracy(root, material, light, spps) -> dict:
    """Mean PSNR / log-L1 of LightNet's object renders against Mitsuba over the test insertion cases, and
    the render seconds per case, per spp (same cases, same seed)."""
    per_spp = {s: {"psnr": [], "log_l1": [], "seconds": 0.0} for s in spps}
    for scene, view in tqdm(case_io.case_views(root, "test"), desc="insertion accuracy", unit="view"):
        maps, cases, camera = case_io.read_case_view(root, scene, view, "test")
        objects = [c for c in cases if c.kind == "object"]
        v = prepare_view(maps["im"], *material, light, float(camera["fov_x_deg"]), mask=maps["mask"][..., 0] > 0.5)
        pred, fov, scale = v.pred, v.fov, float(v.scale)
        for c in objects:
            shading = composite_gbuffer(
                pred, c.pixel, albedo=c.albedo, material=c.material, normal=c.normal, depth=c.depth
            )
            for s in spps:
                t0 = time.perf_counter()
                light_fn = light_net_radiance(v.net, v.ctx_pred, pred, fov, 0)  # afresh: each spp on the same seed
                with torch.no_grad():
                    rgb = render_case(MCRenderLayer(spp=s), shading, fov, c.pixel, light_fn, 0)
                per_spp[s]["seconds"] += time.perf_counter() - t0
                sc = case_scores(rgb, c.radiance, v.photo, c.pixel, scale)
                per_spp[s]["psnr"].append(sc["psnr"])
                per_spp[s]["log_l1"].append(sc["log_l1"])
    n = len(per_spp[spps[0]]["psnr"])
    return {
        "cases": n,
        "rows": [
            {
                "spp": s,
                "psnr": float(np.mean(v["psnr"])),
                "psnr_sem": float(np.std(v["psnr"], ddof=1) / np.sqrt(n)) if n > 1 else float("nan"),
                "log_l1": float(np.mean(v["log_l1"])),
                "render_seconds_per_case": v["seconds"] / max(n, 1),
            }
            for s, v in per_spp.items()
        ],
    }


def run(
    root="outputs/synthesize",
    material_path="outputs/train_material/model.pt",
    light_path="outputs/train_lighting/model.pt",
    repeats: int = 3,
    parts: tuple = PARTS,
    resolutions: tuple = ((120, 160), (240, 320)),
    speed_spp: tuple = (4, 16, 64),
    accuracy_spp: tuple = SPP,
) -> dict:
    unknown = sorted(set(parts) - set(PARTS))
    if unknown or not parts:
        raise ValueError(f"--only {unknown or list(parts)}: choose among {list(PARTS)}")
    root = Path(root)
    material = load_material_export(material_path)
    light, _ = load_light_export(light_path)
    light.eval()
    report = {"threads": torch.get_num_threads()}
    if "speed" in parts:
        report["speed"] = speed(root, material, light, resolutions, speed_spp, repeats)
    if "accuracy" in parts:
        report["accuracy"] = accuracy(root, material, light, accuracy_spp)
    return report


def plot(report: dict, path) -> None:
    fig = Figure(figsize=(9, 3.4))
    axes = fig.subplots(1, 2)
    speed_rows = report.get("speed", [])
    for H, W in sorted({(r["height"], r["width"]) for r in speed_rows}):
        for shadows in (False, True):
            rs = [r for r in speed_rows if r["height"] == H and bool(r.get("shadows")) == shadows]
            label, style = (f"{W}x{H}, with shadows", "s--") if shadows else (f"{W}x{H}", "o-")
            if rs:
                axes[0].plot([r["spp"] for r in rs], [r["seconds_per_insertion"] for r in rs], style, label=label)
    axes[0].set_xscale("log", base=2)
    axes[0].set_xlabel("samples per pixel")
    axes[0].set_ylabel("seconds per insertion (median)")
    if speed_rows:
        axes[0].legend(fontsize=7)
    if "accuracy" not in report:
        axes[1].set_axis_off()
        fig.tight_layout()
        fig.savefig(path, dpi=120)
        return
    acc = report["accuracy"]["rows"]
    ax = axes[1]
    ax.errorbar(
        [r["render_seconds_per_case"] for r in acc],
        [r["psnr"] for r in acc],
        yerr=[r["psnr_sem"] for r in acc],
        fmt="o-",
    )
    for r in acc:
        ax.annotate(f"{r['spp']} spp", (r["render_seconds_per_case"], r["psnr"]), fontsize=7)
    ax.set_xscale("log")
    ax.xaxis.set_minor_formatter(NullFormatter())  # minor labels collide on a span under one decade
    ax.set_xlabel("render seconds per object (160x120)")
    ax.set_ylabel(f"PSNR vs Mitsuba (dB, {report['accuracy']['cases']} test objects)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--root", default="outputs/synthesize")
    p.add_argument("--material", default="outputs/train_material/model.pt")
    p.add_argument("--light", default="outputs/train_lighting/model.pt")
    p.add_argument("--only", nargs="+", choices=PARTS, default=list(PARTS), help="the parts to run")
    p.add_argument("--out", default=None, help="the JSON (default reports/bench/insertion.json)")
    a = p.parse_args(argv)
    report = run(a.root, a.material, a.light, a.repeats, tuple(a.only))
    path = write_report("insertion", report, path=a.out)
    plot(report, path.with_suffix(".png"))
    print(path)


if __name__ == "__main__":
    main()
