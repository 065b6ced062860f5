"""Stage `preprocess`: validates every view of an InteriorVerse-layout root, resizes (mask-aware area
filter) and writes shards + manifest -> outputs/preprocess, and the same for `synthesize`'s
out-of-distribution test set (`ood.root`, its test split only) -> outputs/preprocess_ood; counts ->
reports/preprocess/metrics.json (`ood/<count>` for the second set), durations ->
reports/preprocess/timings.json, both to MLflow; rejections -> rejected.json, rejected_ood.json."""

from __future__ import annotations

import json
from pathlib import Path

from omegaconf import DictConfig

from pipeline.data.preprocess import preprocess
from pipeline.tracking import publish, stage_run


def split_counts(manifest: dict) -> dict[str, float]:
    """The counts a preprocess manifest reports: views kept and rejected, pixels masked, views and scenes
    per split."""
    splits = manifest["splits"]
    return {
        "views_kept": sum(len(s["views"]) for s in splits.values()),
        "views_rejected": manifest["rejected_views"],
        "pixels_masked_as_inconsistent": manifest["fixed_pixels"],
        "lighting_available": int(manifest["lighting"]),
        **{f"{k}_views": len(v["views"]) for k, v in splits.items()},
        **{f"{k}_scenes": len(v["scenes"]) for k, v in splits.items()},
    }


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
        metrics = split_counts(result.manifest)
        timings = {"seconds": result.seconds}
        ood_root = cfg.ood.root
        if ood_root is not None:  # the out-of-distribution test set (`synthesize`'s ood): test split only
            if not Path(ood_root).is_dir():
                raise FileNotFoundError(
                    f"{ood_root}: no out-of-distribution set (ood.root); run `synthesize` or set ood.root=null"
                )
            ood = preprocess(
                ood_root,
                cfg.ood.out_dir,
                int(p.height),
                int(p.width),
                int(p.shard_size),
                float(p.max_inconsistent_fraction),
                None,
                progress=bool(cfg.progress),
                source="synthetic_ood",
                required=("test",),
            )
            (report / "rejected_ood.json").write_text(
                json.dumps({"source": "synthetic_ood", "root": str(ood_root), "rejected": ood.rejected}, indent=1)
                + "\n"
            )
            metrics.update({f"ood/{k}": v for k, v in split_counts(ood.manifest).items()})
            timings["ood_seconds"] = ood.seconds
        publish(report, metrics, (report / "rejected.json",), timings=timings)
        mlflow.log_artifact(str(Path(cfg.out_dir) / "manifest.json"))
    return {**metrics, **timings}
