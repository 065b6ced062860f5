"""dvc.yaml's code and config deps, generated: each stage depends on exactly what it runs and reads.

- Code: the import closure of `stages/<name>.py`, file by file (every import a module makes, at the top or
  inside a function, as `grimp` finds them; the packages an import executes on its way, `__init__.py`
  included), plus the modules Hydra loads by `_target_` from the config files the stage composes.
- Config: the files Hydra composes for the stage (its primary file, `base`, the group options it
  selects, an ablation preset's files), read from the composed config's `hydra.runtime.choices`.
- The profile (`conf/profile/<profile>.yaml`, a `_global_` package every stage composes) is a params dep
  on the top-level keys the stage can read: those its other config files interpolate, and those its
  code names outside import lines (`cfg.<key>`, `"<key>"`). Other profile edits leave the stage alone.
- Each `ablate@<preset>-s<seed>` entry: the ablate stage's closure and config, plus the files its preset
  composes for the training stage and for scoring: `${item.conf[i]}`, one slot per file, from the `conf`
  list this module writes into the entry in params.yaml (DVC cannot splice a list into deps; a shorter
  list is padded with the entry's own preset file). The entry's `needs` stays as written.

Data deps (`outputs/`, `reports/`) are declared by hand and kept as they are. `python -m
pipeline.tracking.stage_deps --write` rewrites dvc.yaml's generated deps (and params.yaml's `conf` lists);
`--check` exits 1 naming every stage whose declared deps differ (a test runs it)."""

from __future__ import annotations

import argparse
import re
import sys
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("pipeline", "stages")
GENERATED = ("pipeline/", "stages/", "conf/")  # dep prefixes this module owns; others are kept
IMPORT = re.compile(r"\s*(from|import)\s+[\w.]+")
COMPOSED = re.compile(r"\bcompose\(\s*[\"'](\w+)[\"']")
SLOT = re.compile(r"\$\{item\.conf\[\d+\]\}")
TARGET = re.compile(r"_target_:\s*([A-Za-z_][\w.]*)")


@cache
def _graph():  # one import graph per process
    import grimp

    return grimp.build_graph(*PACKAGES, cache_dir=None)


def module_file(module: str) -> Path | None:
    """The source file of a project module (`pkg/mod.py` or `pkg/mod/__init__.py`), or None."""
    base = ROOT.joinpath(*module.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def project_module(dotted: str) -> str | None:
    """The longest prefix of a dotted name (a `_target_`) that is a project module, or None."""
    parts = dotted.split(".")
    for n in range(len(parts), 0, -1):
        name = ".".join(parts[:n])
        if parts[0] in PACKAGES and module_file(name) is not None:
            return name
    return None


def import_closure(entries: set[str]) -> set[str]:
    """Every project module that importing `entries` executes: their imports, transitively, and each
    imported module's parent packages (importing `a.b.c` runs `a/__init__.py` and `a/b/__init__.py`)."""
    graph = _graph()
    seen: set[str] = set()
    todo = list(entries)
    while todo:
        module = todo.pop()
        if module in seen:
            continue
        seen.add(module)
        parts = module.split(".")
        todo.extend(".".join(parts[:n]) for n in range(1, len(parts)))
        if module in graph.modules:
            todo.extend(graph.find_modules_directly_imported_by(module))
    return {m for m in seen if m.split(".")[0] in PACKAGES and module_file(m) is not None}


def _rel(path: Path) -> str:
    return str(path.resolve().relative_to(ROOT))


@cache
def composed_files(config: str, overrides: tuple[str, ...]) -> tuple[str, ...]:
    """The conf/ files Hydra composes for `conf/<config>.yaml` with `overrides` (repo-relative): the
    primary file, the plain entries of its defaults list (`base`) and every group option chosen."""
    import yaml

    from pipeline.tracking.compose import compose

    conf = ROOT / "conf"
    cfg = compose(config, overrides, return_hydra_config=True)
    files = {conf / f"{config}.yaml"}
    for group, option in cfg.hydra.runtime.choices.items():
        if option is not None and (conf / group / f"{option}.yaml").is_file():
            files.add(conf / group / f"{option}.yaml")
    todo = list(files)
    while todo:  # plain entries of each file's defaults list: `base`, a preset's `common/lighting`
        path = todo.pop()
        for entry in (yaml.safe_load(path.read_text()) or {}).get("defaults") or []:
            if not isinstance(entry, str) or entry == "_self_":
                continue
            found = conf / f"{entry[1:]}.yaml" if entry.startswith("/") else path.parent / f"{entry}.yaml"
            if found.is_file() and found not in files:
                files.add(found)
                todo.append(found)
    return tuple(sorted(_rel(f) for f in files))


def _code_of(files: list[str]) -> set[str]:
    """The project modules named by `_target_` in config files."""
    found = set()
    for f in files:
        for dotted in TARGET.findall((ROOT / f).read_text()):
            module = project_module(dotted)
            if module is not None:
                found.add(module)
    return found


def profile_keys(profile: str, conf_files: list[str], code_files: list[str]) -> list[str]:
    """The profile's top-level keys a stage can read: interpolated by its other config files (`${key`) or
    named by its code outside import lines (`.key`, `"key"`, `'key'`, `"key.`)."""
    import yaml

    keys = list((yaml.safe_load((ROOT / "conf" / "profile" / f"{profile}.yaml").read_text()) or {}).keys())
    conf_text = "\n".join((ROOT / f).read_text() for f in conf_files)
    code_text = "\n".join(
        line for f in code_files for line in (ROOT / f).read_text().splitlines() if not IMPORT.match(line)
    )
    used = []
    for key in keys:
        k = re.escape(key)
        in_conf = re.search(rf"\$\{{{k}\b", conf_text)
        in_code = re.search(rf"\.{k}\b|[\"']{k}[\"'.]", code_text)
        if in_conf or in_code:
            used.append(key)
    return sorted(used)


def runtime_configs(code_files: list[str]) -> set[str]:
    """Configs a stage's code composes while it runs (`compose("train_lighting", ...)`: `evaluate` scores
    LightNet as its stage configures it), by the literal names its code passes to a `compose` call."""
    return {name for f in code_files for name in COMPOSED.findall((ROOT / f).read_text())}


def stage_inputs(stage: str, profile: str, extra_configs: tuple[tuple[str, tuple[str, ...]], ...] = ()) -> dict:
    """{"code": [...], "conf": [...], "profile_keys": [...]} of one stage: `stages/<stage>.py`'s closure,
    the config files of `conf/<stage>.yaml`, of the configs its code composes (`runtime_configs`) and of
    every (config, overrides) in `extra_configs`, the `_target_` modules of those files (and theirs) and
    the profile keys the stage reads."""
    overrides = [f"profile={profile}"]
    configs = {(stage, ()), *extra_configs}
    done: set = set()
    conf: set[str] = set()
    code: list[str] = []
    while configs - done:  # a config's `_target_` modules may compose further configs at run time
        for config, extra in sorted(configs - done):
            conf |= set(composed_files(config, (*overrides, *extra)))
            done.add((config, extra))
        modules = import_closure({f"stages.{stage}"} | _code_of(sorted(conf)))
        code = sorted(_rel(module_file(m)) for m in modules)
        configs |= {(name, ()) for name in runtime_configs(code)}
    conf.discard(f"conf/profile/{profile}.yaml")  # a params dep on the keys read (`profile_keys`)
    return {"code": code, "conf": sorted(conf), "profile_keys": profile_keys(profile, sorted(conf), code)}


def preset_configs(preset: str, profile: str) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """What `ablate` composes for one preset: its training stage with `ablation=<preset>`, and for a
    LightNet preset the same with the scoring layer (`scoring.render`) and the `edit` config it scores
    insertion with (`pipeline.runs.ablate`)."""
    from pipeline.tracking.compose import compose, preset_stage

    stage = preset_stage(preset)
    configs = [(stage, (f"ablation={preset}",))]
    if stage == "train_lighting":
        cfg = compose(stage, [f"profile={profile}", f"ablation={preset}"])
        configs.append((stage, (f"ablation={preset}", f"render={cfg.scoring.render}")))
        configs.append(("edit", ()))
    return tuple(configs)


@cache
def _preset_inputs(stage: str, profile: str, preset: str) -> dict:
    return stage_inputs(stage, profile, preset_configs(preset, profile))


def _params(profile_keys: list[str], extra: tuple = ()) -> list:
    return [*extra, {"conf/profile/${profile}.yaml": profile_keys}] if profile_keys else list(extra)


def generate(dvc: dict, params: dict) -> tuple[dict[str, dict], dict[str, list[str]]]:
    """({stage: {"deps": [...], "params": [...]}}, {ablation entry: its preset's conf files}) for the
    stages of a parsed dvc.yaml under the profile of a parsed params.yaml. Data deps and the non-profile
    params of each stage are kept as declared."""
    profile = str(params["profile"])
    out: dict[str, dict] = {}
    presets: dict[str, list[str]] = {}
    for name, stage in dvc["stages"].items():
        body = stage.get("do", stage)
        if "foreach" in stage:  # ablate: per preset, the files each preset composes besides the stage's
            base = stage_inputs(name, profile)
            keys = set(base["profile_keys"])
            for key, item in params["ablations"].items():
                extra = _preset_inputs(name, profile, str(item["preset"]))
                presets[key] = sorted(set(extra["conf"]) - set(base["conf"]))
                keys |= set(extra["profile_keys"])
            inputs = {**base, "profile_keys": sorted(keys)}
        else:
            inputs = stage_inputs(name, profile)
        kept = [d for d in body.get("deps", []) if not str(d).startswith(GENERATED) and not SLOT.match(str(d))]
        data = [d for d in kept if "${" not in str(d)]
        templated = [d for d in kept if "${" in str(d)]
        if "foreach" in stage:  # one slot per file, each entry's list padded with its own preset file
            slots = max(len(files) for files in presets.values())
            presets = {
                k: files + [f"conf/ablation/{params['ablations'][k]['preset']}.yaml"] * (slots - len(files))
                for k, files in presets.items()
            }
            templated += [f"${{item.conf[{i}]}}" for i in range(slots)]
        other_params = [p for p in body.get("params", []) if not _is_conf_param(p)]
        out[name] = {
            "deps": [*data, *inputs["code"], *inputs["conf"], *templated],
            "params": _params(inputs["profile_keys"], tuple(other_params)),
        }
    return out, presets


def _is_conf_param(p) -> bool:
    """A params dep on a conf/ file: generated (the profile's keys) or covered by a file dep (base.yaml)."""
    return isinstance(p, dict) and any(str(k).startswith("conf/") for k in p)


def _plain(value):
    """ruamel's round-trip containers as plain dicts and lists (for comparison)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value


def differences(dvc: dict, params: dict) -> list[str]:
    """One line per stage (or ablation entry) whose declared deps or params differ from the generated."""
    wanted, presets = generate(dvc, params)
    lines = []
    for name, gen in wanted.items():
        body = dvc["stages"][name].get("do", dvc["stages"][name])
        for field in ("deps", "params"):
            have = _plain(body.get(field, []))
            if have != gen[field]:
                extra = [str(x) for x in have if x not in gen[field]]
                missing = [str(x) for x in gen[field] if x not in have]
                lines.append(f"{name}.{field}: declared but not read {extra}; read but not declared {missing}")
    for key, files in presets.items():
        have = _plain(params["ablations"][key].get("conf"))
        if have != files:
            lines.append(f"params.yaml ablations.{key}.conf: {have} != {files}")
    return lines


def _load(path: Path):
    from ruamel.yaml import YAML

    yaml = YAML()
    yaml.preserve_quotes = True
    yaml.width = 120
    yaml.indent(mapping=2, sequence=4, offset=2)  # the files' own style: `- item` under its key, indented
    return yaml, yaml.load(path.read_text())


def write(dvc_path: Path = ROOT / "dvc.yaml", params_path: Path = ROOT / "params.yaml") -> list[str]:
    """Rewrite the generated deps of dvc.yaml and the `conf` lists of params.yaml's ablation entries
    (comments and everything else kept). Returns what changed (`differences` before writing)."""
    from ruamel.yaml.comments import CommentedSeq

    yaml, dvc = _load(dvc_path)
    _, params = _load(params_path)
    changed = differences(dvc, params)
    wanted, presets = generate(dvc, params)
    for name, gen in wanted.items():
        body = dvc["stages"][name].get("do", dvc["stages"][name])
        for field in ("deps", "params"):
            body[field] = CommentedSeq(gen[field])
    for key, files in presets.items():
        seq = CommentedSeq(files)
        seq.fa.set_flow_style()
        params["ablations"][key]["conf"] = seq
    with open(dvc_path, "w") as fh:
        yaml.dump(dvc, fh)
    yaml.width = 4096  # one line per ablation entry, as they are written by hand
    with open(params_path, "w") as fh:
        yaml.dump(params, fh)
    return changed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.tracking.stage_deps", description=__doc__.split("\n")[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--write", action="store_true", help="rewrite dvc.yaml's generated deps")
    mode.add_argument("--check", action="store_true", help="exit 1 if dvc.yaml's deps differ from the generated")
    args = parser.parse_args(argv)
    if args.write:
        changed = write()
        print("\n".join(changed) if changed else "dvc.yaml: deps already exact")
        return 0
    _, dvc = _load(ROOT / "dvc.yaml")
    _, params = _load(ROOT / "params.yaml")
    diff = differences(dvc, params)
    if diff:
        print("dvc.yaml's deps differ from what the stages import and read (`make deps` rewrites them):")
        print("\n".join(diff))
        return 1
    print("dvc.yaml: deps exact")
    return 0


if __name__ == "__main__":
    sys.exit(main())
