"""Where a stage writes: the pipeline's fixed paths in a single run (what `dvc repro` runs and tracks),
its own folder in a Hydra multirun job, so that a sweep never overwrites the pipeline's outputs nor one
job another's.

The `${job_dir:PATH}` config resolver returns PATH unchanged outside a multirun (and under the Compose
API). In a multirun job it returns `<hydra.sweep.dir>/<hydra.sweep.subdir>/PATH` for a relative PATH;
an absolute PATH is the user's explicit choice and is kept. Stage configs wrap what they write (out_dir,
report_dir) in it, never what they read (data_dir, model paths), which stay the pipeline's.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf


def _multirun_job_root() -> Path | None:
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        hc = HydraConfig.get()
    except (ImportError, ValueError):  # Compose API or plain OmegaConf: not a Hydra job
        return None
    if hc.mode != RunMode.MULTIRUN:
        return None
    return Path(hc.sweep.dir) / str(hc.sweep.subdir)


def job_dir(path: str) -> str:
    """`path` for a single run; the same path under the multirun job's own folder (see module doc)."""
    root = _multirun_job_root()
    if root is None or Path(path).is_absolute():
        return str(path)
    return str(root / path)


def register_resolvers() -> None:
    """Register `${job_dir:...}` (idempotent; Hydra resolves it lazily, inside the job)."""
    OmegaConf.register_new_resolver("job_dir", job_dir, replace=True)
