"""DVC around a real stage (`preprocess` on the micro data) in a scratch project: a `dvc repro` killed
mid-stage and re-run does not reuse the partial outputs; `dvc push` to a local remote and `dvc pull` in a
fresh clone restore the outputs with `dvc status` clean; `dvc exp run --queue` runs two experiments on
two workers, each tracked in MLflow under its experiment name."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import mlflow
import pytest

from tests.conftest import ROOT

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("dvc")]

DVC_YAML = """
stages:
  preprocess:
    cmd: >-
      python -m stages.preprocess profile=micro progress=false seed=${seed}
      preprocess.shard_size=${shard_size} tracking.experiment=dvc-workflows ood.root=null
    deps:
      - outputs/synthesize
    params:
      - seed
      - shard_size
    outs:
      - outputs/preprocess
    metrics:
      - reports/preprocess/metrics.json:
          cache: false
"""


def _env():
    bin_dir = Path(sys.executable).parent  # dvc and python of this environment first
    return {**os.environ, "PYTHONPATH": str(ROOT), "PATH": f"{bin_dir}:{os.environ['PATH']}", "DVC_NO_ANALYTICS": "1"}


def sh(cwd, *cmd, stderr=True, timeout=300):
    """Run a command in `cwd`; fail the test with its output unless it succeeds. Returns its output."""
    out = subprocess.run(list(cmd), cwd=cwd, env=_env(), capture_output=True, text=True, timeout=timeout)
    if out.returncode != 0:
        pytest.fail(f"{' '.join(cmd)} failed ({out.returncode}):\n{out.stdout[-2000:]}\n{out.stderr[-3000:]}")
    return out.stdout + (out.stderr if stderr else "")


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def project(micro_root, tmp_path_factory):
    """A git + DVC project whose one stage preprocesses the micro data, with a local-directory remote."""
    base = tmp_path_factory.mktemp("dvc")
    repo = base / "project"
    (repo / "outputs").mkdir(parents=True)
    sh(repo, "git", "init", "-q")
    sh(repo, "git", "config", "user.email", "ci@invrender")
    sh(repo, "git", "config", "user.name", "ci")
    sh(repo, "dvc", "init", "-q")
    shutil.copytree(micro_root, repo / "outputs" / "synthesize")
    sh(repo, "dvc", "add", "-q", "outputs/synthesize")
    (repo / "params.yaml").write_text("seed: 0\nshard_size: 4\n")
    (repo / "dvc.yaml").write_text(DVC_YAML)
    (repo / ".gitignore").write_text("/reports/preprocess/*.png\n")
    sh(repo, "dvc", "remote", "add", "-d", "store", str(base / "remote"))
    sh(repo, "git", "add", "-A")
    sh(repo, "git", "commit", "-qm", "project")
    return repo


@pytest.fixture(scope="module")
def interrupted(project):
    """`dvc repro` killed (with its stage) as soon as the stage starts writing, a leftover planted in the
    out as a killed writer would leave one, then `dvc repro` again. Returns what was seen after the kill."""
    out_dir = project / "outputs" / "preprocess"
    proc = subprocess.Popen(
        ["dvc", "repro"],
        cwd=project,
        env=_env(),
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 120
    while not out_dir.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    os.killpg(proc.pid, signal.SIGKILL)  # DVC and the stage together, mid-stage
    proc.wait()
    seen = {"started": out_dir.exists(), "locked": (project / "dvc.lock").exists()}
    if seen["started"]:
        (out_dir / "left-by-the-killed-run.bin").write_bytes(b"partial")
    sh(project, "dvc", "repro")
    sh(project, "git", "add", "-A")
    sh(project, "git", "commit", "-qm", "repro")
    return seen


def test_killed_repro_is_rerun_from_scratch_not_from_its_partial_outputs(project, interrupted):
    assert interrupted["started"], "the stage never started writing"
    assert not interrupted["locked"], "repro finished before the kill; nothing was interrupted"
    out_dir = project / "outputs" / "preprocess"
    assert not (out_dir / "left-by-the-killed-run.bin").exists()  # DVC removed the out before running
    manifest = json.loads((out_dir / "manifest.json").read_text())
    assert sum(len(v) for v in manifest["splits"].values()) > 0
    assert "up to date" in sh(project, "dvc", "status")


def test_push_then_pull_in_a_clean_clone_restores_the_outputs(project, interrupted, tmp_path):
    sh(project, "dvc", "push")
    clone = tmp_path / "clone"
    sh(tmp_path, "git", "clone", "-q", str(project), str(clone))
    assert not (clone / "outputs" / "preprocess").exists()
    sh(clone, "dvc", "pull")
    assert "up to date" in sh(clone, "dvc", "status")
    for name in ("preprocess", "synthesize"):
        assert _tree(clone / "outputs" / name) == _tree(project / "outputs" / name)


def test_queued_experiments_run_on_two_workers(project, interrupted):
    for size in (2, 3):
        sh(project, "dvc", "exp", "run", "--queue", "-S", f"shard_size={size}")
    sh(project, "dvc", "queue", "start", "-j", "2")
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        status = sh(project, "dvc", "queue", "status")
        if "Queued" not in status and "Running" not in status:
            break
        time.sleep(2)
    assert status.count("Success") == 2, status
    shown = json.loads(sh(project, "dvc", "exp", "show", "--json", stderr=False))
    exps = {
        rev["name"]: rev["data"] for commit in shown for exp in commit.get("experiments") or [] for rev in exp["revs"]
    }
    assert sorted(d["params"]["params.yaml"]["data"]["shard_size"] for d in exps.values()) == [2, 3]
    for data in exps.values():
        metrics = data["metrics"]["reports/preprocess/metrics.json"]["data"]
        assert metrics["views_kept"] > 0 and metrics["views_rejected"] == 0
    runs = mlflow.search_runs(experiment_names=["dvc-workflows"], output_format="list")
    tagged = {r.data.tags.get("dvc_exp_name"): r.info.status for r in runs}
    assert all(tagged.get(name) == "FINISHED" for name in exps), tagged
