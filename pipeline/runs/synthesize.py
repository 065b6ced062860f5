"""Stage `synthesize`: procedural rooms rendered with Mitsuba 3 into the InteriorVerse layout with lighting
ground truth -> outputs/synthesize; counts -> reports/synthesize/metrics.json (DVC), timings ->
reports/synthesize/timings.json, both to MLflow."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from pipeline.data.synth.figures import contact_sheet
from pipeline.data.synth.generate import SynthConfig, synthesize
from pipeline.tracking import publish, stage_run

PHASES = ("build", "camera", "gbuffer", "render", "lighting", "cases", "write")


def synthesize_metrics(summary: dict) -> tuple[dict[str, float], dict[str, float]]:
    """(counts, timings) of a `synthesize` summary, flat for DVC/MLflow: the counts depend only on seed
    and config, the timings on the machine and the run."""
    scenes = summary["scenes"]
    views = sum(len(s["valid_fraction"]) for s in scenes)
    timings = {
        "wall_seconds": summary["wall_seconds"],
        "wall_seconds_per_view": summary["wall_seconds"] / max(views, 1),
        "workers": summary["workers"],
    }
    metrics = {
        "scenes": len(scenes),
        "views": views,
        "camera_redraws": sum(s["redraws"] for s in scenes),
        "valid_pixel_fraction": float(np.mean([f for s in scenes for f in s["valid_fraction"]])),
        "surface_probes": sum(s["surface_probes"] for s in scenes),
        "free_probes": sum(s["free_probes"] for s in scenes),
        "insertion_cases": sum(s.get("insertion_cases", 0) for s in scenes),
        "edit_cases": sum(s.get("edit_cases", 0) for s in scenes),
        "scenes_with_window": sum(s["windows"] > 0 for s in scenes),
        "llvm_variant": int(summary["variant"].startswith("llvm")),
        **{f"split_{k}_scenes": v for k, v in summary["splits"].items()},
    }
    for phase in PHASES:  # worker CPU-side seconds per view, summed over workers
        timings[f"{phase}_seconds_per_view"] = sum(s["seconds"].get(phase, 0.0) for s in scenes) / max(views, 1)
    return metrics, timings


def run(cfg: DictConfig) -> dict[str, float]:
    import mlflow

    synth_cfg = SynthConfig.from_dict(OmegaConf.to_container(cfg.synth, resolve=True))
    report = Path(cfg.report_dir)
    with stage_run("synthesize", cfg, tags={"data_source": "synthetic"}):
        summary = synthesize(synth_cfg, cfg.out_dir, int(cfg.seed), progress=bool(cfg.progress))
        metrics, timings = synthesize_metrics(summary)
        mlflow.set_tag("mitsuba_variant", summary["variant"])
        first_views = [
            (s, f"{v:03d}") for v in range(synth_cfg.views) for s in sorted(r["scene"] for r in summary["scenes"])
        ]
        sheet = contact_sheet(cfg.out_dir, first_views[: int(cfg.contact_sheet_views)], report / "samples.png")
        publish(report, metrics, timings=timings)
        mlflow.log_artifact(str(sheet), "figures")
        mlflow.log_artifact(str(Path(cfg.out_dir) / "dataset.json"))
    return {**metrics, **timings}
