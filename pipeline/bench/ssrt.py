"""`python -m pipeline.bench.ssrt`: rays per second and hit quality of screen-space ray tracing.

Analytic box room (exact first hits), 16 cosine rays per valid pixel, at 160x120 and 320x240, for
several traversal settings (max pyramid level: 0 is a pixel-by-pixel march, None the full hierarchy).
Writes reports/bench/ssrt.json and reports/bench/ssrt.png.
"""

from __future__ import annotations

import argparse
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from tqdm import tqdm  # noqa: E402

from pipeline.bench.common import median_seconds, publish  # noqa: E402
from pipeline.bench.scenes import BoxRoom, score_ssrt, ssrt_rays  # noqa: E402
from pipeline.ops import ssrt  # noqa: E402

REFERENCE = {
    "note": "the paper's released SSRT code on the same analytic room at 160x120, FOV 85, 16 rays/px, "
    "measured on this 2-core CPU",
    "rays_per_second": 47_000,
    "precision": 0.845,
    "recall": 0.926,
}


def run(
    resolutions=((120, 160), (240, 320)),
    levels=(0, 2, 4, None),
    fov=85.0,
    rays_per_pixel=16,
    repeats=3,
    device="cpu",
    compiled=(False, True),
) -> dict:
    scene = BoxRoom.default()
    rows = []
    # the full hierarchy also as one compiled, fused step kernel (torch.compile); its one-off compile
    # time is reported separately and is not in the median
    jobs = [(hw, lv, False) for hw in resolutions for lv in levels if False in compiled]
    jobs += [(hw, None, True) for hw in resolutions if True in compiled]
    for (H, W), level, compiled in tqdm(jobs, desc="ssrt bench"):
        depth, normal = scene.render(H, W, fov)
        o, wi = ssrt_rays(depth, normal, fov, rays_per_pixel, torch.Generator().manual_seed(0))
        args = (depth.float().to(device), normal.float().to(device), fov, o.float().to(device), wi.float().to(device))
        t0 = time.perf_counter()
        pix, hit, gap = (t.cpu() for t in ssrt.trace(*args, max_level=level, compiled=compiled))
        first = time.perf_counter() - t0
        sec = median_seconds(lambda a=args, lv=level, c=compiled: ssrt.trace(*a, max_level=lv, compiled=c), repeats)
        score = score_ssrt(scene, depth, normal, fov, o, wi, pix, hit, gap)
        rows.append(
            {
                "height": H,
                "width": W,
                "max_level": level,
                "compiled": compiled,
                "seconds": sec,
                "first_call_seconds": first,
                "rays_per_second": len(o) / sec,
                **score,
            }
        )
    summary = {}
    for compiled in (False, True):
        full = [r for r in rows if r["max_level"] is None and r["height"] == 120 and r["compiled"] == compiled]
        if full:
            key = "speedup_vs_reference_160x120" + ("_compiled" if compiled else "")
            summary[key] = full[0]["rays_per_second"] / REFERENCE["rays_per_second"]
    return {
        "fov_x_deg": fov,
        "rays_per_pixel": rays_per_pixel,
        "device": device,
        "reference": REFERENCE,
        "results": rows,
        "summary": summary,
    }


def plot(report: dict, path) -> None:
    fig, ax = plt.subplots(figsize=(5, 3.2))
    for H, W in sorted({(r["height"], r["width"]) for r in report["results"]}):
        rs = [r for r in report["results"] if r["height"] == H and not r.get("compiled")]
        labels = [str(r["max_level"]) if r["max_level"] is not None else "full" for r in rs]
        line = ax.plot(labels, [r["rays_per_second"] / 1e3 for r in rs], "o-", label=f"{W}x{H}")[0]
        for r in report["results"]:
            if r["height"] == H and r.get("compiled"):
                ax.plot(["full"], [r["rays_per_second"] / 1e3], "*", ms=12, color=line.get_color())
    ax.axhline(REFERENCE["rays_per_second"] / 1e3, color="gray", ls="--", label="reference code, 160x120")
    ax.set_xlabel("max pyramid level (0 = pixel march; star: compiled kernel)")
    ax.set_ylabel("thousand rays / s")
    ax.set_yscale("log")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--device", default="cpu")
    p.add_argument("--repeats", type=int, default=3)
    a = p.parse_args(argv)
    report = run(repeats=a.repeats, device=a.device)
    path = publish("ssrt", report, plot)
    for r in report["results"]:
        print(
            f"{r['width']}x{r['height']} level={r['max_level']} compiled={r['compiled']}: "
            f"{r['rays_per_second']:,.0f} rays/s "
            f"recall {r['recall']:.3f} precision {r['precision']:.3f} confident {r['precision_confident']:.3f}"
        )
    print(path)


if __name__ == "__main__":
    main()
