"""Hydra multirun: jobs write under their own sweep folders (never the pipeline's fixed outputs), are
named and tagged by their overrides, and nest under one MLflow parent run; with the joblib launcher
4 jobs run 2 at a time against the sqlite store and none is lost or half-written."""

from __future__ import annotations

import json

import mlflow
import pytest

from tests.conftest import run_stage_process

pytestmark = pytest.mark.slow


def _sweep(tmp_path, micro_root, experiment, *extra):
    return run_stage_process(
        "preprocess",
        ["-m", "profile=micro", "progress=false", f"data.interiorverse.generated_root={micro_root}", "ood.root=null"]
        + [
            f"tracking.experiment={experiment}",
            "hydra.sweep.dir=sweep",
            "preprocess.shard_size=2,4",
            "seed=0,1",
            *extra,
        ],
        tmp_path,
    )


def _check_sweep(tmp_path, experiment, log):
    assert "database is locked" not in log
    assert not (tmp_path / "outputs").exists() and not (tmp_path / "reports").exists()  # fixed paths untouched
    runs = mlflow.search_runs(experiment_names=[experiment], output_format="list")
    [parent] = [r for r in runs if r.data.tags.get("sweep") == "true"]
    children = [r for r in runs if r is not parent]
    assert len(children) == 4, [r.info.run_name for r in runs]
    assert {r.data.tags.get("mlflow.parentRunId") for r in children} == {parent.info.run_id}
    assert {r.info.status for r in (parent, *children)} == {"FINISHED"}
    for run in children:  # named by the job's overrides, not all alike `preprocess-micro`
        assert run.info.run_name.startswith("preprocess-micro ") and run.data.tags["overrides"] in run.info.run_name
    assert len({r.info.run_name for r in children}) == 4
    for run in children:
        job = run.data.tags["overrides"]
        assert "preprocess.shard_size=" in job and "seed=" in job
        subdir = next(
            p
            for p in (tmp_path / "sweep").iterdir()
            if (p / ".hydra" / "overrides.yaml").exists() and _job_overrides(p) == job.split()
        )
        metrics = json.loads((subdir / "reports" / "preprocess" / "metrics.json").read_text())  # whole JSON
        assert (subdir / "outputs" / "preprocess" / "manifest.json").is_file()
        assert metrics and all(run.data.metrics[k.replace("/", ".")] == pytest.approx(v) for k, v in metrics.items())
    return parent, children


def _job_overrides(job_dir):
    import yaml

    return yaml.safe_load((job_dir / ".hydra" / "overrides.yaml").read_text())


def _overlapping(runs) -> bool:
    spans = sorted((r.info.start_time, r.info.end_time) for r in runs)
    return any(b[0] < a[1] for a, b in zip(spans, spans[1:], strict=False))


def test_basic_launcher_jobs_write_their_own_folders(micro_root, tmp_path):
    log = _sweep(tmp_path, micro_root, "sweep-basic")
    _, children = _check_sweep(tmp_path, "sweep-basic", log)
    assert not _overlapping(children)  # one after another, in the launcher's process
    assert len({r.data.tags["process_id"] for r in children}) == 1


def test_joblib_launcher_runs_four_jobs_two_at_a_time(micro_root, tmp_path):
    log = _sweep(tmp_path, micro_root, "sweep-joblib", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2")
    parent, children = _check_sweep(tmp_path, "sweep-joblib", log)
    assert parent.data.tags["launcher"] == "JoblibLauncher"
    # two worker processes ran them (start-up can stagger them, so they need not overlap in time)
    assert len({r.data.tags["process_id"] for r in children}) == 2
