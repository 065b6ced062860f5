"""dvc.yaml's deps are exactly what each stage imports and composes (`pipeline.tracking.stage_deps`), so an
edit re-runs the stages that can see it and no other."""

from pathlib import Path

import pytest
import yaml

from pipeline.tracking import stage_deps
from tests.conftest import ROOT


@pytest.fixture(scope="module")
def declared():
    dvc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    return dvc, params


def _stages_listing(dvc: dict, params: dict, path: str) -> set[str]:
    """The stage entries (ablate expanded per preset and seed) whose deps name `path`: what an edit of it
    makes stale after a finished `dvc repro` (everything downstream follows only if their outs change)."""
    found = set()
    for name, stage in dvc["stages"].items():
        body = stage.get("do", stage)
        if "foreach" not in stage:
            found |= {name} if path in body["deps"] else set()
            continue
        for key, item in params["ablations"].items():
            deps = [d.replace("${item.needs}", item["needs"]) for d in body["deps"]]
            deps = [item["conf"][int(d[12:-2])] if d.startswith("${item.conf[") else d for d in deps]
            found |= {f"{name}@{key}"} if path in deps else set()
    return found


def test_declared_deps_equal_the_generated(declared):
    dvc, params = declared
    assert stage_deps.differences(dvc, params) == [], "run `make deps` and commit dvc.yaml and params.yaml"


def test_every_code_dep_is_in_its_stages_import_closure(declared):
    """Equality, not coverage: each code dep is a module the stage's entry point imports (directly or
    through the packages an import runs), or one its config names by `_target_`."""
    import grimp

    dvc, _ = declared
    graph = grimp.build_graph("pipeline", "stages", cache_dir=None)
    for name, stage in dvc["stages"].items():
        code = {d for d in stage.get("do", stage)["deps"] if d.endswith(".py")}
        closure = graph.find_upstream_modules(f"stages.{name}") | {f"stages.{name}"}
        reached = {str(stage_deps.module_file(m).relative_to(ROOT)) for m in closure if stage_deps.module_file(m)}
        parts = [Path(f).parts for f in reached]
        packages = {str(Path(*p[:n]) / "__init__.py") for p in parts for n in range(1, len(p))}
        targeted = {"pipeline/tracking/hydra_callbacks.py"}  # conf/base.yaml's Hydra callback
        assert code - (reached | packages | targeted) == set(), name
        assert reached - code == set(), name


@pytest.mark.parametrize(
    ("path", "stale"),
    [
        ("pipeline/tracking/results_page.py", {"report"}),
        ("conf/claims/paper.yaml", {"report"}),
        ("pipeline/systems/evaluation.py", {"evaluate"}),
        ("pipeline/systems/out_of_distribution.py", {"evaluate"}),
        ("pipeline/data/synth/generate.py", {"synthesize"}),
        ("pipeline/ops/equirect.py", set()),  # the CLI's alone
        ("pipeline/models/released.py", set()),
        ("pipeline/tracking/stage_deps.py", set()),
    ],
)
def test_an_edit_makes_only_the_stages_that_read_it_stale(declared, path, stale):
    dvc, params = declared
    assert (ROOT / path).is_file(), path
    assert _stages_listing(dvc, params, path) == stale


def test_a_preset_file_reruns_its_own_entries_only(declared):
    dvc, params = declared
    assert _stages_listing(dvc, params, "conf/ablation/ssrt_only.yaml") == {f"ablate@ssrt_only-s{s}" for s in range(3)}
    lighting = {f"ablate@{k}" for k, v in params["ablations"].items() if not v["preset"].startswith("material")}
    assert _stages_listing(dvc, params, "conf/ablation/common/lighting.yaml") == lighting
    assert _stages_listing(dvc, params, "conf/render/li2020.yaml") == {"ablate@no_mc_render-s0"}


def test_the_profile_is_a_params_dep_on_the_keys_each_stage_reads(declared):
    dvc, _ = declared

    def keys(name):
        body = dvc["stages"][name].get("do", dvc["stages"][name])
        found = [p for p in body["params"] if isinstance(p, dict) and "conf/profile/${profile}.yaml" in p]
        return set(found[0]["conf/profile/${profile}.yaml"]) if found else set()

    assert "synth" in keys("synthesize") and "epochs" not in keys("synthesize")
    assert "synth" not in keys("train_lighting") and "light_loss" in keys("train_lighting")
    assert "light_loss" not in keys("report") and "light_loss" not in keys("train_material")
    assert all("conf/profile" not in d for s in dvc["stages"].values() for d in s.get("do", s)["deps"])


def test_every_lock_entry_has_a_stage(declared):
    dvc, params = declared
    names = {f"ablate@{k}" for k in params["ablations"]} | {n for n, s in dvc["stages"].items() if "foreach" not in s}
    lock = yaml.safe_load((ROOT / "dvc.lock").read_text())
    assert set(lock["stages"]) - names == set()
