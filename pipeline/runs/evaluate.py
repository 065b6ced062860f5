"""Stage `evaluate`: the trained and the fine-tuned MaterialNet on IIW-test (WHDR), NYUv2-test (normal angle,
depth si-RMSE) and the synthetic test split, with the paper's protocols (docs/design.md, section 6), through
`Trainer.test` (`systems.evaluation`). Data sources as in `finetune`; stand-in numbers are never labelled
IIW or NYUv2.

Writes under `report_dir`: metrics.json, table.md (laid out like the paper's table), sources.json,
per-image CSVs `<model>_iiw.csv` and `<model>_nyuv2.csv`, the synthetic splits' per-view CSVs
`<model>_<entry>_views.csv` (each model scored once per split, beside its baselines:
`synthetic_splits`), and `<model>_nyuv2_cases.png` (best and worst images). A per-image score that is not
finite is left out of its mean and counted in `<model>/<bench>/nonfinite`.

Every interval the results page prints for these models is published here (95 %, `bootstrap` resamples of
images, seed `seed`): each mean's (`<model>/<bench>/<metric>_lo`, `_hi`), the fine-tuned model minus the
trained one paired by image (`finetuned_minus_trained/<bench>/<metric>`, `_lo`, `_hi`, `_n`), each gate
ratio's and LightNet minus every other predictor (`systems.out_of_distribution`).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from pipeline.data.formats.photo import srgb8_to_linear
from pipeline.data.standins import benchmark_roots
from pipeline.metrics import normal as normal_metrics
from pipeline.metrics.bootstrap import mean_bootstrap
from pipeline.models.material_net import load_material_export, predict_maps
from pipeline.systems.evaluation import BENCHMARKS, BenchmarkEvaluation, NYUTest, test_loaders
from pipeline.systems.out_of_distribution import paired_keys
from pipeline.systems.trainer import stage_trainer
from pipeline.tracking import publish, stage_run
from pipeline.tracking.figures import ranked_cases

# Zhu et al. 2022, Table (NYUv2 normals and depth, IIW albedo): published numbers, for reference only
PAPER_TABLE = {
    "Li et al. 2020": {"normal_deg": 24.12, "depth_si": 0.160, "whdr": 15.9},
    "Wang et al. 2021": {"normal_deg": 22.95, "depth_si": 0.181, "whdr": 18.2},
    "Zhu et al. 2022 (paper)": {"normal_deg": 21.86, "depth_si": 0.155, "whdr": 15.5},
}


def _write_csv(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def markdown_table(results: dict, sources: dict) -> str:
    iiw_src, nyu_src = sources["iiw"], sources["nyuv2"]
    lines = [
        "# MaterialNet on the real-data benchmarks",
        "",
        f"Data: NYUv2 columns scored on **{nyu_src}**, WHDR on **{iiw_src}**"
        + (
            " (stand-ins built from synthetic views: not comparable with the published rows)."
            if "standin" in nyu_src + iiw_src
            else "."
        ),
        "",
        *(
            [
                "The stand-ins are built from the synthetic test views and `finetune` trains on their train parts,",
                "so the fine-tuned model's synthetic-test numbers below are not held out.",
                "",
            ]
            if "standin" in nyu_src + iiw_src
            else []
        ),
        f"| Method | Normal Angular Error ({nyu_src}) | Depth si-MSE ({nyu_src}) | WHDR % ({iiw_src}, gamma) "
        "| source |",
        "|---|---|---|---|---|",
    ]
    for name, r in results.items():
        lines.append(
            f"| ours: {name} | {r['nyu/normal_deg']:.2f}° | {r['nyu/depth_si']:.3f} | {r['iiw/whdr_gamma']:.1f} "
            "| measured here |"
        )
    for name, r in PAPER_TABLE.items():
        lines.append(
            f"| {name} | {r['normal_deg']:.2f}° | {r['depth_si']:.3f} | {r['whdr']:.1f} | published (NYUv2 / IIW) |"
        )
    lines += [
        "",
        "Protocols (docs/design.md, section 6): normals = per-image mean angle over the valid mask, then the mean over",
        "images (prediction not renormalised after resizing); depth = per-image sqrt of the scale-invariant log",
        "error over 1-10 m, mean over images; WHDR on R^(1/2.2), delta 0.1, mean over images.",
        "",
    ]
    for name, r in results.items():
        lines.append(
            f"- {name}: WHDR linear {r['iiw/whdr_linear']:.1f} %, pooled normal median "
            f"{r['nyu/pooled_median']:.1f}°, AbsRel {r['nyu/abs_rel']:.3f}, delta<1.25 {r['nyu/delta_1.25']:.3f}, "
            f"synthetic normal {r['synthetic/normal_angle_deg']:.1f}°, albedo MSE {r['synthetic/albedo_mse']:.4f}"
        )
    return "\n".join(lines) + "\n"


def finite_means(rows: list[dict], skip: tuple = ("id", "index")) -> tuple[dict[str, float], int]:
    """Mean of every score column over the rows where it is finite, and the number of rows with any
    non-finite score (reported as `nonfinite`, never dropped unseen). A column with no finite value is
    refused: its mean would be undefined."""
    keys = [k for k in rows[0] if k not in skip]
    bad = sum(any(not np.isfinite(r[k]) for k in keys) for r in rows)
    means = {}
    for k in keys:
        vals = [r[k] for r in rows if np.isfinite(r[k])]
        if not vals:
            raise ValueError(f"evaluate: every per-image {k!r} is non-finite ({len(rows)} images)")
        means[k] = float(np.mean(vals))
    return means, bad


def mean_intervals(rows: list[dict], resamples: int, seed: int, skip: tuple = ("id", "index")) -> dict[str, float]:
    """Per score column, the 95 % bootstrap interval over images of its mean over the finite values
    (`<metric>_lo`, `_hi`; none from fewer than two images); the mean itself is `finite_means`'."""
    out = {}
    for k in (k for k in rows[0] if k not in skip):
        values = np.array([r[k] for r in rows], np.float64)
        values = values[np.isfinite(values)]
        ci = mean_bootstrap(values, resamples, seed) if len(values) else {"lo": float("nan")}
        if np.isfinite(ci["lo"]):  # under two images there is no spread to resample: no interval
            out.update({f"{k}_lo": ci["lo"], f"{k}_hi": ci["hi"]})
    return out


def paired_intervals(
    before: list[dict], after: list[dict], resamples: int, seed: int, skip: tuple = ("id", "index")
) -> dict[str, float]:
    """`after` minus `before` per score column, paired by image (both score the same images in the same
    order, else nothing: the difference of two means over different images is no paired figure), over
    the images where both are finite: `<metric>` with `_lo`, `_hi` (95 % bootstrap) and `_n`
    (`paired_keys`)."""
    ids = [k for k in before[0] if k in skip][:1]
    if len(before) != len(after) or any(a[k] != b[k] for a, b in zip(before, after, strict=True) for k in ids):
        return {}
    out = {}
    for k in (k for k in before[0] if k not in skip and k in after[0]):
        out.update(paired_keys(k, [b[k] - a[k] for a, b in zip(before, after, strict=True)], resamples, seed))
    return out


def case_panels(net, meta, nyu: NYUTest, rows: list[dict], key: str, k: int) -> list[dict]:
    """Arrays for the best and worst `k` NYUv2 test images by rows[key] (lower is better): input photo,
    ground-truth and predicted normals, ground-truth and median-scaled predicted depth (m)."""
    ranked = sorted((r for r in rows if np.isfinite(r[key])), key=lambda r: r[key])
    picks = [("best", r) for r in ranked[:k]] + [("worst", r) for r in ranked[::-1][:k]]
    panels = []
    for tag, r in picks:
        item = nyu[nyu.indices.index(r["index"])]
        maps = predict_maps(net, meta, srgb8_to_linear(item["photo"]))
        d = maps["depth"] / 1000.0
        d = d * np.median(item["depth"]) / max(float(np.median(d)), 1e-9)
        panels.append(
            {
                "label": f"{tag} #{r['index']}\n{key}={r[key]:.1f}",
                "photo": item["photo"],
                "normal_gt": np.clip(item["normal"] * 0.5 + 0.5, 0, 1) * item["valid"][..., None],
                "normal_pred": np.clip(maps["normal"] * 0.5 + 0.5, 0, 1),
                "depth_gt": item["depth"],
                "depth_pred": d,
            }
        )
    return panels


def light_system(profile: str, material_path: str, light_path: str, seed: int, overrides=()):
    """`train_lighting`'s LightingSystem under `profile` and `overrides` (predicted G-buffers from the
    MaterialNet export at `material_path`) holding the LightNet export at `light_path`, whose options must
    be the profile's (`initialise_from_export`)."""
    from pipeline.systems.lighting_training import build_system, initialise_from_export
    from pipeline.tracking.compose import compose

    cfg = compose(
        "train_lighting", [f"profile={profile}", f"seed={seed}", f"material_path={material_path}", *overrides]
    )
    system = build_system(cfg)
    initialise_from_export(system, light_path)
    return system


def synthetic_splits(cfg: DictConfig, report: Path) -> tuple[dict[str, float], dict[str, list[dict]]]:
    """Every MaterialNet model of `cfg.models` on the synthetic test split and, with `cfg.ood_data_dir`,
    the out-of-distribution one (`systems.out_of_distribution`), beside the trivial baselines fitted on the
    training split, once per model and split; with the out-of-distribution split, the LightNet export
    `cfg.light_path` on both. Returns the metrics (`<model>/<entry>/...`, `lightnet/<entry>/...` for entry
    synthetic and synthetic_ood) and each model's synthetic-test rows; the per-view rows go to
    `<model>_<entry>_views.csv`."""
    from torch.utils.data import DataLoader

    from pipeline.data.datasets import ShardDataset, collate_views
    from pipeline.systems import out_of_distribution as ood
    from pipeline.systems.lighting_baselines import mean_training_radiance
    from pipeline.systems.material_baselines import MaterialBaselines

    resamples, seed = int(cfg.bootstrap), int(cfg.seed)
    train = ShardDataset(cfg.data_dir, "train", lighting=True)
    loader = DataLoader(train, batch_size=16, collate_fn=collate_views)
    material_baselines = MaterialBaselines.fit(loader)
    roots = {"synthetic": cfg.data_dir}
    if cfg.ood_data_dir is not None:
        roots["synthetic_ood"] = cfg.ood_data_dir
    sets = {entry: ShardDataset(root, ood.SPLITS[entry], lighting=True) for entry, root in roots.items()}
    for entry, dataset in sets.items():
        if len(dataset) == 0:
            raise ValueError(f"the {entry} test split is empty ({roots[entry]})")
    out, synthetic_rows = {}, {}
    for name, path in cfg.models.items():
        net, _ = load_material_export(path)
        for entry, dataset in sets.items():
            rows = ood.material_view_rows(net, dataset, material_baselines)
            _write_csv(report / f"{name}_{entry}_views.csv", rows)
            summary = ood.material_summary(rows, resamples, seed)
            out.update({f"{name}/{entry}/{k.removeprefix('model/')}": v for k, v in summary.items()})
            if entry == "synthetic":
                synthetic_rows[name] = rows
    if cfg.ood_data_dir is None:
        return out, synthetic_rows
    constants = mean_training_radiance(loader)
    system = light_system(str(cfg.profile_name), cfg.models.trained, cfg.light_path, seed, list(cfg.light_overrides))
    for entry, dataset in sets.items():
        rows = ood.lighting_view_rows(system, dataset, constants)
        _write_csv(report / f"lightnet_{entry}_views.csv", rows)
        summary = ood.lighting_summary(rows, resamples, seed)
        out.update({f"lightnet/{entry}/{k.removeprefix('model/')}": v for k, v in summary.items()})
    return out, synthetic_rows


def model_columns(rows: list[dict]) -> list[dict]:
    """The model's own scores of `material_view_rows` rows ({id, <metric>}), without the baselines'."""
    return [
        {"id": r["id"], **{k.removeprefix("model/"): v for k, v in r.items() if k.startswith("model/")}} for r in rows
    ]


def run(cfg: DictConfig) -> dict[str, float]:
    import mlflow

    # the same settings as finetune's (conf/standin): a mismatch is refused, never rebuilt
    bench = benchmark_roots(
        cfg.iiw_root, cfg.nyuv2_root, cfg.standin_dir, cfg.data_dir, int(cfg.seed), cfg.standin, build=False
    )
    sources = {"iiw": bench["iiw"][1], "nyuv2": bench["nyuv2"][1]}
    report = Path(cfg.report_dir)
    results, metrics, scored = {}, {}, {}
    resamples = int(cfg.bootstrap)
    with stage_run("evaluate", cfg, tags={"data_source": f"{sources['iiw']}+{sources['nyuv2']}+synthetic"}) as run:
        mlflow.log_params({"iiw_source": sources["iiw"], "nyuv2_source": sources["nyuv2"]})
        loaders = test_loaders(bench["iiw"][0], bench["nyuv2"][0])  # read once, used per model
        split_metrics, synthetic_rows = synthetic_splits(cfg, report)
        metrics.update(split_metrics)
        nyu = loaders[BENCHMARKS.index("nyuv2")].dataset
        for name, path in cfg.models.items():
            net, meta = load_material_export(path)
            system = BenchmarkEvaluation(net, meta, name)
            trainer = stage_trainer(
                run, {"accelerator": "cpu", "devices": 1, "deterministic": True}, report, (), bool(cfg.progress)
            )
            trainer.test(system, dataloaders=loaders, verbose=False)
            r = {}
            scored[name] = {"nyu" if key == "nyuv2" else key: rows for key, rows in system.rows.items()}
            scored[name]["synthetic"] = model_columns(synthetic_rows[name])
            for key, rows in system.rows.items():
                _write_csv(report / f"{name}_{key}.csv", rows)
            for prefix, rows in scored[name].items():
                means, bad = finite_means(rows)
                r.update({f"{prefix}/{k}": v for k, v in means.items()})
                r.update({f"{prefix}/{k}": v for k, v in mean_intervals(rows, resamples, int(cfg.seed)).items()})
                r[f"{prefix}/nonfinite"] = float(bad)
            r.update({f"nyu/{k}": v for k, v in normal_metrics.pooled_stats(system.pooled_angles).items()})
            results[name] = r
            metrics.update({f"{name}/{k}": v for k, v in r.items()})
            panels = case_panels(net, meta, nyu, system.rows["nyuv2"], "normal_deg", int(cfg.figure_cases))
            figure = ranked_cases(panels, report / f"{name}_nyuv2_cases.png")
            mlflow.log_artifact(str(figure), "figures")
        if {"trained", "finetuned"} <= set(scored):  # what fine-tuning changed, paired by image
            for bench, rows in scored["trained"].items():
                diff = paired_intervals(rows, scored["finetuned"][bench], resamples, int(cfg.seed))
                metrics.update({f"finetuned_minus_trained/{bench}/{k}": v for k, v in diff.items()})
        (report / "table.md").write_text(markdown_table(results, sources))
        (report / "sources.json").write_text(json.dumps(sources, indent=1) + "\n")
        publish(report, metrics)
        mlflow.log_artifacts(str(report), "evaluate")  # table, sources, per-image CSVs, figures
    return metrics
