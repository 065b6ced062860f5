"""Stage functions for the data stages: config -> data work -> MLflow run + DVC metrics + figures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from pipeline.data.preprocess import preprocess
from pipeline.data.synth.figures import contact_sheet
from pipeline.data.synth.generate import SynthConfig, synthesize
from pipeline.tracking import stage_run, write_metrics

PHASES = ("build", "camera", "gbuffer", "render", "lighting", "write")


def synthesize_metrics(summary: dict) -> dict[str, float]:
    """Counts and timings of a `synthesize` summary, flat for DVC/MLflow."""
    scenes = summary["scenes"]
    views = sum(len(s["valid_fraction"]) for s in scenes)
    metrics = {
        "scenes": len(scenes),
        "views": views,
        "wall_seconds": summary["wall_seconds"],
        "wall_seconds_per_view": summary["wall_seconds"] / max(views, 1),
        "camera_redraws": sum(s["redraws"] for s in scenes),
        "valid_pixel_fraction": float(np.mean([f for s in scenes for f in s["valid_fraction"]])),
        "surface_probes": sum(s["surface_probes"] for s in scenes),
        "free_probes": sum(s["free_probes"] for s in scenes),
        "scenes_with_window": sum(s["windows"] > 0 for s in scenes),
        "llvm_variant": int(summary["variant"].startswith("llvm")),
        **{f"split_{k}_scenes": v for k, v in summary["splits"].items()},
    }
    for phase in PHASES:  # worker CPU-side seconds per view, summed over workers
        metrics[f"{phase}_seconds_per_view"] = sum(s["seconds"].get(phase, 0.0) for s in scenes) / max(views, 1)
    return metrics


def run_synthesize(cfg: DictConfig) -> dict[str, float]:
    import mlflow

    synth_cfg = SynthConfig.from_dict(OmegaConf.to_container(cfg.synth, resolve=True))
    report = Path(cfg.report_dir)
    with stage_run("synthesize", cfg, tags={"data_source": "synthetic"}):
        summary = synthesize(synth_cfg, cfg.out_dir, int(cfg.seed), progress=bool(cfg.progress))
        metrics = synthesize_metrics(summary)
        mlflow.set_tag("mitsuba_variant", summary["variant"])
        first_views = [
            (s, f"{v:03d}") for v in range(synth_cfg.views) for s in sorted(r["scene"] for r in summary["scenes"])
        ]
        sheet = contact_sheet(cfg.out_dir, first_views[: int(cfg.contact_sheet_views)], report / "samples.png")
        write_metrics(report / "metrics.json", metrics)
        mlflow.log_metrics(metrics)
        mlflow.log_artifact(str(sheet), "figures")
        mlflow.log_artifact(str(Path(cfg.out_dir) / "dataset.json"))
    return metrics


def run_preprocess(cfg: DictConfig) -> dict[str, float]:
    import mlflow

    ivc = cfg.data.interiorverse
    root = ivc.root or ivc.generated_root
    source = "interiorverse" if ivc.root else "synthetic"
    report = Path(cfg.report_dir)
    p = cfg.preprocess
    with stage_run("preprocess", cfg, tags={"data_source": source}):
        result = preprocess(
            root,
            cfg.out_dir,
            int(p.height),
            int(p.width),
            int(p.shard_size),
            float(p.max_inconsistent_fraction),
            ivc.fov_x_deg,
            progress=bool(cfg.progress),
            source=source,
        )
        report.mkdir(parents=True, exist_ok=True)
        (report / "rejected.json").write_text(
            json.dumps({"source": source, "root": str(root), "rejected": result.rejected}, indent=1) + "\n"
        )
        splits = result.manifest["splits"]
        metrics = {
            "views_kept": sum(len(s["views"]) for s in splits.values()),
            "views_rejected": result.manifest["rejected_views"],
            "pixels_masked_as_inconsistent": result.manifest["fixed_pixels"],
            "lighting_available": int(result.manifest["lighting"]),
            "seconds": result.seconds,
            **{f"{k}_views": len(v["views"]) for k, v in splits.items()},
            **{f"{k}_scenes": len(v["scenes"]) for k, v in splits.items()},
        }
        write_metrics(report / "metrics.json", metrics)
        mlflow.log_metrics(metrics)
        mlflow.log_artifact(str(report / "rejected.json"))
        mlflow.log_artifact(str(Path(cfg.out_dir) / "manifest.json"))
    return metrics
