"""Kill and resume: `train_material` and `train_lighting` killed with SIGKILL in the middle of an epoch
resume from last.ckpt with `resume=last`, finish with exactly the metrics (and DVC out and per-view
scores) of an uninterrupted run of the same seed, and continue the killed run's MLflow run rather than
opening a second one."""

import csv
import hashlib
import json
import os
import signal
import statistics
import subprocess
import sys
import uuid

import mlflow
import pytest

from tests.conftest import ROOT, compose_cfg

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("resume")]

EPOCHS, KILL_EPOCH = 3, 1  # killed after the first batch of epoch 1: last.ckpt holds the end of epoch 0

# Runs one stage in a fresh process with a callback that SIGKILLs that process mid-epoch: no handler,
# no atexit, no MLflow end_run; exactly what the OOM killer or a pre-empted node does.
KILLED_RUN = """
import json, os, signal, sys
sys.path.insert(0, {root!r})
from lightning.pytorch.callbacks import Callback
from tests.conftest import compose_cfg
import importlib

stage, overrides, kill_epoch = sys.argv[1], json.loads(sys.argv[2]), int(sys.argv[3])
runner = importlib.import_module(f"pipeline.runs.{{stage}}")
module = importlib.import_module({training!r}[stage])  # where the stage builds its trainer


class KillMidEpoch(Callback):
    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.current_epoch == kill_epoch and batch_idx == 0:
            os.kill(os.getpid(), signal.SIGKILL)


make_trainer = module.stage_trainer
module.stage_trainer = lambda run, kw, out, callbacks=(), progress=True: make_trainer(
    run, kw, out, [*callbacks, KillMidEpoch()], progress
)
runner.run(compose_cfg(stage, overrides))
raise SystemExit("the stage finished: it was never killed")
"""

TRAINING = {
    "train_material": "pipeline.systems.material_training",
    "train_lighting": "pipeline.systems.lighting_training",
}
STAGES = {
    "train_material": ["system_metrics=false"],
    "train_lighting": ["gbuffers=ground_truth"],
}


def _overrides(stage, shards, tmp, experiment):
    return [
        "profile=micro",
        f"data_dir={shards}",
        f"paths.outputs={tmp}/outputs",
        f"paths.reports={tmp}/reports",
        "progress=false",
        "batch_size=1",  # two training batches per epoch, so there is a middle to kill in
        f"trainer.max_epochs={EPOCHS}",
        f"tracking.experiment={experiment}",
        *STAGES[stage],
    ]


@pytest.fixture(scope="module")
def killed(micro_shards, tmp_path_factory):
    """kill(stage) -> (out root, overrides, rc, log, experiment): the stage killed mid-epoch in its own
    process, once per stage and module (on whichever worker asks first)."""
    done = {}

    def kill(stage):
        if stage not in done:
            tmp = tmp_path_factory.mktemp(f"killed_{stage}")
            experiment = f"test-resume-{stage}-{uuid.uuid4().hex[:8]}"  # unique even if two workers run it
            overrides = _overrides(stage, micro_shards, tmp, experiment)
            proc = subprocess.run(
                [
                    sys.executable,
                    "-c",
                    KILLED_RUN.format(root=str(ROOT), training=TRAINING),
                    stage,
                    json.dumps(overrides),
                    str(KILL_EPOCH),
                ],
                cwd=tmp,
                env=os.environ.copy(),
                capture_output=True,
                text=True,
                timeout=600,
            )
            done[stage] = (tmp, overrides, proc.returncode, proc.stdout + proc.stderr, experiment)
        return done[stage]

    return kill


@pytest.mark.parametrize("stage", list(STAGES))
def test_killed_stage_resumes_to_the_uninterrupted_result(killed, micro_shards, tmp_path, stage):
    import importlib

    module = importlib.import_module(f"pipeline.runs.{stage}")
    tmp, overrides, rc, log, experiment = killed(stage)
    assert rc == -signal.SIGKILL, f"{stage} was not killed (rc {rc}):\n{log[-3000:]}"
    [killed_run] = mlflow.search_runs(experiment_names=[experiment], output_format="list")
    assert killed_run.info.status == "RUNNING"  # SIGKILL left it open: nobody could end it
    assert not (tmp / "reports" / stage / "metrics.json").exists()  # no half-finished report

    resumed = module.run(compose_cfg(stage, [*overrides, "resume=last"]))
    reference = module.run(compose_cfg(stage, [*_overrides(stage, micro_shards, tmp_path, f"test-resume-ref-{stage}")]))
    # CPU, deterministic algorithms, the same seed, and every source of randomness restored from the
    # checkpoint (weights, optimiser, shuffling and augmentation generators, the light sampler): bitwise
    assert resumed == reference
    assert resumed["global_step"] == reference["global_step"] > 0
    # the DVC out: the same bytes (the checkpoints beside it name their runs and differ)
    assert _sha(tmp / "outputs" / stage / "model.pt") == _sha(tmp_path / "outputs" / stage / "model.pt")
    views = f"reports/{stage}/test_views.csv"
    assert (tmp / views).read_bytes() == (tmp_path / views).read_bytes()
    # test batches of one view: the stage's pooled-per-batch numbers are the means of the per-view ones
    for column, values in _views(tmp / views).items():
        assert statistics.fmean(values) == pytest.approx(resumed[_metric_key(stage, column)], rel=1e-5), column

    runs = mlflow.search_runs(experiment_names=[experiment], output_format="list")
    assert [r.info.run_id for r in runs] == [killed_run.info.run_id]  # continued, not a second half-run
    run = runs[0]
    assert run.info.status == "FINISHED"
    assert run.data.tags["resumed"] == "1" and run.data.tags["resumed.resume"] == "last"
    assert run.data.params["resume"] == "None"  # the first execution's params stay as they were logged
    key = next(k for k in resumed if k.endswith("test/render_psnr") or k == "test/albedo_mse")
    assert run.data.metrics[key.replace("/", ".")] == pytest.approx(resumed[key], rel=1e-6)
    client = mlflow.MlflowClient()
    steps = {m.step for m in client.get_metric_history(run.info.run_id, "epoch")}
    assert max(steps) >= reference["global_step"] - 1  # the history runs to the end of training


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _views(path) -> dict[str, list[float]]:
    """The score columns of a test_views.csv."""
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    return {k: [float(r[k]) for r in rows] for k in rows[0] if k != "id"}


def _metric_key(stage: str, column: str) -> str:
    """metrics.json's key for a test_views.csv column: `model/<m>` (train_material) and `<mode>/<m>`
    (train_lighting; `<mode>/untrained/<m>` before training) are the model's, the rest baselines'."""
    who, metric = column.split("/", 1)
    if stage == "train_material":
        return f"test/{metric}" if who == "model" else f"baseline/{column}"
    if who == "mixed":
        if metric.startswith("untrained/"):
            return f"mixed/untrained/test/{metric.removeprefix('untrained/')}"
        return "baseline/model/render_psnr_at_probes" if metric == "render_psnr_at_probes" else f"mixed/test/{metric}"
    return f"baseline/{column}"


def test_resume_refuses_a_truncated_or_foreign_checkpoint(killed, tmp_path):
    from pipeline.systems.trainer import resume_checkpoint

    tmp, *_ = killed("train_material")
    last = tmp / "outputs" / "checkpoints" / "train_material" / "last.ckpt"
    cut = tmp_path / "cut.ckpt"
    cut.write_bytes(last.read_bytes()[: last.stat().st_size // 2])
    with pytest.raises(ValueError, match="cut.ckpt is not a weights-only checkpoint"):
        resume_checkpoint(str(cut), tmp_path)
    import torch

    export = tmp_path / "export.pt"
    torch.save({"format": "invrender.material_net/1", "state_dict": {}}, export)
    with pytest.raises(ValueError, match="export.pt is not a Lightning training checkpoint"):
        resume_checkpoint(str(export), tmp_path)
    with pytest.raises(FileNotFoundError, match="resume=last: no checkpoint"):
        resume_checkpoint("last", tmp_path / "none")
    path, run_id = resume_checkpoint("last", last.parent)
    assert path == str(last) and run_id  # the checkpoint names the run it belongs to
