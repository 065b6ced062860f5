"""Experiment tracking: MLflow runs per stage execution and DVC metrics files."""

from pipeline.tracking.metrics_file import write_metrics
from pipeline.tracking.mlflow_run import project_root, stage_run, tracking_uri
from pipeline.tracking.publish import publish
from pipeline.tracking.sweep_paths import job_dir, register_resolvers

register_resolvers()  # before any stage config is resolved: every run module imports this package

__all__ = ["job_dir", "project_root", "publish", "stage_run", "tracking_uri", "write_metrics"]
