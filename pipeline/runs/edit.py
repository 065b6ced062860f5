"""Stage `edit`: the lighting judged by what it is for. Objects inserted into, and materials edited in,
held-out views are re-rendered through the MC render layer with LightNet as the incident radiance, and
scored against Mitsuba renders of the same cases (written by `synthesize`, `pipeline.data.cases`). The
rows (LightNet, the baselines, the oracle) and how each is rendered and scored:
`pipeline.systems.insertion_scoring`.

Writes `reports/edit/metrics.json` (means per material class and edit kind; LightNet minus every other
row with a paired bootstrap interval that resamples views, whose cases share a photo and predictions,
and a verdict: +1 better, -1 worse, 0 no difference or a single view; `scoring_spp/<row>`, each row's
samples per pixel), `cases.csv` (every case and row: `<row>/psnr`, `<row>/ssim`, `<row>/log_l1`, and for the
oracle, rendered in independent parts, `oracle/psnr_decorrelated` and `oracle/psnr_with_noise` beside its
noise-free `oracle/psnr`; for objects, `ring_<row>/psnr` and `ring_<row>/psnr_surround`, the room around
the object with and without differential rendering, `systems.ring_scoring`), `timings.json`,
`insertion.png`, `editing.png` and `shadows.png` (figure grids), all also to MLflow.

The out-of-distribution set's insertion cases (`ood.data_root`, its test split: rooms of another style
never trained on) are scored by the rows `ood.rows` (no oracle), with the same networks: `ood/`-prefixed
means and intervals in the same metrics, `ood_cases.csv`, `ood_insertion.png`.
"""

from __future__ import annotations

import csv
import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from pipeline.data import interiorverse as iv
from pipeline.systems.insertion_scoring import (
    FIGURE_ROWS,
    ROWS,
    figure_panels,
    ring_panels,
    ring_spp,
    row_spp,
    score_view,
    stage_setup,
    summarise,
    view_context,
    with_views,
)
from pipeline.systems.ring_scoring import RING_ROWS, summarise_ring
from pipeline.tracking import publish, stage_run
from pipeline.tracking.figures import insertion_grid


def score_set(shared: dict, cfg: DictConfig, rows: tuple, desc: str) -> dict:
    """Every case of the views `shared` lists (`stage_setup`), scored by `rows` (and on the ring under those
    of `RING_ROWS` when the stage scores one): {"records": one per case (view, case, kind, label, pixels,
    support, <row>/<score>), "results": `score_view`'s, "photo_of": view id -> (photo, scale, id),
    "seconds": row -> seconds, "metrics": the summary (`summarise`, `summarise_ring`)}."""
    records, results, photo_of, seconds = [], [], {}, {row: 0.0 for row in rows}
    rows_on_ring = tuple(row for row in rows if row in RING_ROWS) if ring_spp(cfg) else ()
    for scene, view in tqdm(shared["views"], desc=desc, unit="view", disable=not cfg.progress):
        ctx, cases = view_context(shared, scene, view, cfg, oracle="oracle" in rows)
        view_id = ctx["id"]
        photo_of[view_id] = (ctx["view"].photo, ctx["view"].scale, view_id)
        for res in score_view(ctx, cases, cfg, rows, ring=bool(rows_on_ring)):
            case = res["case"]
            res["view"] = view_id
            results.append(res)
            row = {"view": view_id, "case": case.name, "kind": case.kind, "label": case.label}
            row["pixels"] = len(case.pixel)
            row["support"] = case.description.get("support", case.description.get("target"))
            row["shape"] = case.description["kind"] if case.kind == "object" else ""
            for name, sc in res["rows"].items():
                row.update({f"{name}/{k}": v for k, v in sc.items()})
            for name, t in res["seconds"].items():
                seconds[name] = seconds.get(name, 0.0) + t
            records.append(row)
    if not records:
        raise iv.DatasetError(f"{shared['root']}: the {cfg.split} views' case files list no case")
    metrics = summarise(records, int(cfg.bootstrap), int(cfg.seed), rows)
    metrics.update({f"scoring_spp/{row}": float(row_spp(cfg, row)) for row in rows})
    if rows_on_ring:
        metrics.update(summarise_ring(records, rows_on_ring, int(cfg.bootstrap), int(cfg.seed)))
        metrics["scoring_spp/ring"] = float(ring_spp(cfg))
    return {"records": records, "results": results, "photo_of": photo_of, "seconds": seconds, "metrics": metrics}


def ood_rows(cfg: DictConfig) -> tuple:
    """The rows the out-of-distribution set is scored by (`ood.rows`): checked, the first `lightnet`;
    () when `ood.data_root` is null (not scored)."""
    ood = cfg.get("ood")
    if ood is None or ood.get("data_root") is None:
        return ()
    rows = tuple(OmegaConf.to_container(ood.rows, resolve=True))
    if not rows or rows[0] != "lightnet" or not set(rows) <= set(ROWS):
        raise ValueError(f"ood.rows={list(rows)}: the first must be lightnet, each one of {list(ROWS)}")
    return rows


def write_cases_csv(records: list[dict], path: Path) -> Path:
    with open(path, "w", newline="") as fh:
        # objects carry ring columns that edits lack (left empty there)
        writer = csv.DictWriter(fh, fieldnames=list(dict.fromkeys(k for r in records for k in r)))
        writer.writeheader()
        writer.writerows(records)
    return path


def run(cfg: DictConfig) -> dict[str, float]:
    import mlflow

    report = Path(cfg.report_dir)
    rows_ood = ood_rows(cfg)
    shared = stage_setup(cfg)
    if rows_ood:  # its data checked before the long scoring; its split is the only one it has
        ood_cfg = OmegaConf.merge(cfg, {"data_root": cfg.ood.data_root, "split": "test"})
        shared_ood = with_views(shared, cfg.ood.data_root, "test")
    t_start = time.perf_counter()
    with stage_run("edit", cfg, tags={"data_source": "synthetic", "split": str(cfg.split)}):
        main = score_set(shared, cfg, ROWS, "edit")
        metrics, records, results, photo_of = main["metrics"], main["records"], main["results"], main["photo_of"]
        report.mkdir(parents=True, exist_ok=True)
        artifacts = [write_cases_csv(records, report / "cases.csv")]
        figures = []
        n_fig = int(cfg.figure_cases)
        for kind, name, title in (
            ("object", "insertion.png", "object insertion"),
            ("edit", "editing.png", "material editing"),
        ):
            panels = figure_panels(results, photo_of, kind, n_fig)
            if panels:
                figures.append(insertion_grid(panels, report / name, f"{title}: ground truth and rows (crops)"))
        panels = ring_panels(results, photo_of, n_fig)
        if panels:
            title = "shadows and bounce light: Mitsuba, LightNet with and without differential rendering (ring PSNR)"
            figures.append(insertion_grid(panels, report / "shadows.png", title))
        timings = {f"seconds_per_case/{row}": s / len(records) for row, s in main["seconds"].items()}
        if rows_ood:
            t_ood = time.perf_counter()
            ood = score_set(shared_ood, ood_cfg, rows_ood, "edit (ood)")
            metrics.update({f"ood/{k}": v for k, v in ood["metrics"].items()})
            artifacts.append(write_cases_csv(ood["records"], report / "ood_cases.csv"))
            figure_rows = tuple(row for row in FIGURE_ROWS if row in rows_ood)
            panels = figure_panels(ood["results"], ood["photo_of"], "object", n_fig, figure_rows)
            if panels:
                title = "object insertion, out-of-distribution rooms: ground truth and rows (crops)"
                figures.append(insertion_grid(panels, report / "ood_insertion.png", title))
            timings["ood/wall_seconds"] = time.perf_counter() - t_ood
        timings["wall_seconds"] = time.perf_counter() - t_start
        publish(report, metrics, artifacts=tuple(artifacts), timings=timings)
        for figure in figures:
            mlflow.log_artifact(str(figure), "figures")
    return metrics
