"""`python -m pipeline.bench.scoring_convergence`: how many samples per pixel the `edit` stage's scoring
needs before Monte Carlo noise stops moving any row's PSNR.

Noise lowers the PSNR of a sharp light (a lamp, the oracle's exact radiance) more than that of a blurred
one, so rows scored at unequal or unconverged noise favour blur. This renders every case of the `edit`
stage's test views (or the first `--max-views`) under every row at each sample count of `--spp`, with one
render layer for all rows and the stage's seeds (`insertion_scoring.score_view`), and reports per row
and case class the mean PSNR at each count and, for each count N with 4N also measured, the mean paired
change PSNR(4N) - PSNR(N) with a 95 % bootstrap interval over views. A row is converged at N when that
change is within `--tolerance` dB (0.1) in every class; `scoring.spp` in conf/edit.yaml should be a count
at which every row is.

The `edit` configuration is composed from conf/ with `--override` on top. Needs the trained exports and
`synthesize`'s cases (`dvc repro train_lighting`). Writes reports/bench/scoring_convergence.json (or
`--out`) and a PNG beside it (PSNR against spp, one panel per class).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from tqdm import tqdm

from pipeline.bench.common import write_report
from pipeline.metrics.bootstrap import paired_bootstrap
from pipeline.systems.insertion_scoring import ROWS, case_group


def measure(
    cfg, spps: list[int], rows: tuple = ROWS, max_views: int | None = None, progress: bool = True
) -> list[dict]:
    """One record per case: {view, class, psnr: {spp: {row: dB}}}, every row rendered at every count with
    the same seeds (the stage's)."""
    from pipeline.systems import insertion_scoring

    shared = insertion_scoring.stage_setup(cfg)
    layers = {n: insertion_scoring.scoring_layer(cfg, n) for n in spps}
    views = shared["views"][:max_views] if max_views else shared["views"]
    records = []
    for scene, view in tqdm(views, desc="scoring convergence", unit="view", disable=not progress):
        ctx, cases = insertion_scoring.view_context(shared, scene, view, cfg, oracle="oracle" in rows)
        per_case = [{"view": ctx["id"], "class": case_group(c.kind, c.label), "psnr": {}} for c in cases]
        for n, layer in layers.items():
            scored = insertion_scoring.score_view({**ctx, "layer": layer}, cases, cfg, rows)
            for rec, res in zip(per_case, scored, strict=True):
                rec["psnr"][n] = {row: res["rows"][row]["psnr"] for row in rows}
        records += per_case
    if not records:
        raise ValueError(f"{cfg.data_root}: the {cfg.split} views' case files list no case")
    return records


def summarise(records: list[dict], spps: list[int], rows: tuple, tolerance: float, resamples: int = 2000) -> dict:
    """Per class (and `all`) and row: mean PSNR per count, and the paired change to 4x each count that has
    one, with its bootstrap interval over views; `converged_spp`: per row, the smallest count whose change
    to 4x is within `tolerance` in every class (None if none is)."""
    classes = sorted({r["class"] for r in records})
    out: dict = {"classes": {}, "converged_spp": {}}
    for label in [*classes, "all"]:
        rs = [r for r in records if label in ("all", r["class"])]
        entry = {"cases": len(rs), "rows": {}}
        for row in rows:
            means = {str(n): float(np.mean([r["psnr"][n][row] for r in rs])) for n in spps}
            changes = {}
            for n in spps:
                if 4 * n in spps:
                    diff = [r["psnr"][4 * n][row] - r["psnr"][n][row] for r in rs]
                    ci = paired_bootstrap(diff, resamples, 0, groups=[r["view"] for r in rs])
                    changes[str(n)] = {"diff": ci["diff"], "lo": ci["lo"], "hi": ci["hi"]}
            entry["rows"][row] = {"mean_psnr": means, "change_at_4x": changes}
        out["classes"][label] = entry
    for row in rows:
        ok = [
            n
            for n in spps
            if 4 * n in spps
            and all(abs(out["classes"][c]["rows"][row]["change_at_4x"][str(n)]["diff"]) <= tolerance for c in classes)
        ]
        out["converged_spp"][row] = min(ok) if ok else None
    return out


def plot(report: dict, path: Path) -> None:
    labels = list(report["classes"])
    fig = Figure(figsize=(3.0 * len(labels), 3.2))
    axes = fig.subplots(1, len(labels), squeeze=False)[0]
    spps = report["spp"]
    for ax, label in zip(axes, labels, strict=True):
        entry = report["classes"][label]
        for row, r in entry["rows"].items():
            ax.plot(spps, [r["mean_psnr"][str(n)] for n in spps], "o-", ms=3, label=row)
        ax.axvline(report["configured_spp"], color="0.6", lw=0.8, ls=":")
        ax.set_xscale("log", base=2)
        ax.set_xticks(spps)
        ax.set_xticklabels([str(n) for n in spps], fontsize=6)
        ax.set_xlabel("samples per pixel (every row)")
        ax.set_title(f"{label} ({entry['cases']} cases)", fontsize=9)
    axes[0].set_ylabel("mean PSNR (dB)")
    axes[0].legend(fontsize=6)
    fig.suptitle("insertion and editing PSNR against samples per pixel (dotted: scoring.spp)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def run(overrides: list[str], spps: list[int], tolerance: float, max_views: int | None, progress: bool = True) -> dict:
    from pipeline.bench.common import compose

    if sorted(set(spps)) != list(spps) or not spps or spps[0] < 1:
        raise ValueError(f"--spp {spps}: give increasing positive counts")
    cfg = compose("edit", overrides)
    records = measure(cfg, spps, ROWS, max_views, progress)
    summary = summarise(records, spps, ROWS, tolerance)
    return {
        "summary": {"smallest converged spp per row (change at 4x within tolerance)": summary["converged_spp"]},
        "configured_spp": int(cfg.scoring.spp),
        "tolerance_db": tolerance,
        "spp": list(spps),
        "views": len({r["view"] for r in records}),
        "light_path": str(cfg.light_path),
        "material_path": str(cfg.material_path),
        "split": str(cfg.split),
        **summary,
    }


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--spp", type=int, nargs="+", default=[16, 64, 256, 1024])
    p.add_argument("--tolerance", type=float, default=0.1, help="dB a converged row may move at 4x the samples")
    p.add_argument("--max-views", type=int, default=None, help="the first N test views only")
    p.add_argument("--out", default="reports/bench/scoring_convergence.json", help="JSON to write (PNG beside it)")
    p.add_argument("--override", nargs="*", default=[], help="more `edit` config overrides (light_path=...)")
    a = p.parse_args(argv)
    try:
        report = run(list(a.override), list(a.spp), a.tolerance, a.max_views)
    except ValueError as exc:
        p.error(str(exc))
    out = Path(a.out)
    write_report("scoring_convergence", report, path=out)
    plot(report, out.with_suffix(".png"))
    for row, n in report["converged_spp"].items():
        print(f"{row:22s} converged at {n} spp" if n else f"{row:22s} not converged at any measured count")
    print(out)


if __name__ == "__main__":
    main()
