"""One MLflow run per stage execution, on an absolute sqlite store at the project root.

MLflow 3 refuses the file store, and relative URIs break inside DVC's temporary experiment copies
(`.dvc/tmp/exps/...`), so the store is always `sqlite:///<abs root>/mlflow.db` with artifacts under
`<abs root>/mlartifacts`, where root is the original project even when running inside such a copy.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

EXPERIMENT = "invrender"
# MLflow 3's UI opens an experiment by its kind; without this tag it may infer GenAI (traces, prompts)
EXPERIMENT_KIND_TAG, EXPERIMENT_KIND = "mlflow.experimentKind", "custom_model_development"


def project_root(start: str | Path | None = None) -> Path:
    """The project root: nearest ancestor of `start` (default cwd) holding dvc.yaml; inside a DVC
    temporary experiment copy, the project that owns `.dvc/tmp/exps`."""
    here = Path(start or os.getcwd()).resolve()
    parts = here.parts
    for i in range(len(parts) - 2):
        if parts[i : i + 3] == (".dvc", "tmp", "exps"):
            return Path(*parts[:i])
    for p in (here, *here.parents):
        if (p / "dvc.yaml").is_file():
            return p
    return here


def tracking_uri(uri: str | None = None) -> tuple[str, str | None]:
    """(tracking URI, artifact location). Precedence: explicit `uri`, $MLFLOW_TRACKING_URI, project sqlite.
    A relative sqlite path is made absolute against the project root. A tracking server (http/https)
    keeps the artifacts where it serves them (location None: its own artifact store), not on this
    client's disk."""
    root = project_root()
    uri = uri or os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{root / 'mlflow.db'}"
    if uri.startswith("sqlite:///") and not uri.startswith("sqlite:////"):
        uri = f"sqlite:///{(root / uri.removeprefix('sqlite:///')).resolve()}"
    if not uri.startswith(("sqlite:", "http:", "https:", "postgresql:", "mysql:")):
        raise ValueError(
            f"tracking.uri={uri!r}: MLflow 3 needs a database or server URI (e.g. sqlite:////abs/mlflow.db)"
        )
    if uri.startswith(("http:", "https:")):
        return uri, None
    db_dir = Path(uri.removeprefix("sqlite:///")).parent if uri.startswith("sqlite:") else root
    return uri, (db_dir / "mlartifacts").as_uri()


def git_sha(root: Path) -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10)
        sha = out.stdout.strip()
        if not sha:
            return "unknown"
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
        return sha + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _flatten(d: dict, prefix: str = "") -> dict[str, str]:
    flat: dict[str, str] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            flat.update(_flatten(v, key + "."))
        else:
            flat[key] = str(v)[:6000]
    return flat


def activate_experiment(cfg: DictConfig) -> None:
    """Point MLflow at the configured store and experiment (`tracking.uri`, `tracking.experiment`),
    creating the experiment with its absolute artifact location on first use. The experiment is typed
    as model training (`mlflow.experimentKind`), also when it exists without that tag; a kind already
    set on it is kept."""
    import mlflow

    uri, artifacts = tracking_uri(OmegaConf.select(cfg, "tracking.uri"))
    mlflow.set_tracking_uri(uri)
    name = OmegaConf.select(cfg, "tracking.experiment") or EXPERIMENT
    experiment = mlflow.get_experiment_by_name(name)
    if experiment is None:
        mlflow.create_experiment(name, artifact_location=artifacts, tags={EXPERIMENT_KIND_TAG: EXPERIMENT_KIND})
    elif EXPERIMENT_KIND_TAG not in experiment.tags:
        mlflow.MlflowClient().set_experiment_tag(experiment.experiment_id, EXPERIMENT_KIND_TAG, EXPERIMENT_KIND)
    mlflow.set_experiment(name)


PARENT_ENV = "INVRENDER_PARENT_RUN_ID"  # a sweep's parent run, for jobs in other processes (joblib, SLURM)


def process_rank() -> int:
    """This process's global rank as the launchers announce it before any process group exists:
    Lightning's DDP launcher (LOCAL_RANK, NODE_RANK), torchrun (RANK), SLURM (SLURM_PROCID); else 0."""
    for key in ("RANK", "SLURM_PROCID"):
        if os.environ.get(key, "").isdigit():
            return int(os.environ[key])
    local = os.environ.get("LOCAL_RANK", "")
    if local.isdigit():
        per_node = int(os.environ.get("LOCAL_WORLD_SIZE", "0") or 0)
        return int(os.environ.get("NODE_RANK", "0") or 0) * per_node + int(local)
    return 0


def sweep_overrides() -> list[str]:
    """The command-line overrides of this Hydra multirun job ([] outside a multirun, or under Compose)."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        hc = HydraConfig.get()
        return list(hc.overrides.task) if hc.mode == RunMode.MULTIRUN else []
    except (ImportError, ValueError):
        return []


def _continue_params(run_id: str, params: dict[str, str], stage: str, cfg: DictConfig) -> None:
    """On a resumed run: log the params it lacks, record the ones that changed (e.g. `resume`,
    `trainer.max_epochs`) as `resumed.<key>` tags (MLflow params are write-once), and keep this
    execution's config beside the first one."""
    import mlflow

    logged = mlflow.get_run(run_id).data
    new = {k: v for k, v in params.items() if k not in logged.params}
    changed = {f"resumed.{k}": v[:5000] for k, v in params.items() if k in logged.params and logged.params[k] != v}
    count = int(logged.tags.get("resumed", "0")) + 1
    if new:
        mlflow.log_params(new)
    mlflow.set_tags({**changed, "resumed": str(count)})
    mlflow.log_text(OmegaConf.to_yaml(cfg, resolve=True), f"config/{stage}.resume-{count}.yaml")


@contextlib.contextmanager
def stage_run(
    stage: str,
    cfg: DictConfig,
    tags: dict[str, str] | None = None,
    system_metrics: bool = False,
    resume_run_id: str | None = None,
) -> Iterator:
    """Open an MLflow run named `<stage>-<profile>` (plus the job's overrides in a Hydra multirun)
    tagged with stage, profile, git sha, DVC_EXP_NAME and overrides; log the resolved config (params +
    `config/<stage>.yaml` artifact). Nested when a parent run is active in this process or named by
    $INVRENDER_PARENT_RUN_ID (sweep jobs in worker processes). `resume_run_id` (from a checkpoint)
    continues that run when the store has it, else a new run is linked to it by a tag.
    system_metrics samples CPU/memory into the run while it is open. Yields the active `mlflow` run,
    or None on a distributed process other than rank 0 (only rank 0 tracks)."""
    import mlflow

    if process_rank() != 0:
        yield None
        return
    activate_experiment(cfg)
    profile = str(OmegaConf.select(cfg, "profile_name") or "unknown")
    overrides = sweep_overrides()
    all_tags = {
        "stage": stage,
        "profile": profile,
        "git_sha": git_sha(project_root()),
        "dvc_exp_name": os.environ.get("DVC_EXP_NAME", ""),
        "overrides": " ".join(overrides)[:5000],
        "process_id": str(os.getpid()),  # which worker ran it, in parallel sweeps
        **(tags or {}),
    }
    params = _flatten(OmegaConf.to_container(cfg, resolve=True))
    existing = None
    if resume_run_id:
        try:
            existing = mlflow.get_run(resume_run_id)
        except mlflow.exceptions.MlflowException:
            all_tags["resumed_from_run_id"] = resume_run_id  # another store: link, do not continue
    active = mlflow.active_run()
    parent = os.environ.get(PARENT_ENV) if active is None else None
    if existing is not None:
        start = {"run_id": resume_run_id}
    else:
        name = f"{stage}-{profile}" + (f" {' '.join(overrides)}" if overrides else "")
        start = {"run_name": name[:250], "nested": active is not None, "tags": all_tags, "parent_run_id": parent}
    with mlflow.start_run(**start, log_system_metrics=system_metrics or None) as run:
        if existing is not None:
            _continue_params(run.info.run_id, params, stage, cfg)
        else:
            mlflow.log_params(params)
            mlflow.log_text(OmegaConf.to_yaml(cfg, resolve=True), f"config/{stage}.yaml")
        yield run
