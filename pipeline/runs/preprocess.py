"""Stage `preprocess`: validates every view of an InteriorVerse-layout root, resizes (mask-aware area
filter) and writes shards + manifest -> outputs/preprocess; counts -> reports/preprocess/metrics.json,
its duration -> reports/preprocess/timings.json, both to MLflow."""

from __future__ import annotations

import json
from pathlib import Path

from omegaconf import DictConfig

from pipeline.data.preprocess import preprocess
from pipeline.tracking import publish, stage_run


def run(cfg: DictConfig) -> dict[str, float]:
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
            **{f"{k}_views": len(v["views"]) for k, v in splits.items()},
            **{f"{k}_scenes": len(v["scenes"]) for k, v in splits.items()},
        }
        publish(report, metrics, (report / "rejected.json",), timings={"seconds": result.seconds})
        mlflow.log_artifact(str(Path(cfg.out_dir) / "manifest.json"))
    return {**metrics, "seconds": result.seconds}
