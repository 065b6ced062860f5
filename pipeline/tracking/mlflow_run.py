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
    creating the experiment with its absolute artifact location on first use."""
    import mlflow

    uri, artifacts = tracking_uri(OmegaConf.select(cfg, "tracking.uri"))
    mlflow.set_tracking_uri(uri)
    name = OmegaConf.select(cfg, "tracking.experiment") or EXPERIMENT
    if mlflow.get_experiment_by_name(name) is None:
        mlflow.create_experiment(name, artifact_location=artifacts)
    mlflow.set_experiment(name)


@contextlib.contextmanager
def stage_run(
    stage: str, cfg: DictConfig, tags: dict[str, str] | None = None, system_metrics: bool = False
) -> Iterator:
    """Open an MLflow run named `<stage>-<profile>` tagged with stage, profile, git sha and DVC_EXP_NAME;
    log the resolved config (params + `config/<stage>.yaml` artifact). Nested when a parent run is active
    (Hydra sweeps). system_metrics samples CPU/memory into the run while it is open. Yields the active
    `mlflow` run."""
    import mlflow

    activate_experiment(cfg)
    profile = str(OmegaConf.select(cfg, "profile_name") or "unknown")
    all_tags = {
        "stage": stage,
        "profile": profile,
        "git_sha": git_sha(project_root()),
        "dvc_exp_name": os.environ.get("DVC_EXP_NAME", ""),
        **(tags or {}),
    }
    resolved = OmegaConf.to_container(cfg, resolve=True)
    with mlflow.start_run(
        run_name=f"{stage}-{profile}",
        nested=mlflow.active_run() is not None,
        tags=all_tags,
        log_system_metrics=system_metrics or None,
    ) as run:
        mlflow.log_params(_flatten(resolved))
        mlflow.log_text(OmegaConf.to_yaml(cfg, resolve=True), f"config/{stage}.yaml")
        yield run
