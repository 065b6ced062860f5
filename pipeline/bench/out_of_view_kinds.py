"""`python -m pipeline.bench.out_of_view_kinds`: the out-of-view branches side by side at equal training minutes.

Each kind in `--kinds` (`model.light_net.out_of_view.kind`) trains LightNet as `train_lighting` trains it
(the stage's config and optimiser, predicted G-buffers from the frozen MaterialNet export, gradient
clipping at the trainer's value, a cosine decay to zero) from the same seed for the same wall-clock
budget: its step time is measured over `--warmup` steps (counted in the budget), and the run takes as many
steps as `--minutes` hold at that pace, the cosine over those steps. Each trained network is then scored on
the held-out test split as the stages score it:
- `train_lighting`'s test metrics (`test_scores`): re-render PSNR (dB), surface and free light nMSE and
  the per-ray-class errors, per view;
- object insertion PSNR (dB) per material class and over all objects against Mitsuba, the `edit` stage's
  LightNet row (`insertion_scoring.score_rows`, every case with the stage's seed; `--edit-override
  scoring.spp=...` sets the samples, the same for every kind), the nearest-probe and scaled-constant rows
  scored once beside the first kind.
Every kind after the first is compared with the first, paired: insertion by case (views resampled whole)
and re-render by view (`metrics.bootstrap.paired_bootstrap`). A difference whose interval holds 0 is none.
With `--exports NAME=PATH ...` nothing is trained: each LightNet export (e.g. the `train_lighting` stage's
own, or the stage run with another `out_of_view.kind`, each at the stage's full schedule) is scored and
compared the same way, its kind read from the export.
Writes reports/bench/out_of_view_kinds.json (or `--name`) and a PNG.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure
from tqdm import tqdm

from pipeline.bench.common import (
    apply_threads,
    gradient_clip,
    optimiser_step,
    publish,
    training_system,
)
from pipeline.bench.learning_curve import (
    CLASSES,
    REFERENCE_ROWS,
    add_held_out_options,
    compare,
    first_rooms_loader,
    score,
)
from pipeline.metrics.bootstrap import paired_bootstrap

VIEW_METRICS = ("render_psnr", "surf_light_nmse", "free_light_nmse")


def train_for(system, optimizer, loader, minutes: float, warmup: int, clip: float, label: str) -> dict:
    """Train for about `minutes`: `warmup` steps at the starting learning rate time a step, then the
    remaining budget's steps under a cosine decay to zero. Returns steps, seconds and the median step time."""
    system.train()
    batches = iter(loader)

    def next_batch():
        nonlocal batches
        try:
            return next(batches)
        except StopIteration:
            batches = iter(loader)
            return next(batches)

    t0, times = time.perf_counter(), []
    for step in range(warmup):
        s = time.perf_counter()
        optimiser_step(system, optimizer, next_batch(), step, clip)
        times.append(time.perf_counter() - s)
    per_step = statistics.median(times)
    total = max(warmup, int(minutes * 60 / per_step))
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=max(1, total - warmup))
    for step in tqdm(range(warmup, total), desc=label, unit="step"):
        optimiser_step(system, optimizer, next_batch(), step, clip)
        scheduler.step()
    return {"steps": total, "seconds": time.perf_counter() - t0, "median_step_seconds": per_step}


def view_pairs(views: list[dict], reference: list[dict], resamples: int, seed: int) -> dict:
    """Per `VIEW_METRICS`: this kind's per-view test metric minus the reference kind's on the same views."""
    ref = {v["id"]: v for v in reference}
    out = {}
    for metric in VIEW_METRICS:
        pairs = [(v[metric], ref[v["id"]][metric]) for v in views if metric in v and metric in ref.get(v["id"], {})]
        if pairs:
            d = paired_bootstrap([a - b for a, b in pairs], resamples, seed)
            out[metric] = {"diff": d["diff"], "lo": d["lo"], "hi": d["hi"], "views": len(pairs)}
    return out


def export_kind(path: str) -> str:
    """The `out_of_view.kind` of a LightNet export (`models.export`; an export without one is `nerf`)."""
    from pipeline.models.export import LIGHT_FORMAT, read_export

    return str(read_export(path, LIGHT_FORMAT)["light_net"].get("out_of_view", {}).get("kind", "nerf"))


def load_export(system, path: str) -> dict:
    """Make the export's LightNet `system`'s: its weights and its whole configuration (volume samples and
    bounds are options, not weights), which `score` re-exports from `system.hparams`. Returns the run's
    timing fields, unknown here."""
    from pipeline.models.light_net import load_light_export

    net, blob = load_light_export(path)
    system.net = net.train(system.training)
    system.hparams["light_net"] = dict(blob["light_net"])
    return {"steps": None, "seconds": float("nan"), "median_step_seconds": float("nan"), "export": str(path)}


def run(
    kinds,
    minutes: float,
    warmup: int,
    seed: int,
    data_dir: str,
    resamples: int,
    overrides=(),
    edit_overrides=(),
    exports: dict[str, str] | None = None,
):
    """Train each of `kinds` for `minutes` (or, with `exports` {name: path}, load each export instead)
    and score it held out; the first is every other's reference."""
    from pipeline.data.datamodules import InteriorVerseDataModule
    from pipeline.data.datasets import ShardDataset

    rooms = len(ShardDataset(data_dir, "train", lighting=True))
    if exports:
        kinds = list(exports)
    report = {"kinds": list(kinds), "minutes": None if exports else minutes, "warmup": warmup, "seed": seed}
    report["rooms"], report["exports"] = rooms, dict(exports or {})
    report["overrides"], report["edit_overrides"] = list(overrides), list(edit_overrides)
    runs, records, views = [], {}, {}
    with tempfile.TemporaryDirectory() as scratch:
        for i, kind in enumerate(kinds):
            branch = export_kind(exports[kind]) if exports else kind
            o = [f"data_dir={data_dir}", f"model.light_net.out_of_view.kind={branch}", *overrides]
            system, optimizer, cfg = training_system("train_lighting", o, seed)
            dm = InteriorVerseDataModule(cfg.data_dir, batch_size=int(cfg.batch_size), seed=seed, lighting=True)
            dm.setup("test")
            if exports:
                timing = load_export(system, exports[kind])
            else:
                loader = first_rooms_loader(cfg.data_dir, rooms, int(cfg.batch_size), seed)
                timing = train_for(system, optimizer, loader, minutes, warmup, gradient_clip(cfg), kind)
            per_view: list[dict] = []
            rows = REFERENCE_ROWS if i == 0 else ("lightnet",)
            scores, recs = score(system, cfg, dm.test_dataloader(), rows, seed, Path(scratch), edit_overrides, per_view)
            records[kind], views[kind] = recs, per_view
            first = kinds[0]
            row = {
                "kind": kind,
                **timing,
                "parameters": sum(p.numel() for p in system.net.parameters()),
                "test": {k: v for k, v in scores.items() if not k.startswith("insertion/")},
                **{k: v for k, v in scores.items() if k.startswith("insertion/")},
                "insertion": compare(recs, records[first], resamples, seed),
                "views_minus_first": view_pairs(per_view, views[first], resamples, seed) if i else {},
            }
            runs.append(row)
            print({k: v for k, v in row.items() if k not in ("insertion", "test")}, flush=True)
    report["runs"] = runs
    report["summary"] = summarise(report)
    return report


def parse_exports(items: list[str], option: str = "--exports") -> dict[str, str]:
    """{name: path} of `NAME=PATH` items; a malformed item, a repeated name or a missing file is refused
    naming it and the command's `option`."""
    out = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise ValueError(f"{option} {item!r}: give NAME=PATH")
        if name in out:
            raise ValueError(f"{option}: {name!r} given twice")
        if not Path(path).is_file():
            raise FileNotFoundError(f"{option} {name}: {path} not found")
        out[name] = path
    return out


def summarise(report: dict) -> dict:
    """One row per kind: steps, step time, parameters, re-render PSNR, probe nMSE and insertion per class
    with its difference from the first kind (interval) where it has one."""
    rows = []
    for r in report["runs"]:
        row = {
            "kind": r["kind"],
            "steps": r["steps"],
            "step s": r["median_step_seconds"],
            "train min": r["seconds"] / 60,
            "re-render dB": r["test"].get("render_psnr"),
            "surf nMSE": r["test"].get("surf_light_nmse"),
            "free nMSE": r["test"].get("free_light_nmse"),
        }
        for c in CLASSES:
            ins = r["insertion"].get(c)
            if ins:
                row[f"{c} dB"] = ins["psnr"]
                if r is not report["runs"][0]:
                    lo, hi = ins["minus_reference_lo"], ins["minus_reference_hi"]
                    row[f"{c} minus first"] = f"{ins['minus_reference']:+.2f} [{lo:+.2f}, {hi:+.2f}]"
        rows.append(row)
    return {"kinds": rows}


def plot(report: dict, path) -> None:
    fig = Figure(figsize=(9, 3.8), layout="constrained")
    ax = fig.add_subplot(1, 1, 1)
    runs = report["runs"]
    x = np.arange(len(CLASSES))
    width = 0.8 / max(1, len(runs))
    for j, r in enumerate(runs):
        y = [r["insertion"].get(c, {}).get("psnr", np.nan) for c in CLASSES]
        lo = [y[k] - r["insertion"].get(c, {}).get("psnr_lo", np.nan) for k, c in enumerate(CLASSES)]
        hi = [r["insertion"].get(c, {}).get("psnr_hi", np.nan) - y[k] for k, c in enumerate(CLASSES)]
        minutes, psnr = r["seconds"] / 60, r["test"]["render_psnr"]
        trained = "the stage's training" if r["steps"] is None else f"{r['steps']} steps, {minutes:.0f} min"
        label = f"{r['kind']} ({trained}; re-render {psnr:.2f} dB)"
        ax.bar(x + j * width, y, width, yerr=[lo, hi], capsize=3, label=label)
    first = runs[0]
    for row, style in (("scaled_constant", ":"), ("nearest_probe", "-.")):
        for k, c in enumerate(CLASSES):
            v = first.get(f"insertion/{c}/{row}")
            if v is not None:
                ax.plot(
                    [k - width / 2, k + width * len(runs) - width / 2],
                    [v, v],
                    style,
                    color="k",
                    lw=1,
                    label=row.replace("_", " ") if k == 0 else None,
                )
    ax.set_xticks(x + width * (len(runs) - 1) / 2, CLASSES)
    ax.set_ylabel("insertion PSNR (dB), held-out test cases")
    ax.set_ylim(bottom=min(10, ax.get_ylim()[0]))
    ax.legend(fontsize=7)
    minutes = report["minutes"]
    budget = "as trained by the stage" if minutes is None else f"at {minutes:g} training minutes each"
    ax.set_title(f"out-of-view branches {budget} (95 % intervals over views)", fontsize=9)
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--kinds", nargs="+", default=["nerf", "roombox"])
    p.add_argument("--minutes", type=float, default=10.0, help="training wall-clock budget per kind")
    p.add_argument("--warmup", type=int, default=20, help="steps that time a step (inside the budget)")
    p.add_argument(
        "--exports",
        nargs="+",
        default=None,
        metavar="NAME=PATH",
        help="score these LightNet exports instead of training (the first is the reference)",
    )
    add_held_out_options(p, "out_of_view_kinds")
    a = p.parse_args(argv)
    apply_threads(a.threads)
    exports = parse_exports(a.exports) if a.exports else None
    report = run(a.kinds, a.minutes, a.warmup, a.seed, a.data_dir, a.resamples, a.override, a.edit_override, exports)
    print(publish(a.name, report, plot))


if __name__ == "__main__":
    main()
