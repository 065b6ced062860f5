"""Shared helpers for benchmarks: timing medians, machine description, quoted figures, JSON output.

A bench JSON keeps what it timed or measured in its own run under `measured` and any figure it did not
measure (a number from a paper or another program) under `quoted`, each as {value, unit, source};
nothing under `measured` is derived from a quoted figure. Every JSON also records its `provenance`: the
commit it ran (and whether the tree had uncommitted changes), the command, the date, and each stage config
it composed (`compose`: name, overrides, profile and a hash of the resolved config), so a reader can
tell whether it measured what the current profile runs.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from pipeline.tracking import project_root

# the stage configs this process composed (`compose`), recorded in its JSON's provenance
COMPOSED: list[dict] = []
# machine-specific keys left out of a config's hash: where things are, not what runs
UNHASHED = ("paths", "tracking", "progress", "hydra", "out_dir", "report_dir", "data_dir", "ood_data_dir")


def config_hash(cfg) -> str:
    """SHA-256 (first 16 hex digits) of a composed config, resolved with its `paths.*` roots as
    placeholders (where the outputs are is not what runs), without its machine-specific keys."""
    from omegaconf import OmegaConf

    cfg = cfg.copy()
    for key in list(OmegaConf.select(cfg, "paths") or {}):
        cfg.paths[key] = f"<paths.{key}>"
    plain = OmegaConf.to_container(cfg, resolve=True)
    kept = {k: v for k, v in plain.items() if k not in UNHASHED and not str(k).endswith("_path")}
    return hashlib.sha256(json.dumps(kept, sort_keys=True, default=str).encode()).hexdigest()[:16]


def compose(name: str, overrides: list[str] | tuple[str, ...] = ()):
    """`conf/<name>.yaml` with `overrides` (`pipeline.tracking.compose`), recorded for the provenance."""
    from omegaconf import OmegaConf

    from pipeline.tracking.compose import compose as compose_config

    cfg = compose_config(name, list(overrides))
    profile = OmegaConf.select(cfg, "profile_name")
    COMPOSED.append({"config": name, "overrides": list(overrides), "profile": profile, "sha256": config_hash(cfg)})
    return cfg


def training_system(stage: str, overrides: list[str], seed: int):
    """(system, optimiser, config) of a training stage (`train_lighting` or `train_material`) composed with
    `seed` and `overrides`, built as the stage builds it, its logging silenced (outside Lightning a step's
    logs go nowhere) and the stage's optimiser over the network's parameters: the one builder of the
    benches that train."""
    from hydra.utils import instantiate

    from pipeline.systems import lighting_training, material_training

    builders = {"train_lighting": lighting_training.build_system, "train_material": material_training.build_system}
    if stage not in builders:
        raise ValueError(f"stage={stage!r}: choose one of {sorted(builders)}")
    cfg = compose(stage, [f"seed={seed}", *overrides])
    torch.manual_seed(seed)
    system = builders[stage](cfg)
    system.log = lambda *args, **kwargs: None
    return system, instantiate(cfg.optim.optimizer)(system.net.parameters()), cfg


def gradient_clip(cfg) -> float:
    """The stage's gradient-norm clip (`trainer.gradient_clip_val`; 0 for none)."""
    return float(cfg.trainer.get("gradient_clip_val") or 0.0)


def optimiser_step(system, optimizer, batch, step: int, clip: float) -> float:
    """One training step as Lightning runs the stage's: the system's loss, backward, the gradient norm
    clipped at `clip` (when > 0), the optimiser's step. Returns the loss."""
    loss = system.training_step(batch, step)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    if clip > 0:
        torch.nn.utils.clip_grad_norm_(system.net.parameters(), clip)
    optimizer.step()
    return float(loss.detach())


_STARTED_AT: tuple[str | None, bool | None] | None = None  # the code a bench process started on


def started_commit() -> tuple[str | None, bool | None]:
    """`git_commit()` as it was when this process first asked (a bench asks on importing this module), so
    a long run's JSON names the code it ran, not a commit made while it ran."""
    global _STARTED_AT
    if _STARTED_AT is None:
        _STARTED_AT = git_commit()
    return _STARTED_AT


CODE_FOLDERS = ("pipeline", "stages", "conf")  # what a bench imports or composes: new files there are code too


def git_commit() -> tuple[str | None, bool | None]:
    """(HEAD's SHA, whether the code differs from it: tracked files changed, or files not yet added under
    `CODE_FOLDERS`, such as a new bench module), or (None, None) outside a git checkout.

    `$INVRENDER_SOURCE_COMMIT`, when set, names the commit instead, dirty unknown: a copy of the tree on
    another machine (a device machine's) may carry no .git, or an older one with this tree laid over it,
    whose HEAD would name the wrong commit."""
    named = os.environ.get("INVRENDER_SOURCE_COMMIT")
    if named:
        return named, None
    root = project_root()
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True)
        dirty = subprocess.run(["git", "diff", "--quiet", "HEAD", "--"], cwd=root, capture_output=True)
        added = subprocess.run(
            ["git", "ls-files", "--others", "--exclude-standard", "--", *CODE_FOLDERS],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        )
    except (OSError, subprocess.CalledProcessError):
        return None, None
    return sha.stdout.strip(), dirty.returncode != 0 or bool(added.stdout.strip())


def _main_module() -> str:
    """The module this process runs (`pipeline.bench.<name>` under `python -m`), else the script's name."""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    return spec.name if spec is not None else Path(sys.argv[0] if sys.argv else "?").stem


def provenance() -> dict:
    """What a bench JSON says about its own run: commit, dirty tree, command, UTC date, the stage configs
    composed (`compose`) and their profile (None when it composed none: a bench of its own settings).
    The commit and dirty flag are the ones the process started on (`started_commit`)."""
    commit, dirty = started_commit()
    profiles = sorted({c["profile"] for c in COMPOSED if c["profile"] is not None})
    return {
        "commit": commit,
        "dirty": dirty,
        "command": " ".join(["python", "-m", _main_module(), *sys.argv[1:]]),
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d"),
        "profile": ",".join(profiles) if profiles else None,
        "configs": distinct_configs(COMPOSED),
    }


def distinct_configs(composed: list[dict]) -> list[dict]:
    """`composed` with each (config, hash) once, in first-composed order: a bench that builds a stage's
    system several times composes the same config each time (its overrides may differ only in paths)."""
    seen, out = set(), []
    for c in composed:
        key = (c["config"], c["sha256"])
        if key not in seen:
            seen.add(key)
            out.append(c)
    return out


def median_seconds(fn, repeats: int = 3, warmup: int = 1) -> float:
    """Median wall time (s) of fn() over `repeats` runs after `warmup` untimed runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def device_name(device: str = "cpu") -> str:
    """The device a bench ran on, as the JSON records it: `cpu`, or `cuda (<GPU name>)`."""
    dev = torch.device(device)
    if dev.type == "cuda":
        return f"cuda ({torch.cuda.get_device_name(dev)})"
    return dev.type


def threads(n: int) -> str:
    """`1 thread`, `2 threads`: a thread count for figure labels."""
    return f"{n} thread" + ("s" if n != 1 else "")


def add_threads_option(parser) -> None:
    """`--threads N`: torch's intra-op threads for the run (default: torch's own). 1 keeps OpenMP from
    spin-waiting when other work shares the CPU; the JSON records the count either way."""
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's own)")


def apply_threads(n: int | None) -> None:
    if n is not None:
        torch.set_num_threads(n)


def machine(device: str = "cpu") -> dict:
    """Platform, versions, CPU count, torch's intra-op thread count and the device the bench ran on."""
    return {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "device": device_name(device),
    }


def quoted(value: float, unit: str, source: str) -> dict:
    """A figure the bench did not measure: its value, unit and where it comes from."""
    return {"value": value, "unit": unit, "source": source}


def bench_dir() -> Path:
    """reports/bench/ of this checkout: where every bench writes its JSON and PNG."""
    return project_root() / "reports" / "bench"


def write_report(name: str, payload: dict, device: str = "cpu", path: Path | None = None) -> Path:
    """reports/bench/<name>.json (or `path`): the payload with the bench's name, the machine and the
    run's `provenance`."""
    path = Path(path) if path is not None else bench_dir() / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    head = {"benchmark": name, "machine": machine(device), "provenance": provenance()}
    path.write_text(json.dumps({**head, **payload}, indent=1) + "\n")
    return path


def publish(name: str, report: dict, plot, device: str = "cpu") -> Path:
    """Write reports/bench/<name>.json (with the machine and `device` the bench ran on) and, beside it,
    the figure `plot(report, path)` draws as <name>.png."""
    path = write_report(name, report, device)
    plot(report, path.with_suffix(".png"))
    return path


def edit_object_cases(view_id: str, cases: list) -> list:
    """The object cases of one view's `cases` (as `insertion_scoring.view_context` reads them), checked to come first:
    the `edit` stage seeds a case by its index in the view's list, so the objects alone keep the seeds it
    gives them only when no edit is listed before them."""
    objects = [c for c in cases if c.kind == "object"]
    if cases[: len(objects)] != objects:
        raise ValueError(f"{view_id}: edits listed before objects; the seeds would differ from `edit`'s")
    return objects


started_commit()  # on import: what the bench starts on
