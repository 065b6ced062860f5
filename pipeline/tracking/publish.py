"""Publish a stage's metrics: `reports/<stage>/metrics.json` (DVC) and the open MLflow run, one call.

Timings are published beside them, never inside: `metrics.json` is hashed into dvc.lock, so a number that
changes from run to run would make a re-run of an unchanged stage look like a change.
`reports/<stage>/timings.json` (not a DVC metric) and MLflow hold them.
"""

from __future__ import annotations

from pathlib import Path

from pipeline.tracking.metrics_file import write_metrics


def mlflow_key(name: str) -> str:
    """A metric name MLflow accepts: '/' -> '.', '<' -> 'lt' (MLflow refuses '<'; '/' nests in its UI)."""
    return name.replace("/", ".").replace("<", "lt")


def publish(
    report_dir: str | Path, metrics: dict[str, float], artifacts: tuple = (), timings: dict[str, float] | None = None
) -> Path:
    """Write `<report_dir>/metrics.json` (and `timings.json` when `timings` are given), log every number
    to the active MLflow run (the same numbers: a non-finite value is refused by `write_metrics` before
    anything is logged) and log the files and `artifacts` (paths) under the run's `reports/`. Returns the
    metrics file."""
    import mlflow

    clash = set(metrics) & set(timings or {})
    if clash:
        raise ValueError(f"{report_dir}: {sorted(clash)} given both as metrics and as timings")
    path = write_metrics(Path(report_dir) / "metrics.json", metrics)
    files = [path]
    if timings:
        files.append(write_metrics(Path(report_dir) / "timings.json", timings))
    mlflow.log_metrics({mlflow_key(k): float(v) for k, v in {**metrics, **(timings or {})}.items()})
    for artifact in (*files, *artifacts):
        mlflow.log_artifact(str(artifact), "reports")
    return path
