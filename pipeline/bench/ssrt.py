"""`python -m pipeline.bench.ssrt`: rays per second and hit quality of screen-space ray tracing.

Analytic box room (exact first hits), 16 cosine rays per valid pixel, at 160x120 and 320x240, for
several traversal settings (max pyramid level: 0 is a pixel-by-pixel march, None the full hierarchy).
`--reference PATH` also times and scores another SSRT implementation on the same rays: PATH is a Python
file defining `trace(depth, normal, fov_x, origin, direction) -> (pixel, hit, gap)` with the arguments
and results of `pipeline.ops.ssrt.trace`; speed-ups over it are then measured in the same run. Figures
that were not measured here are under `quoted`, with their source, and nothing is derived from them.
Writes reports/bench/ssrt.json and reports/bench/ssrt.png.
"""

from __future__ import annotations

import argparse
import importlib.util
import time
from pathlib import Path

import torch
from matplotlib.figure import Figure
from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter
from tqdm import tqdm

from pipeline.bench.common import (
    add_threads_option,
    apply_threads,
    device_name,
    median_seconds,
    publish,
    quoted,
    threads,
)
from pipeline.bench.scenes import BoxRoom, score_ssrt, ssrt_rays
from pipeline.ops import ssrt

_QUOTED_SOURCE = (
    "the paper's released SSRT (jingsenzhu/IndoorInverseRendering, lightnet/models/render/ssrt.py) on this "
    "bench's analytic room at 160x120, FOV 85, 16 rays/px, on a 2-core CPU, as written into this bench's "
    "source; no script or log of that run is in this repository and this bench did not re-run it "
    "(`--reference PATH` times a reference implementation in the same run)"
)
QUOTED = {
    "reference_code_rays_per_second_160x120": quoted(47_000, "rays/s", _QUOTED_SOURCE),
    "reference_code_precision_160x120": quoted(0.845, "fraction of reported hits", _QUOTED_SOURCE),
    "reference_code_recall_160x120": quoted(0.926, "fraction of visible true hits", _QUOTED_SOURCE),
}


def load_reference(path: str | Path):
    """The `trace` function of the Python file at `path` (see the module docstring)."""
    path = Path(path)
    spec = importlib.util.spec_from_file_location(f"ssrt_reference_{path.stem}", path)
    if spec is None or spec.loader is None:
        raise ValueError(f"--reference {path}: not a Python file")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    if not callable(getattr(module, "trace", None)):
        raise ValueError(f"--reference {path}: defines no trace(depth, normal, fov_x, origin, direction)")
    return module.trace


def _timed_row(trace, args, repeats: int, scene, depth, normal, fov, o, wi) -> dict:
    """Seconds (median over `repeats` after one untimed call), first-call seconds, rays/s and hit scores of
    `trace(*args)` on the rays o, wi (N, 3)."""
    t0 = time.perf_counter()
    pix, hit, gap = (t.cpu() for t in trace(*args))
    first = time.perf_counter() - t0
    sec = median_seconds(lambda: trace(*args), repeats)
    score = score_ssrt(scene, depth, normal, fov, o, wi, pix, hit, gap)
    return {"seconds": sec, "first_call_seconds": first, "rays_per_second": len(o) / sec, **score}


def run(
    resolutions=((120, 160), (240, 320)),
    levels=(0, 2, 4, None),
    fov=85.0,
    rays_per_pixel=16,
    repeats=3,
    device="cpu",
    compiled=(False, True),
    reference: str | Path | None = None,
    reference_resolutions=((120, 160),),
) -> dict:
    """Time and score `ssrt.trace` per resolution (H, W) and max pyramid level (and, where `compiled`
    holds True, the full hierarchy as one compiled kernel), on `device`; with `reference` (a file path)
    also that file's `trace` at `reference_resolutions`. Returns {"measured": ..., "quoted": QUOTED}."""
    scene = BoxRoom.default()
    reference_trace = load_reference(reference) if reference else None
    rows, reference_rows = [], []
    # the full hierarchy also as one compiled, fused step kernel (torch.compile); its one-off compile
    # time is in first_call_seconds, not in the median
    jobs = [(hw, lv, False) for hw in resolutions for lv in levels if False in compiled]
    jobs += [(hw, None, True) for hw in resolutions if True in compiled]
    jobs += [(hw, "reference", False) for hw in reference_resolutions if reference_trace is not None]
    for (H, W), level, comp in tqdm(jobs, desc="ssrt bench"):
        depth, normal = scene.render(H, W, fov)
        o, wi = ssrt_rays(depth, normal, fov, rays_per_pixel, torch.Generator().manual_seed(0))
        args = (depth.float().to(device), normal.float().to(device), fov, o.float().to(device), wi.float().to(device))
        sample = (scene, depth, normal, fov, o, wi)
        if level == "reference":
            reference_rows.append({"height": H, "width": W, **_timed_row(reference_trace, args, repeats, *sample)})
            continue

        def trace(*a, lv=level, c=comp):
            return ssrt.trace(*a, max_level=lv, compiled=c)

        rows.append(
            {"height": H, "width": W, "max_level": level, "compiled": comp, **_timed_row(trace, args, repeats, *sample)}
        )
    measured = {
        "device": device_name(device),
        "torch_threads": torch.get_num_threads(),
        "fov_x_deg": fov,
        "rays_per_pixel": rays_per_pixel,
        "repeats": repeats,
        "results": rows,
    }
    if reference_trace is not None:
        measured["reference_path"] = str(reference)
        measured["reference_results"] = reference_rows
        measured["speedup_vs_reference"] = speedups(rows, reference_rows)
    return {"measured": measured, "quoted": QUOTED}


def speedups(rows: list[dict], reference_rows: list[dict]) -> list[dict]:
    """Rays/s of each row over the reference's at the same resolution, both timed in this run."""
    ref = {(r["height"], r["width"]): r["rays_per_second"] for r in reference_rows}
    return [
        {
            "height": r["height"],
            "width": r["width"],
            "max_level": r["max_level"],
            "compiled": r["compiled"],
            "speedup": r["rays_per_second"] / ref[(r["height"], r["width"])],
        }
        for r in rows
        if (r["height"], r["width"]) in ref
    ]


def plot(report: dict, path) -> None:
    """Measured rays/s per max pyramid level and resolution (log scale); the quoted reference figure as a
    grey dotted line labelled as quoted, a reference timed in this run as a dashed line."""
    m = report["measured"]
    fig = Figure(figsize=(7.2, 4.2))
    ax = fig.subplots()
    for H, W in sorted({(r["height"], r["width"]) for r in m["results"]}):
        rs = [r for r in m["results"] if r["height"] == H and not r["compiled"]]
        labels = [str(r["max_level"]) if r["max_level"] is not None else "full" for r in rs]
        line = ax.plot(labels, [r["rays_per_second"] / 1e3 for r in rs], "o-", label=f"{W}x{H}")[0]
        for r in m["results"]:
            if r["height"] == H and r["compiled"]:
                ax.plot(["full"], [r["rays_per_second"] / 1e3], "*", ms=12, color=line.get_color())
                ax.plot([], [], "*", ms=9, color=line.get_color(), label=f"{W}x{H}, full, compiled kernel")
        for r in m.get("reference_results", []):
            if r["height"] == H:
                ax.axhline(r["rays_per_second"] / 1e3, color=line.get_color(), ls="--", lw=1)
                ax.plot([], [], "--", color=line.get_color(), label=f"{W}x{H}, reference file (timed here)")
    q = report["quoted"]["reference_code_rays_per_second_160x120"]
    ax.axhline(q["value"] / 1e3, color="gray", ls=":", lw=1.2)
    ax.plot([], [], ":", color="gray", label="160x120, released code: quoted, not timed here")
    ax.set_xlabel("max pyramid level of the traversal (0 = pixel-by-pixel march, full = whole pyramid)")
    ax.set_ylabel("thousand rays / s (median, log scale)")
    ax.set_yscale("log")
    ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    ax.yaxis.set_major_formatter(ScalarFormatter())
    ax.yaxis.set_minor_formatter(NullFormatter())
    ax.set_title(f"SSRT speed, {m['rays_per_pixel']} rays/px, {m['device']}, {threads(m['torch_threads'])}", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--repeats", type=int, default=3)
    add_threads_option(p)
    p.add_argument("--reference", default=None, help="Python file defining trace(...) to time on the same rays")
    a = p.parse_args(argv)
    apply_threads(a.threads)
    report = run(repeats=a.repeats, device=a.device, reference=a.reference)
    path = publish("ssrt", report, plot, device=a.device)
    m = report["measured"]
    for r in m["results"] + [
        {**r, "max_level": "reference", "compiled": False} for r in m.get("reference_results", [])
    ]:
        print(
            f"{r['width']}x{r['height']} level={r['max_level']} compiled={r['compiled']}: "
            f"{r['rays_per_second']:,.0f} rays/s "
            f"recall {r['recall']:.3f} precision {r['precision']:.3f} confident {r['precision_confident']:.3f}"
        )
    print(path)


if __name__ == "__main__":
    main()
