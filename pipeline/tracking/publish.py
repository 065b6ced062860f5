"""Publish a stage's metrics: `reports/<stage>/metrics.json` (DVC) and the open MLflow run, one call."""

from __future__ import annotations

from pathlib import Path

from pipeline.tracking.metrics_file import write_metrics


def mlflow_key(name: str) -> str:
    """A metric name MLflow accepts: '/' -> '.', '<' -> 'lt' (MLflow refuses '<'; '/' nests in its UI)."""
    return name.replace("/", ".").replace("<", "lt")


def publish(report_dir: str | Path, metrics: dict[str, float], artifacts: tuple = ()) -> Path:
    """Write `<report_dir>/metrics.json`, log every metric to the active MLflow run (the same numbers:
    a non-finite value is refused by `write_metrics` before anything is logged) and log `artifacts`
    (paths) with the metrics file under the run's `reports/`. Returns the metrics file."""
    import mlflow

    path = write_metrics(Path(report_dir) / "metrics.json", metrics)
    mlflow.log_metrics({mlflow_key(k): float(v) for k, v in metrics.items()})
    for artifact in (path, *artifacts):
        mlflow.log_artifact(str(artifact), "reports")
    return path
