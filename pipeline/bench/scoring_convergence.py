"""`python -m pipeline.bench.scoring_convergence`: is the `edit` stage's scoring converged, i.e. does
any row's PSNR still move when its samples per pixel grow?

Noise lowers the PSNR of a sharp light (a lamp, the oracle's exact radiance) more than that of a blurred
one, so rows scored at unconverged noise favour blur. This renders every case of the `edit` stage's test
views (or `--views`, or the first `--max-views`) under every row at each `--scale` times the row's configured samples
(`insertion_scoring.row_spp`: `scoring.spp`, `scoring.row_spp`), with the stage's scoring layer and seeds
(`insertion_scoring.score_view`), and reports per row and case class the mean PSNR at each scale and, for
each scale s with 4s also measured, the mean paired change PSNR(4s) - PSNR(s) with a 95 % bootstrap
interval over views. A row is converged at s when that change is within `--tolerance` dB (0.1) in every
class; the stage's configuration is converged when every row is at scale 1.

The `edit` configuration is composed from conf/ with `--override` on top. Needs the trained exports and
`synthesize`'s cases (`dvc repro train_lighting`). Writes reports/bench/scoring_convergence.json (or
`--out`) and a PNG beside it (PSNR against the scale, one panel per class). `--ring` also measures the
ring around objects (`systems.ring_scoring`) at each scale times `scoring.ring.spp`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from tqdm import tqdm

from pipeline.bench.common import write_report
from pipeline.metrics.bootstrap import paired_bootstrap
from pipeline.systems.insertion_scoring import PSNR_VARIANTS, ROWS, case_group


def measure(
    cfg,
    scales: list[int],
    rows: tuple = ROWS,
    max_views: int | None = None,
    progress: bool = True,
    view_ids: list[str] | None = None,
    ring: bool = False,
) -> list[dict]:
    """One record per case: {view, class, psnr: {scale: {row: dB}}} (and `psnr_with_noise`,
    `psnr_decorrelated` alike for the rows scored in parts, `insertion_scoring.parts`), every row
    rendered at each `scale` times its configured samples per pixel (`insertion_scoring.row_spp`) with
    the same seeds (the stage's). With `ring`, object cases also carry `ring`: {scale: {ring_<row>: dB}},
    the ring's PSNR of each row in `RING_ROWS` (`systems.ring_scoring`) at `scale` times
    `scoring.ring.spp` (rows whose ring has no changed pixel left out)."""
    from pipeline.systems import insertion_scoring

    shared = insertion_scoring.stage_setup(cfg)
    layers = {n: insertion_scoring.scoring_layers(cfg, n) for n in scales}
    ring_spp = insertion_scoring.ring_spp(cfg)
    if ring and not ring_spp:
        raise ValueError("--ring: the edit configuration scores no ring (scoring.ring.enabled=false)")
    ring_layers = {n: insertion_scoring.scoring_layer(cfg, ring_spp * n) if ring else None for n in scales}
    views = shared["views"]
    if view_ids:
        unknown = sorted(set(view_ids) - {f"{scene}/{view}" for scene, view in views})
        if unknown:
            raise ValueError(f"--views {unknown}: not among the {cfg.split} views with cases")
        views = [(scene, view) for scene, view in views if f"{scene}/{view}" in view_ids]
    views = views[:max_views] if max_views else views
    records = []
    for scene, view in tqdm(views, desc="scoring convergence", unit="view", disable=not progress):
        ctx, cases = insertion_scoring.view_context(shared, scene, view, cfg, oracle="oracle" in rows)
        per_case = [{"view": ctx["id"], "class": case_group(c.kind, c.label), "psnr": {}} for c in cases]
        for n, layer in layers.items():
            scored = insertion_scoring.score_view(
                {**ctx, "layers": layer, "ring_layer": ring_layers[n]}, cases, cfg, rows, ring=ring
            )
            for rec, res in zip(per_case, scored, strict=True):
                rec["psnr"][n] = {row: res["rows"][row]["psnr"] for row in rows}
                if "ring" in res:
                    ring_psnr = {k: v["psnr"] for k, v in res["rows"].items() if k.startswith("ring_")}
                    rec.setdefault("ring", {})[n] = {k: v for k, v in ring_psnr.items() if np.isfinite(v)}
                for variant in PSNR_VARIANTS:  # rows scored in parts: their other PSNRs too
                    other = {row: res["rows"][row][variant] for row in rows if variant in res["rows"][row]}
                    if other:
                        rec.setdefault(variant, {})[n] = other
        records += per_case
    if not records:
        raise ValueError(f"{cfg.data_root}: the {cfg.split} views' case files list no case")
    return records


def summarise(records: list[dict], scales: list[int], rows: tuple, tolerance: float, resamples: int = 2000) -> dict:
    """Per class (and `all`) and row: mean PSNR per scale, and the paired change to 4x each scale that has
    one, with its bootstrap interval over views; `converged_scale`: per row, the smallest scale whose change
    to 4x is within `tolerance` in every class (None if none is)."""
    classes = sorted({r["class"] for r in records})
    out: dict = {"classes": {}, "converged_scale": {}}
    for label in [*classes, "all"]:
        rs = [r for r in records if label in ("all", r["class"])]
        entry = {"cases": len(rs), "rows": {}}
        for row in rows:
            means = {str(n): float(np.mean([r["psnr"][n][row] for r in rs])) for n in scales}
            entry["rows"][row] = {"mean_psnr": means, "change_at_4x": _changes(rs, scales, row, "psnr", resamples)}
            for variant in PSNR_VARIANTS:
                if all(row in r.get(variant, {}).get(scales[0], {}) for r in rs):
                    entry["rows"][row][f"mean_{variant}"] = {
                        str(n): float(np.mean([r[variant][n][row] for r in rs])) for n in scales
                    }
                    entry["rows"][row][f"{variant}_change_at_4x"] = _changes(rs, scales, row, variant, resamples)
        out["classes"][label] = entry
    for row in rows:
        ok = [
            n
            for n in scales
            if 4 * n in scales
            and all(abs(out["classes"][c]["rows"][row]["change_at_4x"][str(n)]["diff"]) <= tolerance for c in classes)
        ]
        out["converged_scale"][row] = min(ok) if ok else None
    return out


def summarise_ring(records: list[dict], scales: list[int], resamples: int = 2000) -> dict:
    """Per ring row (`ring_<row>`): the object cases whose ring it scored at every scale, its mean ring
    PSNR per scale and the paired change to 4x each scale that has one (interval over views)."""
    with_ring = [r for r in records if "ring" in r]
    names = sorted({k for r in with_ring for k in r["ring"][scales[0]]})
    out = {}
    for name in names:
        rs = [r for r in with_ring if all(name in r["ring"][n] for n in scales)]
        out[name] = {
            "cases": len(rs),
            "mean_psnr": {str(n): float(np.mean([r["ring"][n][name] for r in rs])) for n in scales},
            "change_at_4x": _changes(rs, scales, name, "ring", resamples),
        }
    return out


def _changes(rs: list[dict], scales: list[int], row: str, key: str, resamples: int = 2000) -> dict:
    """{scale: {diff, lo, hi}}: the mean paired change of `key` (a PSNR, dB) from each scale to 4x it, with
    its bootstrap interval over views, for every scale whose 4x was measured."""
    changes = {}
    for n in scales:
        if 4 * n in scales:
            diff = [r[key][4 * n][row] - r[key][n][row] for r in rs]
            ci = paired_bootstrap(diff, resamples, 0, groups=[r["view"] for r in rs])
            changes[str(n)] = {"diff": ci["diff"], "lo": ci["lo"], "hi": ci["hi"]}
    return changes


def headline(summary: dict, spp: dict[str, int], tolerance: float) -> list[dict]:
    """One row per scored row: its configured spp, the paired change at 4x over all cases (dB, with the
    interval), the largest change of any class, and whether every class is within `tolerance`."""
    out = []
    for row, n in spp.items():
        change = summary["classes"]["all"]["rows"][row]["change_at_4x"].get("1")
        if change is None:
            continue
        worst = max(
            (abs(c["rows"][row]["change_at_4x"]["1"]["diff"]) for k, c in summary["classes"].items() if k != "all"),
            default=float("nan"),
        )
        out.append(
            {
                "row": row,
                "spp": n,
                "change at 4x, all cases (dB)": change["diff"],
                "lo": change["lo"],
                "hi": change["hi"],
                "largest class change (dB)": worst,
                "converged": "yes" if worst <= tolerance else "no",
            }
        )
    return out


OTHER_LINES = (("psnr_with_noise", "x--", "plain"), ("psnr_decorrelated", "+:", "decorrelated"))


def _scale_axis(ax, scales: list[int]) -> None:
    """A log2 x axis with one tick per measured scale, labelled `<n>x`."""
    ax.set_xscale("log", base=2)
    ax.set_xticks(scales)
    ax.set_xticklabels([f"{n}x" for n in scales], fontsize=6)


def plot(report: dict, path: Path) -> None:
    labels = list(report["classes"])
    ring = report.get("ring") or {}
    fig = Figure(figsize=(3.0 * (len(labels) + bool(ring)), 3.2))
    axes = fig.subplots(1, len(labels) + bool(ring), squeeze=False)[0]
    scales = report["scales"]
    if ring:  # the ring around objects (`--ring`): each row's mean ring PSNR against the scale
        ax = axes[-1]
        for name, entry in ring.items():
            ax.plot(scales, [entry["mean_psnr"][str(n)] for n in scales], "s-", ms=3, label=name)
        ax.set_title(f"ring around objects ({max(e['cases'] for e in ring.values())} cases)", fontsize=9)
        _scale_axis(ax, scales)
        ax.set_xlabel(f"samples (x {report.get('ring_spp')})", fontsize=7)
        ax.legend(fontsize=6)
        axes = axes[:-1]
    for ax, label in zip(axes, labels, strict=True):
        entry = report["classes"][label]
        for row, r in entry["rows"].items():
            line = ax.plot(scales, [r["mean_psnr"][str(n)] for n in scales], "o-", ms=3, label=row)[0]
            for variant, style, name in OTHER_LINES:
                if f"mean_{variant}" in r:  # the same renders' other PSNRs (plain: noise included)
                    other = [r[f"mean_{variant}"][str(n)] for n in scales]
                    ax.plot(scales, other, style, ms=3, color=line.get_color(), label=f"{row}, {name} PSNR")
        _scale_axis(ax, scales)
        ax.set_xlabel("samples (x the row's configured)", fontsize=7)
        ax.set_title(f"{label} ({entry['cases']} cases)", fontsize=9)
    axes[0].set_ylabel("mean PSNR (dB)")
    axes[0].legend(fontsize=6)
    spp = ", ".join(f"{row} {n}" for row, n in report["row_spp"].items())
    fig.suptitle(f"insertion and editing PSNR against samples (configured spp: {spp})", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def run(
    overrides: list[str],
    scales: list[int],
    tolerance: float,
    max_views: int | None,
    progress: bool = True,
    view_ids: list[str] | None = None,
    rows: tuple = ROWS,
    ring: bool = False,
) -> dict:
    from pipeline.bench.common import compose
    from pipeline.systems.insertion_scoring import row_spp

    if sorted(set(scales)) != list(scales) or not scales or scales[0] < 1:
        raise ValueError(f"--scale {scales}: give increasing positive factors")
    unknown = [row for row in rows if row not in ROWS]
    if unknown or not rows:
        raise ValueError(f"--rows {list(rows)}: choose among {list(ROWS)}")
    cfg = compose("edit", overrides)
    spp = {row: row_spp(cfg, row) for row in rows}
    records = measure(cfg, scales, tuple(rows), max_views, progress, view_ids, ring)
    summary = summarise(records, scales, tuple(rows), tolerance)
    if ring:
        summary["ring"] = summarise_ring(records, scales)
        summary["ring_spp"] = int(cfg.scoring.ring.spp)
    return {
        "summary": {"each row at its configured samples per pixel and at 4x them": headline(summary, spp, tolerance)},
        "row_spp": spp,
        "scoring_layer": str(cfg.scoring.layer),
        "guide": bool(cfg.scoring.guide),
        "oracle_paths": int(cfg.oracle.paths),
        "oracle_psnr": str(cfg.oracle.psnr),
        "tolerance_db": tolerance,
        "scales": list(scales),
        "views": len({r["view"] for r in records}),
        "view_ids": sorted({r["view"] for r in records}),
        "light_path": str(cfg.light_path),
        "material_path": str(cfg.material_path),
        "split": str(cfg.split),
        **summary,
    }


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scale", type=int, nargs="+", default=[1, 4], help="factors of every row's configured spp")
    p.add_argument("--tolerance", type=float, default=0.1, help="dB a converged row may move at 4x the samples")
    p.add_argument("--max-views", type=int, default=None, help="the first N test views only")
    p.add_argument("--views", nargs="*", default=None, help="these test views only (scene/view ids)")
    p.add_argument("--rows", nargs="+", default=list(ROWS), help=f"the rows to measure (default all: {' '.join(ROWS)})")
    p.add_argument("--ring", action="store_true", help="also the ring around objects (scoring.ring.spp x each scale)")
    p.add_argument("--out", default="reports/bench/scoring_convergence.json", help="JSON to write (PNG beside it)")
    p.add_argument("--override", nargs="*", default=[], help="more `edit` config overrides (light_path=...)")
    a = p.parse_args(argv)
    try:
        report = run(
            list(a.override), list(a.scale), a.tolerance, a.max_views, view_ids=a.views, rows=tuple(a.rows), ring=a.ring
        )
    except ValueError as exc:
        p.error(str(exc))
    out = Path(a.out)
    write_report("scoring_convergence", report, path=out)
    plot(report, out.with_suffix(".png"))
    for row, n in report["converged_scale"].items():
        print(f"{row:22s} converged at {n}x its spp" if n else f"{row:22s} not converged at any measured scale")
    for name, entry in report.get("ring", {}).items():
        change = entry["change_at_4x"].get("1")
        if change:
            print(f"{name:22s} ring PSNR at 4x: {change['diff']:+.3f} dB [{change['lo']:+.3f}, {change['hi']:+.3f}]")
    print(out)


if __name__ == "__main__":
    main()
