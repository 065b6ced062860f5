"""`python -m pipeline.bench.light_gain`: is LightNet's light too dim or too bright for what it lights?

A render through the MC layer is linear in the incident radiance: with the same sample directions, the
render under g L is exactly g times the render under L. For every object insertion case of the `edit`
stage's test views, this renders the object once under LightNet (on the frozen MaterialNet's G-buffers:
the `edit` stage's `lightnet` row, same seeds) and once under the scaled constant, and scores g times each
render against Mitsuba's for a list of gains g. Per material class of the inserted object (mirror,
glossy, diffuse) and over all objects it reports the mean insertion PSNR at every gain and the gain that
maximises it. A best gain above 1 says the light is too dim for that class, below 1 too bright; a mirror
prefers a dimmer light than its mean when the light is blurred (the tone-mapped PSNR of a smeared lamp).
The gains are fitted on the test cases themselves: a diagnostic of bias, not a calibration.

Also writes each object case's scores at gain 1 as a CSV in the column names of the `edit` stage's
cases.csv (`view`, `case`, `kind`, `label`, `<row>/psnr`, `<row>/ssim`, `<row>/log_l1` for the two rows), so
`python -m pipeline.bench.compare_runs --cases A.csv B.csv` pairs two light_gain runs (two LightNet
exports) on the same cases without the oracle row's cost.
The `edit` configuration is composed from conf/ with `--override` on top: pass `profile=... seed=...` when
the pipeline's params.yaml uses other values than the defaults (tiny, 0).
Needs the trained exports and `synthesize`'s cases (`dvc repro train_lighting`). Writes
reports/bench/light_gain.json (or `--out`), a PNG beside it (PSNR against gain, one panel per class) and
the CSV (`--cases-csv`, default beside the JSON).
"""

from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure
from matplotlib.ticker import NullLocator
from tqdm import tqdm

from pipeline.bench.common import edit_object_cases, write_report
from pipeline.metrics.image import psnr_tonemapped

ROWS = ("lightnet", "scaled_constant")
CLASSES = ("mirror", "glossy", "diffuse")
DEFAULT_GAINS = (0.5, 0.7, 0.85, 1.0, 1.2, 1.4, 1.7, 2.0, 2.5, 3.0)


def check_gains(gains) -> tuple[float, ...]:
    """The gains as floats, 1 among them; a gain that is not a positive finite number is refused."""
    out = tuple(float(g) for g in gains)
    bad = [g for g in out if not (math.isfinite(g) and g > 0)]
    if bad or not out:
        raise ValueError(f"--gains {list(gains)}: give positive finite gains ({bad or 'none given'})")
    return tuple(sorted(set(out) | {1.0}))


def case_gain_psnr(render: torch.Tensor, target: torch.Tensor, scale: float, gains) -> list[float]:
    """Insertion PSNR (dB) of `gain * render` against target, HDR radiance (M, 3) of the case's pixels
    tone-mapped at the photo's mean `scale`, one per gain: the `edit` stage's PSNR (`case_scores`)."""
    s = torch.full((len(render),), float(scale), dtype=torch.float64)
    pred, truth = render.double(), target.double()
    return [float(psnr_tonemapped(pred * g, truth, s)) for g in gains]


def summarise(records: list[dict], gains: tuple[float, ...], rows=ROWS) -> dict:
    """Per class and over all objects, per row: mean PSNR at every gain, the best gain and its PSNR, and
    the PSNR at gain 1. records: {view, label, "<row>@gains": [psnr per gain]}."""
    out = {}
    for label in (*CLASSES, "all"):
        rs = [r for r in records if label == "all" or r["label"] == label]
        if not rs:
            continue
        per_row = {}
        for row in rows:
            curve = np.mean([r[f"{row}@gains"] for r in rs], axis=0)
            best = int(np.argmax(curve))
            per_row[row] = {
                "psnr": [float(v) for v in curve],
                "psnr_at_1": float(curve[gains.index(1.0)]),
                "best_gain": gains[best],
                "psnr_at_best_gain": float(curve[best]),
            }
        out[label] = {"cases": len(rs), "views": len({r["view"] for r in rs}), "rows": per_row}
    return out


def headline(classes: dict) -> list[dict]:
    """One row per class: LightNet's PSNR at gain 1, its best gain and the PSNR there, and the scaled
    constant's PSNR at gain 1 (the results page's table)."""
    rows = []
    for label, entry in classes.items():
        net, const = entry["rows"]["lightnet"], entry["rows"]["scaled_constant"]
        rows.append(
            {
                "class": label,
                "cases": entry["cases"],
                "LightNet at gain 1 (dB)": net["psnr_at_1"],
                "best gain": net["best_gain"],
                "LightNet at best gain (dB)": net["psnr_at_best_gain"],
                "scaled constant (dB)": const["psnr_at_1"],
            }
        )
    return rows


def run(overrides: list[str], gains: tuple[float, ...], cases_csv: Path, progress: bool = True) -> dict:
    """Scores every object case of the test views of the `edit` configuration composed with `overrides`
    (light_path, material_path, data_root, ...); writes the per-case CSV and returns the report."""
    from pipeline.bench.common import compose
    from pipeline.systems import insertion_scoring

    cfg = compose("edit", overrides)
    shared = insertion_scoring.stage_setup(cfg)
    records, csv_rows = [], []
    for scene, view in tqdm(shared["views"], desc="light gain", unit="view", disable=not progress):
        ctx, cases = insertion_scoring.view_context(shared, scene, view, cfg, oracle=False)
        v = ctx["view"]
        objects = edit_object_cases(ctx["id"], cases)
        for res in insertion_scoring.score_view(ctx, objects, cfg, ROWS):
            case = res["case"]
            rec = {"view": ctx["id"], "label": case.label}
            row = {"view": ctx["id"], "case": case.name, "kind": case.kind, "label": case.label}
            for name in ROWS:
                rec[f"{name}@gains"] = case_gain_psnr(res["renders"][name], case.radiance, float(v.scale), gains)
                row.update({f"{name}/{k}": s for k, s in res["rows"][name].items()})
            records.append(rec)
            csv_rows.append(row)
    if not records:
        raise ValueError(f"{cfg.data_root}: the {cfg.split} views' case files list no object case")
    cases_csv.parent.mkdir(parents=True, exist_ok=True)
    with open(cases_csv, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(csv_rows[0]))
        writer.writeheader()
        writer.writerows(csv_rows)
    classes = summarise(records, gains)
    return {
        "summary": {"insertion PSNR per class (gains fitted on these cases: a diagnostic)": headline(classes)},
        "light_path": str(cfg.light_path),
        "material_path": str(cfg.material_path),
        "split": str(cfg.split),
        "spp": int(cfg.scoring.spp),
        "gains": list(gains),
        "classes": classes,
        "cases_csv": str(cases_csv),
    }


def plot(report: dict, path: Path) -> None:
    gains = report["gains"]
    labels = [c for c in (*CLASSES, "all") if c in report["classes"]]
    fig = Figure(figsize=(3.2 * len(labels), 3.2))
    axes = fig.subplots(1, len(labels), squeeze=False)[0]
    for ax, label in zip(axes, labels, strict=True):
        entry = report["classes"][label]
        for row, style in zip(ROWS, ("o-", "s--"), strict=True):
            r = entry["rows"][row]
            ax.plot(gains, r["psnr"], style, ms=3, label=row)
            ax.plot([r["best_gain"]], [r["psnr_at_best_gain"]], "k*", ms=8)
        ax.axvline(1.0, color="0.6", lw=0.8)
        ax.set_xscale("log")
        ax.xaxis.set_minor_locator(NullLocator())  # only the gains measured are labelled
        ax.set_xticks(gains)
        ax.set_xticklabels([f"{g:g}" for g in gains], fontsize=6)
        ax.set_xlabel("gain on the incident radiance")
        ax.set_title(f"{label} ({entry['cases']} cases)", fontsize=9)
    axes[0].set_ylabel("insertion PSNR (dB)")
    axes[0].legend(fontsize=7)
    fig.suptitle("insertion PSNR against a gain on the light (star: best gain, fitted on these cases)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default="outputs/train_lighting/model.pt", help="LightNet export")
    p.add_argument("--material", default="outputs/train_material/model.pt", help="MaterialNet export")
    p.add_argument("--gains", type=float, nargs="+", default=list(DEFAULT_GAINS))
    p.add_argument("--out", default="reports/bench/light_gain.json", help="JSON to write (PNG beside it)")
    p.add_argument("--cases-csv", default=None, help="per-case CSV at gain 1 (default: <out>_cases.csv)")
    p.add_argument("--override", nargs="*", default=[], help="more `edit` config overrides (data_root=...)")
    a = p.parse_args(argv)
    try:
        gains = check_gains(a.gains)
    except ValueError as exc:
        p.error(str(exc))
    out = Path(a.out)
    cases_csv = Path(a.cases_csv) if a.cases_csv else out.with_name(out.stem + "_cases.csv")
    overrides = [f"light_path={a.model}", f"material_path={a.material}", *a.override]
    report = run(overrides, gains, cases_csv)
    write_report("light_gain", report, path=out)
    plot(report, out.with_suffix(".png"))
    for label, entry in report["classes"].items():
        r = entry["rows"]["lightnet"]
        best = f"best gain {r['best_gain']:g} ({r['psnr_at_best_gain']:.2f} dB)"
        print(f"{label:8s} PSNR at gain 1 {r['psnr_at_1']:.2f} dB, {best}")
    print(out)


if __name__ == "__main__":
    main()
