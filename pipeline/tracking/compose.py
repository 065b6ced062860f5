"""The project's config composer: `conf/<name>.yaml` with overrides, from inside a Hydra app (its search
path) or from plain Python (stages that compose another stage's config, benches, tests), and the
ablation presets' training stage. One composer, so every caller resolves a config the same way."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"
PRESET_STAGES = {"common/lighting": "train_lighting", "common/material": "train_material"}


def compose(name: str, overrides: list[str] | tuple[str, ...] = (), return_hydra_config: bool = False) -> DictConfig:
    """`conf/<name>.yaml` composed with `overrides` (Hydra's Compose API, no working-dir change), with
    Hydra's own node (`hydra.runtime.choices`: the group options chosen) when `return_hydra_config`. The
    `${job_dir:...}` resolver is registered by importing this package, as every stage does."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    kwargs = {"config_name": name, "overrides": list(overrides), "return_hydra_config": return_hydra_config}
    if GlobalHydra.instance().is_initialized():
        return hydra_compose(**kwargs)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return hydra_compose(**kwargs)


def preset_stage(preset: str) -> str:
    """The training stage a preset applies to: the schedule it includes (`common/lighting` or
    `common/material`). Raises naming the preset file when it is missing or includes neither."""
    import yaml

    path = CONF_DIR / "ablation" / f"{preset}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise FileNotFoundError(f"ablation={preset}: no {path} (presets: {', '.join(known)})")
    defaults = (yaml.safe_load(path.read_text()) or {}).get("defaults") or []
    found = [PRESET_STAGES[d] for d in defaults if isinstance(d, str) and d in PRESET_STAGES]
    if len(found) != 1:
        raise ValueError(f"{path}: its defaults must include exactly one of {sorted(PRESET_STAGES)}")
    return found[0]
