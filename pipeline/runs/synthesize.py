"""Stage `synthesize`: procedural rooms rendered with Mitsuba 3 into the InteriorVerse layout with lighting
ground truth -> outputs/synthesize, and an out-of-distribution test set of rooms in another style (`ood`:
other layouts, object shapes, materials and lights, never trained on; rooms `ood_0000`, ...) ->
outputs/synthesize_ood; counts ->
reports/synthesize/metrics.json (DVC; `ood/<count>` for the second set), timings ->
reports/synthesize/timings.json, both to MLflow; contact sheets samples.png and ood_samples.png."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from pipeline.data.synth.figures import contact_sheet
from pipeline.data.synth.generate import SynthConfig, synthesize
from pipeline.tracking import publish, stage_run

OOD_PREFIX = "ood"  # its rooms are ood_0000, ...: no view id names a room of the main set

PHASES = ("build", "camera", "gbuffer", "render", "denoise", "lighting", "cases", "write")


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


def ood_config(cfg: DictConfig) -> SynthConfig | None:
    """The out-of-distribution set's generator config: `ood.synth` merged over the stage's `synth`, with
    `ood.scenes` rooms; None when `ood.scenes` is 0."""
    ood = cfg.get("ood")
    if ood is None or int(ood.scenes) == 0:
        return None
    if int(ood.scenes) < 0:
        raise ValueError(f"ood.scenes={ood.scenes}: give 0 (no out-of-distribution set) or more")
    base, over = (OmegaConf.create(OmegaConf.to_container(c, resolve=True)) for c in (cfg.synth, ood.synth))
    merged = OmegaConf.merge(base, over, {"scenes": int(ood.scenes)})  # plain copies: new keys allowed
    return SynthConfig.from_dict(OmegaConf.to_container(merged))


def _sheet(out_dir, summary: dict, views: int, n: int, path: Path) -> Path:
    first = [(s, f"{v:03d}") for v in range(views) for s in sorted(r["scene"] for r in summary["scenes"])]
    return contact_sheet(out_dir, first[:n], path)


def run(cfg: DictConfig) -> dict[str, float]:
    import mlflow

    synth_cfg = SynthConfig.from_dict(OmegaConf.to_container(cfg.synth, resolve=True))
    ood_cfg = ood_config(cfg)  # checked before the long render
    report = Path(cfg.report_dir)
    with stage_run("synthesize", cfg, tags={"data_source": "synthetic"}):
        summary = synthesize(synth_cfg, cfg.out_dir, int(cfg.seed), progress=bool(cfg.progress))
        metrics, timings = synthesize_metrics(summary)
        mlflow.set_tag("mitsuba_variant", summary["variant"])
        n_sheet = int(cfg.contact_sheet_views)
        sheets = [_sheet(cfg.out_dir, summary, synth_cfg.views, n_sheet, report / "samples.png")]
        if ood_cfg is not None:
            seed = int(cfg.seed) + int(cfg.ood.seed_offset)
            ood = synthesize(ood_cfg, cfg.ood.out_dir, seed, progress=bool(cfg.progress), prefix=OOD_PREFIX)
            ood_metrics, ood_timings = synthesize_metrics(ood)
            metrics.update({f"ood/{k}": v for k, v in ood_metrics.items()})
            timings.update({f"ood/{k}": v for k, v in ood_timings.items()})
            sheets.append(_sheet(cfg.ood.out_dir, ood, ood_cfg.views, n_sheet, report / "ood_samples.png"))
        publish(report, metrics, timings=timings)
        for sheet in sheets:
            mlflow.log_artifact(str(sheet), "figures")
        mlflow.log_artifact(str(Path(cfg.out_dir) / "dataset.json"))
    return {**metrics, **timings}
