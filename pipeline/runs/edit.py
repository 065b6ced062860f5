"""Stage `edit`: the lighting judged by what it is for. Objects inserted into, and materials edited in,
held-out views are re-rendered through the MC render layer with LightNet as the incident radiance, and
scored against Mitsuba renders of the same cases (written by `synthesize`, `pipeline.data.cases`).

Rows, each rendering the same pixels with the same samples per pixel (`scoring.spp`, one layer for all:
enough that no row's PSNR moves by more than 0.1 dB at 4x the samples, so noise, which penalises sharp
light, favours no row) and one seed per case (its own per view; rows on the same shading G-buffers draw
the same directions: every row of an object case, and the rows on predicted G-buffers of an edit and
the rows on ground-truth ones):
- `lightnet`: LightNet on the photo and the frozen MaterialNet's G-buffers (the method);
- `lightnet_gt_gbuffers`: LightNet on the ground-truth G-buffers (what a perfect MaterialNet would give);
- `constant`, `scaled_constant`: the content-blind lights of `train_lighting` (mean training radiance,
  and the same at the photo's exposure);
- `nearest_probe`: the ground-truth free-point probe nearest to the case as a distant environment map
  (the best a single environment map can do, given the true light at one point);
- `oracle`: Mitsuba's incident radiance for every sample ray (`data.synth.oracle`, `oracle.paths` path
  samples each), on the ground-truth G-buffers: validates the evaluation itself.
Objects bring their own exact G-buffers in every row; edits apply the new material to the predicted
G-buffers (rows on predictions) or the ground truth (`lightnet_gt_gbuffers`, `oracle`).

Writes `reports/edit/metrics.json` (means per material class and edit kind; LightNet minus every other
row with a paired bootstrap interval that resamples views, whose cases share a photo and predictions,
and a verdict: +1 better, -1 worse, 0 no difference or a single view), `cases.csv` (every case and
row), `timings.json`, `insertion.png` and `editing.png` (figure grids), all also to MLflow.

Objects are placed where they truly are (their ground-truth G-buffers) in every row, so the LightNet
row measures the light at that point as the method sees the scene: its SSRT marches the predicted depth
(metres through the export's depth scale; zero outside the view's valid mask, as in `train_lighting`).
"""

from __future__ import annotations

import csv
import time
from pathlib import Path

from omegaconf import DictConfig
from tqdm import tqdm

from pipeline.data import interiorverse as iv
from pipeline.systems.insertion_scoring import ROWS, figure_panels, score_view, stage_setup, summarise, view_context
from pipeline.tracking import publish, stage_run
from pipeline.tracking.figures import insertion_grid


def run(cfg: DictConfig) -> dict[str, float]:
    import mlflow

    report = Path(cfg.report_dir)
    shared = stage_setup(cfg)
    records, results, photo_of, seconds = [], [], {}, {row: 0.0 for row in ROWS}
    t_start = time.perf_counter()
    with stage_run("edit", cfg, tags={"data_source": "synthetic", "split": str(cfg.split)}):
        for scene, view in tqdm(shared["views"], desc="edit", unit="view", disable=not cfg.progress):
            ctx, cases = view_context(shared, scene, view, cfg)
            view_id = ctx["id"]
            photo_of[view_id] = (ctx["view"].photo, ctx["view"].scale, view_id)
            for res in score_view(ctx, cases, cfg):
                case = res["case"]
                res["view"] = view_id
                results.append(res)
                row = {"view": view_id, "case": case.name, "kind": case.kind, "label": case.label}
                row["pixels"] = len(case.pixel)
                row["support"] = case.description.get("support", case.description.get("target"))
                for name, sc in res["rows"].items():
                    row.update({f"{name}/{k}": v for k, v in sc.items()})
                for name, t in res["seconds"].items():
                    seconds[name] += t
                records.append(row)
        if not records:
            raise iv.DatasetError(f"{shared['root']}: the {cfg.split} views' case files list no case")
        metrics = summarise(records, int(cfg.bootstrap), int(cfg.seed))
        metrics["scoring_spp"] = float(cfg.scoring.spp)  # every row's samples per pixel
        report.mkdir(parents=True, exist_ok=True)
        with open(report / "cases.csv", "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(records[0]))
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
        n_cases = len(records)
        timings = {f"seconds_per_case/{row}": s / n_cases for row, s in seconds.items()}
        timings["wall_seconds"] = time.perf_counter() - t_start
        publish(report, metrics, artifacts=(report / "cases.csv",), timings=timings)
        for figure in figures:
            mlflow.log_artifact(str(figure), "figures")
    return metrics
