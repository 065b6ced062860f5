"""Scale-out configs: `trainer=ddp_cpu` runs train_material as 2 gloo processes (one MLflow run, metrics
logged once, by rank 0; a valid model), `trainer=ddp` composes for GPU nodes, and the SLURM launcher
composes with the documented submission parameters (no SLURM here)."""

from __future__ import annotations

import os

import mlflow
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from tests.conftest import ROOT, compose_cfg, run_stage_process


@pytest.mark.slow
def test_ddp_cpu_trains_on_two_processes_and_rank_zero_alone_tracks(micro_shards, tmp_path):
    from pipeline.models.material_net import load_material_export

    experiment = "test-ddp-cpu"
    log = run_stage_process(
        "train_material",
        ["trainer=ddp_cpu", "profile=micro", "progress=false", f"data_dir={micro_shards}", "paths.outputs=outputs"]
        + [
            "paths.reports=reports",
            "system_metrics=false",
            "trainer.max_epochs=2",
            f"tracking.experiment={experiment}",
        ],
        tmp_path,
    )
    assert "Starting with 2 processes" in log and "distributed_backend=gloo" in log

    [run] = mlflow.search_runs(experiment_names=[experiment], output_format="list")  # rank 1 opened none
    assert run.info.status == "FINISHED"
    assert run.data.params["trainer.strategy"] == "ddp" and run.data.params["trainer.devices"] == "2"
    history = mlflow.MlflowClient().get_metric_history(run.info.run_id, "val/loss")
    assert len(history) == 2  # once per epoch, not once per process
    import json

    metrics = json.loads((tmp_path / "reports" / "train_material" / "metrics.json").read_text())
    assert metrics["epochs"] == 2 and all(np.isfinite(v) for v in metrics.values())
    assert run.data.metrics["test.albedo_mse"] == pytest.approx(metrics["test/albedo_mse"])

    net, meta = load_material_export(tmp_path / "outputs" / "train_material" / "model.pt")
    with torch.no_grad():
        pred = net(torch.rand(1, 3, *meta["input_size"]))
    assert all(torch.isfinite(v).all() for v in pred.values())


def test_ddp_config_composes_for_gpu_nodes():
    cfg = compose_cfg("train_lighting", ["trainer=ddp", "trainer.num_nodes=4"])
    t = OmegaConf.to_container(cfg.trainer, resolve=True)
    assert t["strategy"] == "ddp" and t["accelerator"] == "gpu" and t["devices"] == -1 and t["num_nodes"] == 4
    assert t["sync_batchnorm"] is True and t["max_epochs"] == cfg.epochs.train_lighting  # the stage's own keys stay


def test_slurm_launcher_composes_and_writes_the_expected_sbatch_script(tmp_path, monkeypatch):
    import submitit
    from hydra import compose, initialize_config_dir
    from hydra_plugins.hydra_submitit_launcher.submitit_launcher import SlurmLauncher

    overrides = [
        "hydra/launcher=invrender_slurm",
        "hydra.launcher.partition=gpu",
        "hydra.launcher.timeout_min=720",
        f"hydra.sweep.dir={tmp_path}/sweep",
        f"hydra.launcher.submitit_folder={tmp_path}/slurm/%j",
        "trainer=ddp",
        "trainer.num_nodes=2",
    ]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="train_material", overrides=overrides, return_hydra_config=True)
    launcher_cfg = OmegaConf.to_container(cfg.hydra.launcher, resolve=True)
    assert launcher_cfg.pop("_target_") == "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
    assert launcher_cfg["nodes"] == 2 and launcher_cfg["tasks_per_node"] == launcher_cfg["gpus_per_node"] == 8

    # the plugin's own launch() builds the submitit executor; the submission itself is where SLURM would
    # be needed, so it stops there and the sbatch script is rendered instead
    captured = {}

    class Submitted(Exception):
        pass

    def submit(self, fn, *args):
        captured.update(executor=self, jobs=len(args[0]))
        raise Submitted

    monkeypatch.setattr(submitit.AutoExecutor, "map_array", submit)
    fake = tmp_path / "bin" / "srun"  # submitit looks for srun before it builds a SLURM executor
    fake.parent.mkdir()
    fake.write_text("#!/bin/sh\nexit 1\n")
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", f"{fake.parent}:{os.environ['PATH']}")
    launcher = SlurmLauncher(**launcher_cfg)
    launcher.config = cfg
    with pytest.raises(Submitted):
        launcher.launch([["seed=0"], ["seed=1"]], initial_job_idx=0)
    assert captured["jobs"] == 2
    script = captured["executor"]._executor._make_submission_file_text("python -u job.py", "uid")
    for line in (
        "#SBATCH --partition=gpu",
        "#SBATCH --nodes=2",
        "#SBATCH --ntasks-per-node=8",
        "#SBATCH --gpus-per-node=8",
        "#SBATCH --cpus-per-task=8",
        "#SBATCH --mem=64GB",
        "#SBATCH --time=720",
        "#SBATCH --signal=USR2@120",
    ):
        assert line in script, script
