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
"""

from __future__ import annotations

import csv
import time
from pathlib import Path

from omegaconf import DictConfig
from tqdm import tqdm

from pipeline.data import interiorverse as iv
from pipeline.systems.insertion_scoring import (
    ROWS,
    figure_panels,
    ring_panels,
    ring_spp,
    row_spp,
    score_view,
    stage_setup,
    summarise,
    view_context,
)
from pipeline.systems.ring_scoring import RING_ROWS, summarise_ring
from pipeline.tracking import publish, stage_run
from pipeline.tracking.figures import insertion_grid


def run(cfg: DictConfig) -> dict[str, float]:
    import mlflow

    report = Path(cfg.report_dir)
    shared = stage_setup(cfg)
    records, results, photo_of, seconds = [], [], {}, {row: 0.0 for row in ROWS}
    rows_on_ring = tuple(row for row in ROWS if row in RING_ROWS) if ring_spp(cfg) else ()
    t_start = time.perf_counter()
    with stage_run("edit", cfg, tags={"data_source": "synthetic", "split": str(cfg.split)}):
        for scene, view in tqdm(shared["views"], desc="edit", unit="view", disable=not cfg.progress):
            ctx, cases = view_context(shared, scene, view, cfg)
            view_id = ctx["id"]
            photo_of[view_id] = (ctx["view"].photo, ctx["view"].scale, view_id)
            for res in score_view(ctx, cases, cfg, ring=bool(rows_on_ring)):
                case = res["case"]
                res["view"] = view_id
                results.append(res)
                row = {"view": view_id, "case": case.name, "kind": case.kind, "label": case.label}
                row["pixels"] = len(case.pixel)
                row["support"] = case.description.get("support", case.description.get("target"))
                for name, sc in res["rows"].items():
                    row.update({f"{name}/{k}": v for k, v in sc.items()})
                for name, t in res["seconds"].items():
                    seconds[name] = seconds.get(name, 0.0) + t
                records.append(row)
        if not records:
            raise iv.DatasetError(f"{shared['root']}: the {cfg.split} views' case files list no case")
        metrics = summarise(records, int(cfg.bootstrap), int(cfg.seed))
        metrics.update({f"scoring_spp/{row}": float(row_spp(cfg, row)) for row in ROWS})
        if rows_on_ring:
            metrics.update(summarise_ring(records, rows_on_ring, int(cfg.bootstrap), int(cfg.seed)))
            metrics["scoring_spp/ring"] = float(ring_spp(cfg))
        report.mkdir(parents=True, exist_ok=True)
        with open(report / "cases.csv", "w", newline="") as fh:
            # objects carry ring columns that edits lack (left empty there)
            writer = csv.DictWriter(fh, fieldnames=list(dict.fromkeys(k for r in records for k in r)))
            writer.writeheader()
            writer.writerows(records)
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
        n_cases = len(records)
        timings = {f"seconds_per_case/{row}": s / n_cases for row, s in seconds.items()}
        timings["wall_seconds"] = time.perf_counter() - t_start
        publish(report, metrics, artifacts=(report / "cases.csv",), timings=timings)
        for figure in figures:
            mlflow.log_artifact(str(figure), "figures")
    return metrics
