"""Every bench JSON says which commit and which configuration it measured, and the results page marks a
bench that did not measure the current profile's configuration."""

import json
import re
from pathlib import Path

import pytest

from pipeline.bench import common
from pipeline.tracking.results_page import provenance_line


@pytest.fixture(autouse=True)
def _fresh_record(monkeypatch):
    monkeypatch.setattr(common, "COMPOSED", [])


def test_a_bench_json_records_commit_profile_and_config_hash(tmp_path):
    common.compose("train_lighting", ["profile=micro"])
    path = common.write_report("probe", {"measured": {"x": 1.0}}, path=tmp_path / "probe.json")
    prov = json.loads(path.read_text())["provenance"]
    assert re.fullmatch(r"[0-9a-f]{40}", prov["commit"]) and isinstance(prov["dirty"], bool)
    assert prov["profile"] == "micro" and re.fullmatch(r"\d{4}-\d\d-\d\d", prov["date"])
    [config] = prov["configs"]
    assert config["config"] == "train_lighting" and config["overrides"] == ["profile=micro"]
    assert re.fullmatch(r"[0-9a-f]{16}", config["sha256"])


def test_a_config_composed_again_is_recorded_once(tmp_path):
    for _ in range(3):
        common.compose("train_lighting", ["profile=micro"])
    common.compose("train_lighting", ["profile=micro", "paths.outputs=/elsewhere"])  # where, not what
    common.compose("train_material", ["profile=micro"])
    configs = common.provenance()["configs"]
    assert [c["config"] for c in configs] == ["train_lighting", "train_material"]


def test_the_config_hash_follows_what_runs_not_where_files_are():
    base = common.config_hash(common.compose("train_lighting", ["profile=micro"]))
    assert common.config_hash(common.compose("train_lighting", ["profile=micro"])) == base
    assert common.config_hash(common.compose("train_lighting", ["profile=micro", "paths.outputs=/elsewhere"])) == base
    assert common.config_hash(common.compose("train_lighting", ["profile=micro", "render.spp=3"])) != base
    assert common.config_hash(common.compose("train_lighting", ["profile=tiny"])) != base


def test_the_page_marks_benches_not_measured_on_the_current_profile():
    record = {"commit": "a" * 40, "dirty": False, "date": "2026-11-27", "configs": []}
    assert "predates" in provenance_line({}, "tiny")  # measured before provenance was recorded
    other = provenance_line({"provenance": {**record, "profile": "micro"}}, "tiny")
    assert "Not the current profile's configuration" in other
    same = provenance_line({"provenance": {**record, "profile": "tiny"}}, "tiny")
    assert "commit aaaaaaaaaa" in same and "Not" not in same
    own = provenance_line({"provenance": {**record, "profile": None}}, "tiny")
    assert "Its own settings" in own


def test_provenance_names_the_commit_the_process_started_on(monkeypatch):
    # a commit made while a long bench runs must not be credited with its numbers
    from pipeline.bench import common

    before = common.provenance()["commit"]
    monkeypatch.setattr(common, "git_commit", lambda: ("f" * 40, False))
    assert common.provenance()["commit"] == before


def test_a_copied_tree_names_the_commit_it_was_copied_from(monkeypatch, tmp_path):
    # a device machine's copy has no .git, or an older one under this tree: the environment names the commit
    monkeypatch.setattr(common, "project_root", lambda: tmp_path)
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path.parent))
    monkeypatch.delenv("INVRENDER_SOURCE_COMMIT", raising=False)
    assert common.git_commit() == (None, None)
    monkeypatch.setenv("INVRENDER_SOURCE_COMMIT", "c" * 40)
    assert common.git_commit() == ("c" * 40, None)
    monkeypatch.setattr(common, "project_root", lambda: Path(__file__).parent)  # inside a checkout too
    assert common.git_commit() == ("c" * 40, None)


def test_a_new_code_file_not_yet_added_makes_the_tree_dirty(monkeypatch, tmp_path):
    # a bench run from a module not yet committed ran code its commit does not hold
    import subprocess

    monkeypatch.delenv("INVRENDER_SOURCE_COMMIT", raising=False)
    monkeypatch.setattr(common, "project_root", lambda: tmp_path)
    git = ["git", "-c", "user.email=a@b", "-c", "user.name=a"]
    subprocess.run([*git, "init", "-q"], cwd=tmp_path, check=True)
    (tmp_path / "pipeline").mkdir()
    (tmp_path / "pipeline" / "a.py").write_text("x = 1\n")
    (tmp_path / ".gitignore").write_text("*.log\n")
    subprocess.run([*git, "add", "."], cwd=tmp_path, check=True)
    subprocess.run([*git, "commit", "-q", "-m", "a"], cwd=tmp_path, check=True)
    assert common.git_commit()[1] is False
    (tmp_path / "notes.txt").write_text("not code")  # outside the code folders
    (tmp_path / "pipeline" / "run.log").write_text("ignored")
    assert common.git_commit()[1] is False
    (tmp_path / "pipeline" / "bench.py").write_text("y = 2\n")
    assert common.git_commit()[1] is True
