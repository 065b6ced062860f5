"""Shared fixtures: Hydra Compose API, one MLflow sqlite store per test session, one micro dataset."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
from filelock import FileLock

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
LLVM = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"


def _threads_per_worker() -> int | None:
    """CPU threads for each xdist worker: the cores shared out, at least one (None outside xdist).

    Each worker's PyTorch (and the stage subprocesses it starts) would otherwise run an OpenMP team as
    wide as the machine; two such teams on two cores spin against each other and made small tensor
    tests up to 25x slower than alone."""
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if not workers:
        return None
    return max(1, (os.cpu_count() or 1) // int(workers))


THREADS = _threads_per_worker()
if THREADS is not None:  # before anything imports torch; inherited by subprocesses
    os.environ.setdefault("OMP_NUM_THREADS", str(THREADS))
    os.environ.setdefault("MKL_NUM_THREADS", str(THREADS))


def free_port() -> int:
    """A TCP port on 127.0.0.1 nothing listens on now (for servers a test starts)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for_http(url: str, seconds: float, what: str) -> None:
    """Poll `url` every 0.5 s until it answers; fail the test naming `what` after `seconds`."""
    import time
    import urllib.request

    for _ in range(int(seconds * 2)):
        try:
            urllib.request.urlopen(url, timeout=1)
            return
        except OSError:
            time.sleep(0.5)
    pytest.fail(f"{what} did not answer within {seconds:.0f} s")


def run_stage_process(stage: str, args: list[str], cwd: Path) -> str:
    """`python -m stages.<stage> *args` in its own process, run from `cwd` with this checkout importable;
    fails the test with the tail of its output unless it succeeds. Returns stdout + stderr."""
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-m", f"stages.{stage}", *args],
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=600,
    )
    log = out.stdout + out.stderr
    if out.returncode != 0:
        pytest.fail(f"stages.{stage} {' '.join(args)} failed ({out.returncode}):\n{log[-4000:]}")
    return log


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    """Tag each `xdist_group` test's node id with its group, as `--dist loadgroup` expects.

    pytest-xdist 3.8 writes the tag to `item._nodeid`, which pytest 9 no longer reads (the id lives in
    `item._id`), so the groups were silently ignored: a group's tests ran on both workers, each building
    the group's module fixture (the released LightNet, the finetuned models, the DVC project) again."""
    _slow_modules_first(items)
    if not getattr(config.option, "loadgroup", False):  # set on xdist workers under --dist loadgroup
        return
    try:
        from _pytest.nodeid import coerce_node_id
    except ImportError:  # pytest < 9 reads item._nodeid, where xdist's own tag already is
        return

    for item in items:
        marks = item.iter_markers("xdist_group")
        names = sorted({str(m.args[0] if m.args else m.kwargs.get("name", "default")) for m in marks})
        if names and "@" not in item.nodeid:
            item._id = coerce_node_id(f"{item.nodeid}@{'_'.join(names)}")


def _slow_modules_first(items) -> None:
    """Run the modules that hold a `slow` test first, each kept whole (its module fixtures built once).

    xdist hands out tests in collection order, so a long test collected late (the paper profile's run of
    every stage, ~2.5 min) started while the other worker was running out of work and set the suite's
    wall time; longest first leaves the short tests to fill both workers at the end."""
    slow = {item.nodeid.split("::")[0] for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.nodeid.split("::")[0] not in slow)  # stable: order kept within each


def compose_cfg(name: str, overrides: list[str] | None = None):
    """Compose `conf/<name>.yaml` with overrides: the project's one composer (`pipeline.tracking.compose`),
    which registers the `${job_dir:...}` resolver as every stage does."""
    from pipeline.tracking.compose import compose

    return compose(name, list(overrides or []))


def _shared_dir(tmp_path_factory, worker_id) -> Path:
    """A temp folder shared by all xdist workers of this session (the master's own when not distributed)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if worker_id != "master" else base


@pytest.fixture(scope="session", autouse=True)
def _environment(tmp_path_factory, worker_id):
    """One MLflow sqlite store for the whole session (creating one costs seconds; the first worker
    creates it under a lock), no analytics, libLLVM 19 for Mitsuba."""
    if os.path.exists(LLVM):
        os.environ.setdefault("DRJIT_LIBLLVM_PATH", LLVM)
    os.environ["DVC_NO_ANALYTICS"] = "1"
    if THREADS is not None:  # in case a plugin imported torch before this file set the env
        import torch

        torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
    shared = _shared_dir(tmp_path_factory, worker_id)
    uri = f"sqlite:///{shared / 'mlflow.db'}"
    with FileLock(str(shared / "mlflow.lock")):
        import mlflow

        mlflow.set_tracking_uri(uri)
        mlflow.search_experiments()  # creates the schema once
    os.environ["MLFLOW_TRACKING_URI"] = uri
    yield


@pytest.fixture(scope="session")
def micro_stage_paths(tmp_path_factory, worker_id):
    """Output/report roots of one `synthesize` run on the micro profile, shared by all xdist workers."""
    shared = _shared_dir(tmp_path_factory, worker_id)
    base = shared / "micro_synth"
    with FileLock(str(shared / "micro_synth.lock")):
        done = base / "done.json"
        if not done.exists():
            if base.exists():
                shutil.rmtree(base)
            from stages import synthesize

            cfg = compose_cfg(
                "synthesize",
                ["profile=micro", f"paths.outputs={base}/outputs", f"paths.reports={base}/reports", "progress=false"],
            )
            metrics = synthesize.run(cfg)
            done.write_text(json.dumps(metrics))
    return {
        "outputs": base / "outputs",
        "reports": base / "reports",
        "metrics": json.loads((base / "done.json").read_text()),
    }


@pytest.fixture(scope="session")
def micro_root(micro_stage_paths) -> Path:
    """Read-only micro dataset root (InteriorVerse layout). Copy it before modifying anything."""
    return micro_stage_paths["outputs"] / "synthesize"


def _micro_preprocessed(stage_paths, tmp_path_factory, worker_id, name: str, root: str, **kwargs) -> Path:
    """Shards of one micro `synthesize` output folder (`root`), written once under `name` for all workers."""
    shared = _shared_dir(tmp_path_factory, worker_id)
    base = shared / name
    with FileLock(str(shared / f"{name}.lock")):
        if not (base / "manifest.json").exists():
            from pipeline.data.preprocess import preprocess

            preprocess(stage_paths["outputs"] / root, base, 48, 64, shard_size=4, progress=False, **kwargs)
    return base


@pytest.fixture(scope="session")
def micro_shards(micro_stage_paths, tmp_path_factory, worker_id) -> Path:
    """Read-only preprocess shards of the micro dataset (the `data_dir` of the training stages)."""
    return _micro_preprocessed(
        micro_stage_paths, tmp_path_factory, worker_id, "micro_shards", "synthesize", source="synthetic"
    )


@pytest.fixture
def micro_shards_without_rooms(micro_shards, tmp_path) -> Path:
    """A copy of the micro shards whose manifest's `source_root` (the room files) is gone."""
    data = tmp_path / "shards"
    shutil.copytree(micro_shards, data)
    manifest = json.loads((data / "manifest.json").read_text())
    manifest["source_root"] = str(tmp_path / "gone")
    (data / "manifest.json").write_text(json.dumps(manifest))
    return data


@pytest.fixture(scope="session")
def micro_ood_shards(micro_stage_paths, tmp_path_factory, worker_id) -> Path:
    """Read-only preprocess shards of the micro run's out-of-distribution set (test split only)."""
    return _micro_preprocessed(
        micro_stage_paths,
        tmp_path_factory,
        worker_id,
        "micro_ood_shards",
        "synthesize_ood",
        source="synthetic_ood",
        required=("test",),
    )


@pytest.fixture(scope="session")
def micro_exports(tmp_path_factory, worker_id):
    """Untrained MaterialNet (`material.pt`, trained at 48x64, depth scale 3) and LightNet (`light.pt`)
    exports of the micro profile's options, shared by all xdist workers: for the entry points that load
    exports (insert, edit, predict, the edit stage), whose tests are about files and refusals."""
    shared = _shared_dir(tmp_path_factory, worker_id)
    out = shared / "micro_exports"
    with FileLock(str(shared / "micro_exports.lock")):
        if not (out / "light.pt").exists():
            import torch
            from omegaconf import OmegaConf

            from pipeline.models.export import save_light_export, save_material_export
            from pipeline.models.light_net import LightNet
            from pipeline.models.material_net import MaterialNet

            torch.manual_seed(0)
            mk = OmegaConf.to_container(
                compose_cfg("train_material", ["profile=micro"]).model.material_net, resolve=True
            )
            lk = OmegaConf.to_container(compose_cfg("train_lighting", ["profile=micro"]).model.light_net, resolve=True)
            save_material_export(out / "material.pt", mk, MaterialNet(**mk), (48, 64), 3.0)
            save_light_export(out / "light.pt", lk, LightNet(**lk))
    return out


@pytest.fixture(scope="session")
def mitsuba_variant():
    """Set a Mitsuba variant in this test process (llvm when it works here, else scalar)."""
    from pipeline.data.synth import mitsuba_backend as mb

    variant = mb.choose_variant("auto")
    mb.init_mitsuba(variant)
    return variant
