"""Lightning Trainer wiring shared by the training stages (systems is the only Lightning-aware layer)."""

from __future__ import annotations


def stage_trainer(run, trainer_kwargs: dict, out_dir, callbacks=(), progress: bool = True):
    """A Lightning Trainer logging to the stage's open MLflow run (`run`), writing under `out_dir`."""
    import lightning as L
    import mlflow
    from lightning.pytorch.loggers import MLFlowLogger

    logger = MLFlowLogger(
        experiment_name=mlflow.get_experiment(run.info.experiment_id).name,
        tracking_uri=mlflow.get_tracking_uri(),
        run_id=run.info.run_id,
    )
    return L.Trainer(
        **trainer_kwargs,
        logger=logger,
        callbacks=list(callbacks),
        default_root_dir=str(out_dir),
        enable_progress_bar=progress,
        enable_model_summary=False,
    )
