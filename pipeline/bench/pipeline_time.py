"""`python -m pipeline.bench.pipeline_time`: what `dvc repro` costs on this machine, stage by stage, against
the profile's time budget.

Every stage execution is one top-level MLflow run (`tracking.stage_run`: tags `stage`, `profile`, and for
`ablate` `preset` and `seed`), so the store holds each stage's wall time as the run's start and end. For every
stage instance of dvc.yaml (its plain stages in file order, one `ablate@<key>` per entry of params.yaml
`ablations`), this bench takes the latest finished run of that instance under `--profile` (a top-level run;
for `ablate` the run tagged with its preset and seed, wherever `report` has attached it), and
writes reports/bench/pipeline_time.json (per instance: minutes, start date, the commit it ran at; the total
against `--budget` minutes; instances never run are listed, and the total is then a lower bound) and a PNG:
each stage's minutes (ablation presets summed over their seeds) and the cumulative sum against the budget.

A run's duration leaves out the process start before the run opens (Python imports, Hydra's composition)
and DVC's hashing between stages: together about half a minute per stage here.
"""

from __future__ import annotations

import argparse
import datetime
import sqlite3
from pathlib import Path

import yaml
from matplotlib.figure import Figure

from pipeline.bench.common import publish
from pipeline.tracking.mlflow_run import project_root

RUNS = """
select r.run_uuid, r.start_time, r.end_time,
       max(case when t.key = 'stage' then t.value end),
       max(case when t.key = 'profile' then t.value end),
       max(case when t.key = 'preset' then t.value end),
       max(case when t.key = 'seed' then t.value end),
       max(case when t.key = 'git_sha' then t.value end),
       max(case when t.key = 'mlflow.parentRunId' then t.value end)
from runs r join tags t on t.run_uuid = r.run_uuid
where r.status = 'FINISHED' and r.lifecycle_stage = 'active'
group by r.run_uuid
"""


def stage_instances(root: Path) -> list[str]:
    """dvc.yaml's stage instances in file order: plain stages by name, `ablate@<key>` per params entry."""
    stages = yaml.safe_load((root / "dvc.yaml").read_text())["stages"]
    ablations = yaml.safe_load((root / "params.yaml").read_text()).get("ablations") or {}
    out = []
    for name, stage in stages.items():
        out += [f"{name}@{key}" for key in ablations] if "foreach" in stage else [name]
    return out


def latest_runs(db: Path, profile: str) -> dict[str, dict]:
    """{instance: {minutes, started, commit}} of the latest finished top-level run of each stage instance
    under `profile` in the MLflow store `db` (an ablation run is `ablate@<preset>-s<seed>`)."""
    if not db.is_file():
        raise FileNotFoundError(f"{db}: no MLflow store (run `dvc repro` first)")
    with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as con:
        rows = con.execute(RUNS).fetchall()
    out: dict[str, dict] = {}
    for _, start, end, stage, run_profile, preset, seed, sha, parent in sorted(rows, key=lambda r: r[1]):
        # a run nested in another stage's (the training inside an ablation run) is part of that stage; an
        # ablation run (tagged with its preset) is its own, wherever the `report` stage has attached it
        own = preset is not None if stage == "ablate" else parent is None
        if not own or stage is None or run_profile != profile or end is None:
            continue
        name = f"{stage}@{preset}-s{seed}" if stage == "ablate" else stage
        out[name] = {
            "minutes": (end - start) / 60000.0,
            "started": datetime.datetime.fromtimestamp(start / 1000, datetime.UTC).strftime("%Y-%m-%d %H:%M"),
            "commit": (sha or "").removesuffix("-dirty")[:12] + ("-dirty" if (sha or "").endswith("-dirty") else ""),
        }
    return out


def measure(root: Path, db: Path, profile: str, budget: float) -> dict:
    """The JSON's `measured` block: every instance's row, the total and the budget."""
    runs = latest_runs(db, profile)
    rows, missing = [], []
    for name in stage_instances(root):
        if name in runs:
            rows.append({"stage": name, **runs[name]})
        else:
            missing.append(name)
    total = sum(r["minutes"] for r in rows)
    groups: dict[str, float] = {}
    for r in rows:
        key = r["stage"].split("-s")[0] if r["stage"].startswith("ablate@") else r["stage"]
        groups[key] = groups.get(key, 0.0) + r["minutes"]
    return {
        "total_minutes": total,
        "budget_minutes": budget,
        "over_budget_minutes": total - budget,
        "ablate_minutes": sum(v for k, v in groups.items() if k.startswith("ablate@")),
        "instances_run": len(rows),
        "instances_missing": len(missing),
        "minutes by stage (ablation presets summed over seeds)": groups,
        "each stage instance's latest run": rows,
        "missing": missing,
    }


def plot(report: dict, path: Path) -> None:
    m = report["measured"]
    groups = m["minutes by stage (ablation presets summed over seeds)"]
    names, minutes = list(groups), list(groups.values())
    fig = Figure(figsize=(11, 0.32 * len(names) + 2.2))
    ax, cum = fig.subplots(1, 2, gridspec_kw={"width_ratios": [3, 1]})
    ax.barh(range(len(names)), minutes, color=["tab:orange" if n.startswith("ablate@") else "tab:blue" for n in names])
    ax.set_yticks(range(len(names)), names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("minutes (latest finished run of each instance)")
    for i, v in enumerate(minutes):
        ax.text(v, i, f" {v:.1f}", va="center", fontsize=7)
    bottom = 0.0
    for n, v in zip(names, minutes, strict=True):
        cum.bar(0, v, bottom=bottom, color="tab:orange" if n.startswith("ablate@") else "tab:blue", edgecolor="white")
        bottom += v
    cum.axhline(m["budget_minutes"], color="tab:red", lw=2)
    budget = f" budget {m['budget_minutes']:g} min"
    cum.text(0.45, m["budget_minutes"], budget, color="tab:red", va="bottom", fontsize=8)
    cum.set_xticks([])
    cum.set_xlim(-0.6, 1.4)
    cum.set_ylabel("cumulative minutes")
    cum.set_title(f"total {m['total_minutes']:.0f} min" + (" (some never run)" if m["missing"] else ""), fontsize=9)
    fig.suptitle(f"dvc repro on this machine, stage by stage ({report['profile']})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--db", type=Path, default=None, help="the MLflow store (default: mlflow.db at the root)")
    parser.add_argument("--profile", default="tiny", help="the profile whose runs are timed")
    parser.add_argument("--budget", type=float, default=120.0, help="minutes `dvc repro` should stay within")
    parser.add_argument("--name", default="pipeline_time", help="reports/bench/<name>.json")
    args = parser.parse_args(argv)
    root = project_root()
    db = args.db if args.db is not None else root / "mlflow.db"
    report = {"profile": args.profile, "measured": measure(root, db, args.profile, args.budget)}
    return publish(args.name, report, plot)


if __name__ == "__main__":
    main()
