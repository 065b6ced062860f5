"""Lightning Trainer wiring shared by the training stages (systems is the only Lightning-aware layer):
the Trainer itself, where checkpoints live, resuming from a checkpoint, and the MLflow run id carried
inside checkpoints."""

from __future__ import annotations

from pathlib import Path

import torch

RUN_ID_KEY = "MLflowRunId"  # the callback's state key inside checkpoint["callbacks"]


def checkpoint_dir(out_dir: str | Path) -> Path:
    """Where a stage writing `out_dir` keeps its Lightning checkpoints: `<parent>/checkpoints/<name>`
    (outputs/train_material -> outputs/checkpoints/train_material; an ablation's
    outputs/ablate/full-s0 -> outputs/ablate/checkpoints/full-s0), beside the stage's DVC out and never
    inside it. A checkpoint holds the MLflow run id and absolute paths (the callbacks'
    `best_model_path`, `dirpath`), so inside the out it would give the out a new hash on every run of
    the same seed; the out keeps only what the same seed reproduces byte for byte (model.pt)."""
    out = Path(out_dir)
    return out.parent / "checkpoints" / out.name


def resume_checkpoint(resume: str | None, ckpt_dir: str | Path) -> tuple[str | None, str | None]:
    """(checkpoint path, MLflow run id stored in it) for a stage's `resume` setting: None/''/'none' ->
    (None, None); 'last' -> `<ckpt_dir>/last.ckpt` (`checkpoint_dir`); anything else is a path. The file is loaded
    weights-only first, so a checkpoint whose unpickling would run code is refused before Lightning
    sees it. Raises FileNotFoundError / ValueError naming the setting and the file."""
    if resume in (None, "", "none"):
        return None, None
    path = Path(ckpt_dir) / "last.ckpt" if resume == "last" else Path(resume)
    if not path.is_file():
        raise FileNotFoundError(f"resume={resume}: no checkpoint at {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # unpickling, zip and truncation errors differ by cause; all are refusals
        first = (str(exc).strip().splitlines() or [""])[0]
        raise ValueError(
            f"resume={resume}: {path} is not a weights-only checkpoint ({type(exc).__name__}: {first})"
        ) from exc
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt or "loops" not in ckpt:
        raise ValueError(f"resume={resume}: {path} is not a Lightning training checkpoint (no state_dict/loops)")
    run_id = ckpt.get("callbacks", {}).get(RUN_ID_KEY, {}).get("run_id")
    return str(path), run_id


def epoch_checkpoints(ckpt_dir: str | Path, monitor: str, mode: str):
    """(best, last): Lightning checkpoint callbacks writing `<ckpt_dir>/best.ckpt` (the best `monitor`
    value so far, `mode` "min" or "max") and `<ckpt_dir>/last.ckpt` (the end of every training epoch,
    whether or not it validated). The path of
    each file is its callback's `best_model_path`. Lightning's own `save_last` rewrites last.ckpt only in
    an epoch that also rewrote best.ckpt, so after an epoch without improvement last.ckpt held older
    weights and `resume=last` trained those epochs again."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    best = ModelCheckpoint(dirpath=ckpt_dir, filename="best", monitor=monitor, mode=mode, enable_version_counter=False)
    last = ModelCheckpoint(
        dirpath=ckpt_dir, filename="last", save_top_k=1, enable_version_counter=False, save_on_train_epoch_end=True
    )
    return best, last


def _run_id_callback(run_id: str):
    from lightning.pytorch.callbacks import Callback

    class MLflowRunId(Callback):
        """Writes the stage's MLflow run id into every checkpoint, so `resume` continues that run."""

        @property
        def state_key(self) -> str:
            return RUN_ID_KEY

        def state_dict(self) -> dict:
            return {"run_id": run_id}

        def load_state_dict(self, state_dict: dict) -> None:
            pass  # the run to continue was chosen before the Trainer existed (resume_checkpoint)

    return MLflowRunId()


def gather_rows(rows: list[dict]) -> list[dict]:
    """Per-view rows a test step collected (dicts with an "id"), from every process of a distributed run
    on every process, in the test split's order; one process: `rows` as they are. Lightning's distributed
    sampler deals the split's views round-robin (process r gets views r, r + W, ...) and repeats the first
    ones to even out the last batch; the repeats are dropped, the first row of each id kept."""
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return rows
    parts: list = [None] * dist.get_world_size()
    dist.all_gather_object(parts, rows)
    dealt = [part[i] for i in range(max(map(len, parts))) for part in parts if i < len(part)]
    seen, out = set(), []
    for row in dealt:
        if row["id"] not in seen:
            seen.add(row["id"])
            out.append(row)
    return out


def stage_trainer(run, trainer_kwargs: dict, root_dir, callbacks=(), progress: bool = True):
    """A Lightning Trainer logging to the stage's open MLflow run (`run`; None on ranks other than 0,
    which log nothing), with `root_dir` as Lightning's default root (the stage's `checkpoint_dir`, so
    nothing Lightning writes lands in the DVC out); its checkpoints carry the run id."""
    import lightning as L
    import mlflow
    from lightning.pytorch.loggers import MLFlowLogger

    class StageRunLogger(MLFlowLogger):
        """Lightning's MLflow logger, minus ending the run: Lightning ends it after every validate/fit/
        test call, which marked a stage FINISHED while it still ran (and after a kill). The stage's
        `stage_run` owns the run's status."""

        def finalize(self, status: str = "success") -> None:
            pass

    logger, extra = False, []
    if run is not None:
        logger = StageRunLogger(
            experiment_name=mlflow.get_experiment(run.info.experiment_id).name,
            tracking_uri=mlflow.get_tracking_uri(),
            run_id=run.info.run_id,
        )
        extra = [_run_id_callback(run.info.run_id)]
    return L.Trainer(
        **trainer_kwargs,
        logger=logger,
        callbacks=[*callbacks, *extra],
        default_root_dir=str(root_dir),
        enable_progress_bar=progress,
        enable_model_summary=False,
    )
