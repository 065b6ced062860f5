"""The MLflow UI in a real browser: a run logged as a stage logs it (`tracking.publish`), served by
`mlflow ui` on 127.0.0.1 and opened in headless Debian chromium, shows its name, a metric and its figure."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import free_port, wait_for_http

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        CHROMIUM is None, reason="Debian's chromium is not installed (`make setup` installs it as root)"
    ),
]


def _dom(url: str) -> str:
    out = subprocess.run(
        [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=20000", "--dump-dom", url],
        capture_output=True,
        text=True,
        timeout=120,
    )
    return out.stdout


def test_mlflow_ui_shows_a_stage_run_its_metric_and_its_figure(tmp_path):
    import mlflow
    from matplotlib.figure import Figure

    from pipeline.tracking import publish

    uri = os.environ["MLFLOW_TRACKING_URI"]  # the session's sqlite store (tests/conftest.py)
    mlflow.set_tracking_uri(uri)
    # an experiment of its own with its artifacts in tmp_path (the default would be ./mlruns in the checkout)
    exp = mlflow.create_experiment(f"ui-check-{tmp_path.name}", artifact_location=(tmp_path / "artifacts").as_uri())
    mlflow.set_experiment(experiment_id=exp)
    fig = tmp_path / "insertion_ui_check.png"
    figure = Figure()
    figure.subplots().plot([0, 1], [0, 1])
    figure.savefig(fig)
    with mlflow.start_run(run_name="edit-uicheck", tags={"stage": "edit"}) as run:
        publish(tmp_path / "report", {"insert/all/lightnet/psnr": 17.25})
        mlflow.log_artifact(str(fig), "figures")
    exp_id, run_id = run.info.experiment_id, run.info.run_id
    port = free_port()
    env = {**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
    server = subprocess.Popen(
        [sys.executable, "-m", "mlflow", "ui", "--backend-store-uri", uri, "--host", "127.0.0.1", "--port", str(port)]
        + ["--workers", "1"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        base = f"http://127.0.0.1:{port}"
        wait_for_http(base, 60, "mlflow ui")
        overview = _dom(f"{base}/#/experiments/{exp_id}/runs/{run_id}")
        assert "edit-uicheck" in overview
        assert "insert.all.lightnet.psnr" in overview and "17.25" in overview
        artifacts = _dom(f"{base}/#/experiments/{exp_id}/runs/{run_id}/artifacts")
        assert "figures" in artifacts and "reports" in artifacts
    finally:
        server.terminate()
        server.wait(timeout=30)
    assert Path(fig).is_file()
