"""Both networks on the out-of-distribution test set (`synthesize`'s `ood` rooms: another style, never
trained on) beside the in-distribution synthetic test split, scored by the same code on both (the
`evaluate` stage's `synthetic` and `synthetic_ood` entries, `runs.evaluate.out_of_distribution`).

- MaterialNet: each view's map errors (`metrics.synthetic.material_metrics`) and every trivial baseline's
  (`MaterialBaselines`, fitted on the in-distribution training split: what a model that learned nothing
  would reach), and per (baseline, map) the ratio model / baseline of their means over views with a
  bootstrap interval that resamples views (`ratio_bootstrap`): below 1, better than the baseline.
- LightNet: `train_lighting`'s test metrics per view (light errors at every probe texel, the re-render
  PSNR) and the content-blind baselines' and probe oracles' on the same views and draws
  (`baseline_metrics`), and LightNet minus each of them on every metric, paired by view.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import DataLoader

from pipeline.data.datasets import ShardDataset, collate_views
from pipeline.metrics.bootstrap import paired_bootstrap, ratio_bootstrap
from pipeline.metrics.synthetic import material_metrics
from pipeline.systems.material_baselines import BASELINE_MAPS, MaterialBaselines

SPLITS = {"synthetic": "test", "synthetic_ood": "test"}  # entry -> split of its preprocess root


@torch.no_grad()
def material_view_rows(net, dataset: ShardDataset, baselines: MaterialBaselines) -> list[dict]:
    """One row per view: `id`, the model's map errors `model/<metric>` and each baseline's
    `<baseline>/<metric>` (the metric functions of the synthetic test)."""
    net.eval()
    rows = []
    for batch in DataLoader(dataset, batch_size=4, collate_fn=collate_views):
        model = material_metrics(net(batch["im"]), batch)
        base = baselines.metrics(batch)
        for i, view in enumerate(batch["id"]):
            row = {"id": view, **{f"model/{k}": float(v[i]) for k, v in model.items()}}
            row.update({k: float(v[i]) for k, v in base.items()})
            rows.append(row)
    return rows


def material_summary(rows: list[dict], resamples: int, seed: int) -> dict[str, float]:
    """Means of the model's and the baselines' errors over views and, per (baseline, map), the ratio of
    means model / baseline with its interval (`gate/<baseline>/<metric>`, `_lo`, `_hi`). A view whose
    value is not finite (no valid pixel of a map) is left out of that metric."""
    out = {}
    keys = [k for k in rows[0] if k != "id"]
    for k in keys:
        values = np.array([r[k] for r in rows], np.float64)
        out[k] = float(values[np.isfinite(values)].mean())
    for name, metrics in BASELINE_MAPS.items():
        for metric in metrics:
            a = np.array([r[f"model/{metric}"] for r in rows], np.float64)
            b = np.array([r[f"{name}/{metric}"] for r in rows], np.float64)
            ok = np.isfinite(a) & np.isfinite(b)
            ci = ratio_bootstrap(a[ok], b[ok], resamples, seed)
            out[f"gate/{name}/{metric}"] = ci["ratio"]
            out[f"gate/{name}/{metric}_lo"] = ci["lo"]
            out[f"gate/{name}/{metric}_hi"] = ci["hi"]
    return out


@torch.no_grad()
def lighting_view_rows(system, dataset: ShardDataset, constants) -> list[dict]:
    """One row per view: `id`, LightNet's test metrics (`model/<metric>`) and the baselines'
    (`<baseline>/<metric>`) on the same views and directions, as `train_lighting`'s test step scores them."""
    from pipeline.systems.lighting_baselines import baseline_metrics

    system.eval()
    rows = []
    for batch in DataLoader(dataset, batch_size=4, collate_fn=collate_views):
        views = [{"id": view} for view in batch["id"]]
        system.evaluate_batch(batch, views)
        baseline_metrics(batch, constants, system, views)
        for view in views:  # the model's own columns carry no '/', the baselines' are `<baseline>/<metric>`
            scores = {(k if "/" in k else f"model/{k}"): v for k, v in view.items() if k != "id"}
            rows.append({"id": view["id"], **scores})
    return rows


def lighting_summary(rows: list[dict], resamples: int, seed: int) -> dict[str, float]:
    """Means over views of every column, and LightNet minus every other predictor of the rows (the
    constants and the probe oracles) on each metric both score, paired by view over the views where the
    difference is finite (a view without free probes scores no free metric): `minus_<predictor>/<metric>`
    with `_lo`, `_hi` (95 % bootstrap over views) and `_n` (views scored). These are the intervals the
    results page prints; it computes none of its own."""
    out = {}
    for k in (k for k in rows[0] if k != "id"):
        values = np.array([r.get(k, np.nan) for r in rows], np.float64)
        if np.isfinite(values).any():
            out[k] = float(values[np.isfinite(values)].mean())
    for column in (k for k in rows[0] if k != "id" and not k.startswith("model/")):
        who, metric = column.split("/", 1)
        if f"model/{metric}" in rows[0]:
            diff = [r[f"model/{metric}"] - r.get(column, np.nan) for r in rows]
            out.update(paired_keys(f"minus_{who}/{metric}", diff, resamples, seed))
    return out


def paired_keys(key: str, diff, resamples: int, seed: int) -> dict[str, float]:
    """Paired differences (n,) as published metrics, over the finite ones (nothing when none is): `<key>`
    (their mean), `<key>_n` (units) and, from two units on, `<key>_lo`, `<key>_hi` (95 % bootstrap; a
    metric file holds finite numbers only)."""
    d = np.asarray(diff, np.float64)
    d = d[np.isfinite(d)]
    if not len(d):
        return {}
    ci = paired_bootstrap(d, resamples, seed)
    out = {key: ci["diff"], f"{key}_n": ci["n"]}
    if np.isfinite(ci["lo"]):
        out.update({f"{key}_lo": ci["lo"], f"{key}_hi": ci["hi"]})
    return out
