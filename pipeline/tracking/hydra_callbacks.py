"""Hydra callback: a multirun sweep is one MLflow parent run with every job's stage run nested in it."""

from __future__ import annotations

import os
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from pipeline.tracking.mlflow_run import PARENT_ENV, activate_experiment, git_sha, project_root


class MLflowSweepParent(Callback):
    """Opens `<stage>-sweep` before the first job and closes it after the last. Jobs of Hydra's basic
    launcher run in this process, so `stage_run` sees the active parent and nests under it; jobs of
    other launchers (joblib workers, SLURM tasks) find its id in $INVRENDER_PARENT_RUN_ID, which their
    processes inherit."""

    def __init__(self) -> None:
        self._run = None

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        import mlflow

        activate_experiment(config)
        stage = str(OmegaConf.select(config, "stage") or "sweep")
        overrides = list(OmegaConf.select(config, "hydra.overrides.task") or [])
        self._run = mlflow.start_run(
            run_name=f"{stage}-sweep",
            tags={
                "stage": stage,
                "sweep": "true",
                "git_sha": git_sha(project_root()),
                "dvc_exp_name": os.environ.get("DVC_EXP_NAME", ""),
            },
        )
        mlflow.log_param("sweep_overrides", " ".join(overrides)[:6000])
        launcher = str(OmegaConf.select(config, "hydra.launcher._target_") or "")
        mlflow.set_tag("launcher", launcher.rsplit(".", 1)[-1])
        os.environ[PARENT_ENV] = self._run.info.run_id

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        import mlflow

        if self._run is not None:
            os.environ.pop(PARENT_ENV, None)
            mlflow.end_run()
            self._run = None
