"""`python -m pipeline.bench.compare_runs`: two runs of the pipeline on the same test views, paired.

Given the `edit` stage's cases.csv of a run before and after a change (`--cases OLD NEW`), the
`train_lighting` stage's test_views.csv of both (`--views OLD NEW`) or the `train_material` stage's
(`--material OLD NEW`), in any combination, it pairs each case (view, case) or view (id) across the two
runs and reports, per group, the mean before and after and the mean difference (after minus before)
with its 95 % bootstrap interval, whole views resampled (`metrics.bootstrap.paired_bootstrap`):
insertion PSNR per object material and over all objects, edit PSNR per edit, the LightNet test metrics
(re-render PSNR, light nMSE, log-L1), and MaterialNet's per-view map errors. A difference whose
interval holds 0 is reported as none (a group from one view has no interval). Cases or views present in
one run only are refused by name: the two runs must have scored the same views.

Writes `--out` (JSON) and prints a table.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path

from pipeline.metrics.bootstrap import paired_bootstrap

CASE_METRIC = "lightnet/psnr"
VIEW_METRICS = ("render_psnr", "surf_light_nmse", "free_light_nmse", "surf_light_log_l1", "free_light_log_l1")


def read_rows(path: Path, key) -> dict:
    """{key(row): row} of a CSV; a missing file or a repeated key is refused naming the file."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"{path}: not found")
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"{path}: no rows")
    out = {}
    for row in rows:
        k = key(row)
        if k in out:
            raise ValueError(f"{path}: {k} appears twice")
        out[k] = row
    return out


def _number(row: dict, column: str, path: Path, key) -> float:
    try:
        value = float(row[column])
    except (KeyError, ValueError) as exc:
        raise ValueError(f"{path}: {key}: column {column!r} missing or not a number") from exc
    if not math.isfinite(value):
        raise ValueError(f"{path}: {key}: {column} is {value}")
    return value


def paired(old: dict, new: dict, old_path: Path, new_path: Path) -> list:
    """The keys both runs hold, in order; refuses keys present in one run only."""
    only_old, only_new = sorted(set(old) - set(new)), sorted(set(new) - set(old))
    if only_old or only_new:
        raise ValueError(
            f"{old_path} and {new_path} did not score the same cases: only before {only_old[:5]}, "
            f"only after {only_new[:5]}"
        )
    return sorted(old)


def summarise(before: list[float], after: list[float], views: list[str]) -> dict:
    diff = paired_bootstrap([b - a for a, b in zip(before, after, strict=True)], groups=views)
    if math.isnan(diff["lo"]):  # a single view: nothing to resample
        verdict = "no interval"
    else:
        verdict = "none" if diff["lo"] <= 0 <= diff["hi"] else ("higher" if diff["lo"] > 0 else "lower")
    return {"before": sum(before) / len(before), "after": sum(after) / len(after), **diff, "verdict": verdict}


def compare_cases(old_path: Path, new_path: Path) -> dict:
    key = lambda r: (r["view"], r["case"])  # noqa: E731
    old, new = read_rows(old_path, key), read_rows(new_path, key)
    keys = paired(old, new, old_path, new_path)
    groups: dict[str, list] = {}
    for k in keys:
        o, n = old[k], new[k]
        if (o["kind"], o["label"]) != (n["kind"], n["label"]):
            raise ValueError(f"{k}: {o['kind']}/{o['label']} before, {n['kind']}/{n['label']} after")
        names = [f"{o['kind']}/{o['label']}"] + (["object/all"] if o["kind"] == "object" else [])
        pair = (_number(o, CASE_METRIC, old_path, k), _number(n, CASE_METRIC, new_path, k), k[0])
        for name in names:
            groups.setdefault(name, []).append(pair)
    return {name: summarise(*map(list, zip(*rows, strict=True))) for name, rows in sorted(groups.items())}


def compare_views(old_path: Path, new_path: Path, mode: str = "mixed", metrics=VIEW_METRICS) -> dict:
    """Per metric of `metrics` (None: every `<mode>/` column), the `<mode>/<metric>` column of two per-view
    CSVs paired by view id."""
    old, new = read_rows(old_path, lambda r: r["id"]), read_rows(new_path, lambda r: r["id"])
    keys = paired(old, new, old_path, new_path)
    if metrics is None:
        metrics = [c.removeprefix(f"{mode}/") for c in old[keys[0]] if c.startswith(f"{mode}/")]
    out = {}
    for metric in metrics:
        column = f"{mode}/{metric}"
        if column not in old[keys[0]] or column not in new[keys[0]]:
            continue
        before = [_number(old[k], column, old_path, k) for k in keys]
        after = [_number(new[k], column, new_path, k) for k in keys]
        out[metric] = summarise(before, after, keys)
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", nargs=2, metavar=("OLD", "NEW"), help="the edit stage's cases.csv of both runs")
    p.add_argument("--views", nargs=2, metavar=("OLD", "NEW"), help="train_lighting's test_views.csv of both")
    p.add_argument("--material", nargs=2, metavar=("OLD", "NEW"), help="train_material's test_views.csv of both")
    p.add_argument("--out", required=True, help="JSON to write")
    a = p.parse_args(argv)
    if not a.cases and not a.views and not a.material:
        p.error("give --cases, --views or --material (or several)")
    report = {}
    if a.cases:
        report["cases"] = {"files": a.cases, "metric": CASE_METRIC, "groups": compare_cases(*map(Path, a.cases))}
    if a.views:
        report["views"] = {"files": a.views, "metrics": compare_views(*map(Path, a.views))}
    if a.material:
        material = compare_views(*map(Path, a.material), mode="model", metrics=None)  # every map it scores
        report["material"] = {"files": a.material, "metrics": material}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(report, indent=1) + "\n")
    for part in ("cases", "views", "material"):
        rows = report.get(part, {}).get("groups") or report.get(part, {}).get("metrics") or {}
        for name, r in rows.items():
            print(
                f"{part:5s} {name:22s} {r['before']:8.3f} -> {r['after']:8.3f}  "
                f"{r['diff']:+.3f} [{r['lo']:+.3f}, {r['hi']:+.3f}] {r['verdict']}"
            )
    print(a.out)


if __name__ == "__main__":
    main()
