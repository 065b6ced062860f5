"""`tracking.uri=http://...`: a stage run against an MLflow tracking server (started here on 127.0.0.1)
lands on the server with its metrics, and its artifacts in the server's artifact store, not on disk
beside the client."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tests.conftest import compose_cfg, free_port, wait_for_http

pytestmark = pytest.mark.slow


def test_a_stage_runs_against_a_tracking_server(micro_root, tmp_path):
    from mlflow.tracking import MlflowClient

    from pipeline.runs.preprocess import run

    session_uri = os.environ["MLFLOW_TRACKING_URI"]  # set_tracking_uri also rewrites the variable
    port = free_port()
    server_dir = tmp_path / "server"
    server_dir.mkdir()
    env = {**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
    env.pop("MLFLOW_TRACKING_URI", None)
    server = subprocess.Popen(
        [sys.executable, "-m", "mlflow", "server", "--host", "127.0.0.1", "--port", str(port), "--workers", "1"]
        + ["--backend-store-uri", f"sqlite:///{server_dir / 'mlflow.db'}"]
        + ["--artifacts-destination", str(server_dir / "artifacts")],
        env=env,
        cwd=server_dir,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    uri = f"http://127.0.0.1:{port}"
    try:
        wait_for_http(f"{uri}/health", 120, "mlflow server")
        cfg = compose_cfg(
            "preprocess",
            [
                "profile=micro",
                f"data.interiorverse.generated_root={micro_root}",
                "ood.root=null",
                f"out_dir={tmp_path / 'out'}",
                f"report_dir={tmp_path / 'report'}",
                f"tracking.uri={uri}",
                "tracking.experiment=server-check",
                "progress=false",
            ],
        )
        metrics = run(cfg)
        client = MlflowClient(tracking_uri=uri)
        exp = client.get_experiment_by_name("server-check")
        runs = client.search_runs([exp.experiment_id])
        assert [r.info.run_name for r in runs] == ["preprocess-micro"]
        logged = runs[0].data.metrics
        assert logged and all(
            logged[k.replace("/", ".")] == pytest.approx(v) for k, v in metrics.items() if "/" not in k
        )
        assert [a.path for a in client.list_artifacts(runs[0].info.run_id, "reports")]
        assert exp.artifact_location.startswith("mlflow-artifacts:")  # the server's store, not this disk
        assert any((server_dir / "artifacts").rglob("metrics.json"))
    finally:
        import mlflow

        os.environ["MLFLOW_TRACKING_URI"] = session_uri  # later tests in this process: the session store
        mlflow.set_tracking_uri(session_uri)
        server.terminate()
        server.wait(timeout=30)
