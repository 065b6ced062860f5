"""`python -m pipeline.bench.learning_curve`: what more training steps or more training rooms would buy.

LightNet is trained as `train_lighting` trains it (the stage's config: predicted G-buffers from the frozen
MaterialNet export, its training step, AdamW, gradient clipping at the trainer's value, a cosine decay to
zero) on two axes, each point its own run from the same seeded initialisation:
- rooms: the first n views of the training split for each n in `--rooms`, every run `--steps` steps (the
  main stage's budget by default: 20 epochs of 63 batches);
- steps: all training rooms for each budget in `--budgets` (and `--steps`), the cosine over each budget.
The cosine here decays per step over the run's budget (the stage steps it per epoch: the same curve,
sampled finer). Each run is scored on the held-out test split:
- re-render PSNR (dB) and surface / free light nMSE, `train_lighting`'s test metrics (`test_scores`);
- object insertion PSNR (dB) per material class and over all objects against Mitsuba, the `edit` stage's
  scoring of its LightNet row (`insertion_scoring.score_rows`) on the test cases, each case with the stage's seed.
Every point's insertion is compared with the reference point (most rooms, most steps) on the same cases,
paired by view (`paired_bootstrap`, whole views resampled); the scaled-constant and nearest-probe rows are
scored once, on the reference run. The training seconds are timed per run (the axis against minutes).
Writes reports/bench/learning_curve.json (or `--name`) and a PNG: insertion and re-render PSNR against
training minutes and against training rooms.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure
from tqdm import tqdm

from pipeline.bench.common import (
    add_threads_option,
    apply_threads,
    gradient_clip,
    optimiser_step,
    publish,
    training_system,
)
from pipeline.metrics.bootstrap import mean_bootstrap, paired_bootstrap

CLASSES = ("mirror", "glossy", "diffuse", "all")
REFERENCE_ROWS = ("lightnet", "scaled_constant", "nearest_probe")
TEST_METRICS = ("render_psnr", "surf_light_nmse", "free_light_nmse")


def add_held_out_options(parser, name: str) -> None:
    """The options of a bench that trains LightNet and scores it held out: data, stage and edit overrides,
    bootstrap resamples, seed, the JSON's name and the torch threads."""
    parser.add_argument("--data-dir", default="outputs/preprocess")
    parser.add_argument("--override", action="append", default=[], help="a train_lighting override (repeatable)")
    parser.add_argument("--edit-override", action="append", default=[], help="an edit override (repeatable)")
    parser.add_argument("--resamples", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--name", default=name, help="the JSON/PNG name under reports/bench")
    add_threads_option(parser)


def first_rooms_loader(data_dir: str, rooms: int, batch_size: int, seed: int):
    """A shuffling loader (seeded) over the first `rooms` views of the training split, the last partial
    batch dropped as the stage drops it. Raises naming the split when it holds fewer views."""
    from torch.utils.data import DataLoader, Subset

    from pipeline.data.datasets import ShardDataset, collate_views

    train = ShardDataset(data_dir, "train", lighting=True)
    if rooms > len(train) or rooms < batch_size:
        raise ValueError(
            f"--rooms {rooms}: need between the batch size ({batch_size}) and the {len(train)} views of "
            f"{data_dir}'s training split"
        )
    return DataLoader(
        Subset(train, range(rooms)),
        batch_size,
        shuffle=True,
        generator=torch.Generator().manual_seed(seed),
        collate_fn=collate_views,
        drop_last=True,
    )


def train(system, optimizer, loader, steps: int, clip: float, label: str) -> float:
    """`steps` training steps with a per-step cosine decay to zero; returns the seconds they took."""
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=steps)
    system.train()
    step, t0 = 0, time.perf_counter()
    with tqdm(total=steps, desc=label, unit="step") as bar:
        while step < steps:
            for batch in loader:
                optimiser_step(system, optimizer, batch, step, clip)
                scheduler.step()
                step += 1
                bar.update(1)
                if step >= steps:
                    break
    return time.perf_counter() - t0


def score(
    system, cfg, test_loader, rows: tuple, seed: int, export_dir: Path, edit_overrides=(), views=None
) -> tuple[dict, list[dict]]:
    """Test-split metrics of the trained system: `TEST_METRICS` (views: a list each view's own test
    metrics are appended to, `test_scores`) and the insertion means per class for `rows` (the edit
    stage's `insert/<class>/<row>/psnr`), and the per-case insertion records."""
    from omegaconf import OmegaConf

    from pipeline.bench.common import compose
    from pipeline.models.export import save_light_export
    from pipeline.systems import insertion_scoring
    from pipeline.systems.lighting_training import test_scores

    tested = test_scores(system, test_loader, views)
    out = {k: float(tested[k]) for k in TEST_METRICS}
    path = export_dir / "light.pt"
    save_light_export(path, system.hparams["light_net"], system.net)
    edit_cfg = compose(
        "edit", [*edit_overrides, f"seed={seed}", f"light_path={path}", f"material_path={cfg.material_path}"]
    )
    OmegaConf.set_readonly(edit_cfg, False)
    summary, records = insertion_scoring.score_rows(edit_cfg, rows, progress=True)
    for c in CLASSES:
        for row in rows:
            key = f"insert/{c}/{row}/psnr"
            if key in summary:
                out[f"insertion/{c}/{row}"] = summary[key]
    return out, [r for r in records if r["kind"] == "object"]


def compare(records: list[dict], reference: list[dict], resamples: int, seed: int) -> dict:
    """Per class: this run's insertion PSNR minus the reference run's on the same cases (paired by case,
    views resampled whole), and the interval of this run's own mean (views resampled)."""
    for r, q in zip(records, reference, strict=True):
        if (r["view"], r["label"]) != (q["view"], q["label"]):
            raise ValueError(f"the cases differ from the reference run's at {r['view']} ({r['label']})")
    out = {}
    for c in CLASSES:
        pairs = [(r, q) for r, q in zip(records, reference, strict=True) if c == "all" or r["label"] == c]
        if not pairs:
            continue
        a = [p[0]["lightnet/psnr"] for p in pairs]
        views = [p[0]["view"] for p in pairs]
        change = [p[0]["lightnet/psnr"] - p[1]["lightnet/psnr"] for p in pairs]
        diff = paired_bootstrap(change, resamples, seed, groups=views)
        own = mean_bootstrap(a, resamples, seed, groups=views)
        out[c] = {
            "psnr": own["mean"],
            "psnr_lo": own["lo"],
            "psnr_hi": own["hi"],
            "minus_reference": diff["diff"],
            "minus_reference_lo": diff["lo"],
            "minus_reference_hi": diff["hi"],
            "cases": len(pairs),
        }
    return out


def run(rooms, steps: int, budgets, seed: int, data_dir: str, resamples: int, overrides=(), edit_overrides=()) -> dict:
    """Train and score every point of both axes (module docstring). overrides: of `train_lighting`;
    edit_overrides: of the `edit` config the insertion is scored with (e.g. its data_root)."""
    from pipeline.data.datamodules import InteriorVerseDataModule

    most = max(rooms)
    plan = [(n, steps) for n in sorted(rooms)]
    plan += [(most, b) for b in sorted(budgets) if b != steps]
    reference = (most, steps)
    report = {"rooms": sorted(rooms), "steps": steps, "budgets": sorted({*budgets, steps}), "seed": seed}
    report["overrides"] = list(overrides)
    runs, records = [], {}
    with tempfile.TemporaryDirectory() as scratch:
        # the reference run first, so every other run is compared with it as soon as it is scored
        for n, s in sorted(plan, key=lambda p: p != reference):
            system, optimizer, cfg = training_system("train_lighting", [f"data_dir={data_dir}", *overrides], seed)
            dm = InteriorVerseDataModule(cfg.data_dir, batch_size=int(cfg.batch_size), seed=seed, lighting=True)
            dm.setup("test")
            loader = first_rooms_loader(cfg.data_dir, n, int(cfg.batch_size), seed)
            clip = gradient_clip(cfg)
            seconds = train(system, optimizer, loader, s, clip, f"{n} rooms, {s} steps")
            rows = REFERENCE_ROWS if (n, s) == reference else ("lightnet",)
            scores, recs = score(system, cfg, dm.test_dataloader(), rows, seed, Path(scratch), edit_overrides)
            records[(n, s)] = recs
            row = {
                "rooms": n,
                "steps": s,
                "epochs": s / len(loader),
                "train_minutes": seconds / 60.0,
                **scores,
                "insertion": compare(recs, records[reference], resamples, seed),
            }
            runs.append(row)
            print({k: v for k, v in row.items() if k != "insertion"}, flush=True)
    report["reference"] = {"rooms": reference[0], "steps": reference[1]}
    report["runs"] = sorted(runs, key=lambda r: (r["rooms"], r["steps"]))
    return report


def plot(report: dict, path) -> None:
    """Insertion PSNR per class (bootstrap interval over views) and re-render PSNR (dB) against training
    steps (all rooms; a step's seconds are what `bench.train_step` measures, the wall minutes of each run
    are in the JSON) and against training rooms (the full budget, log axis)."""
    fig = Figure(figsize=(11, 4.2), layout="constrained")
    axes = fig.subplots(1, 2)
    most, steps = report["reference"]["rooms"], report["reference"]["steps"]
    axes_runs = (
        (
            "steps",
            "training steps (minutes: the JSON's train_minutes)",
            [r for r in report["runs"] if r["rooms"] == most],
        ),
        ("rooms", "training rooms", [r for r in report["runs"] if r["steps"] == steps]),
    )
    reference = next(r for r in report["runs"] if (r["rooms"], r["steps"]) == (most, steps))
    colours = {"mirror": "tab:blue", "glossy": "tab:orange", "diffuse": "tab:green", "all": "black"}
    for ax, (x_key, x_label, rs) in zip(axes, axes_runs, strict=True):
        rs = sorted(rs, key=lambda r: r[x_key])
        x = [r[x_key] for r in rs]
        for c in CLASSES:
            if not all(c in r["insertion"] for r in rs):
                continue
            y = np.array([r["insertion"][c]["psnr"] for r in rs])
            lo = y - np.array([r["insertion"][c]["psnr_lo"] for r in rs])
            hi = np.array([r["insertion"][c]["psnr_hi"] for r in rs]) - y
            ax.errorbar(x, y, yerr=[lo, hi], marker="o", capsize=3, color=colours[c], label=f"insertion, {c}")
        ax.plot(x, [r["render_psnr"] for r in rs], "s--", color="tab:red", label="re-render (test views)")
        for row, style in (("scaled_constant", ":"), ("nearest_probe", "-.")):
            value = reference.get(f"insertion/all/{row}")
            if value is not None:
                ax.axhline(value, color="grey", ls=style, lw=1, label=f"insertion, all: {row.replace('_', ' ')}")
        ax.set_xlabel(x_label)
        ax.set_ylabel("PSNR (dB)")
        if x_key == "rooms":
            ax.set_xscale("log", base=2)
            ax.set_xticks(x, [str(v) for v in x])
        ax.grid(alpha=0.3)
    axes[0].set_title(f"all {most} rooms, budgets of {', '.join(str(b) for b in report['budgets'])} steps", fontsize=9)
    axes[1].set_title(f"{steps} steps each", fontsize=9)
    axes[1].legend(fontsize=8)
    fig.suptitle("LightNet on held-out test rooms against training compute and data (95 % intervals over views)")
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rooms", type=int, nargs="+", default=[63, 126, 252])
    p.add_argument("--steps", type=int, default=1260, help="every room count's budget (tiny: 20 epochs x 63)")
    p.add_argument("--budgets", type=int, nargs="*", default=[315, 630], help="steps on all rooms, beside --steps")
    add_held_out_options(p, "learning_curve")
    a = p.parse_args(argv)
    apply_threads(a.threads)
    report = run(a.rooms, a.steps, a.budgets, a.seed, a.data_dir, a.resamples, a.override, a.edit_override)
    print(publish(a.name, report, plot))


if __name__ == "__main__":
    main()
