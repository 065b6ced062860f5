"""`bench.pipeline_time`: each dvc.yaml stage instance timed by its latest finished top-level MLflow run of
the profile; nested, unfinished and other profiles' runs ignored; instances never run listed as missing."""

import json
import sqlite3

import pytest
import yaml

from pipeline.bench import pipeline_time


def _store(path, runs):
    """A store with MLflow's `runs` and `tags` columns the bench reads; runs: (id, start_min, end_min, status,
    tags)."""
    con = sqlite3.connect(path)
    con.execute("create table runs (run_uuid text, start_time int, end_time int, status text, lifecycle_stage text)")
    con.execute("create table tags (run_uuid text, key text, value text)")
    for rid, start, end, status, tags in runs:
        ms = None if end is None else int(end * 60000)
        con.execute("insert into runs values (?, ?, ?, ?, 'active')", (rid, int(start * 60000), ms, status))
        con.executemany("insert into tags values (?, ?, ?)", [(rid, k, v) for k, v in tags.items()])
    con.commit()
    con.close()


def test_latest_finished_top_level_run_of_each_instance(tmp_path):
    (tmp_path / "dvc.yaml").write_text(
        yaml.safe_dump({"stages": {"synthesize": {"cmd": "a"}, "ablate": {"foreach": "${ablations}"}, "report": {}}})
    )
    (tmp_path / "params.yaml").write_text(yaml.safe_dump({"ablations": {"full-s0": {}, "full-s1": {}}}))
    # runs: id, start and end (minutes), status, tags
    tiny = {"profile": "tiny", "git_sha": "abc-dirty"}
    _store(
        tmp_path / "mlflow.db",
        [
            ("a", 0, 30, "FINISHED", {"stage": "synthesize", **tiny}),
            ("b", 100, 110, "FINISHED", {"stage": "synthesize", **tiny}),  # the latest: 10 minutes
            ("c", 200, 290, "FINISHED", {"stage": "synthesize", "profile": "micro"}),  # another profile
            ("d", 120, 125, "FINISHED", {"stage": "ablate", "preset": "full", "seed": "0", **tiny}),
            ("e", 121, 124, "FINISHED", {"stage": "train_lighting", "mlflow.parentRunId": "d", **tiny}),  # nested
            ("r", 140, 141, "FINISHED", {"stage": "report", **tiny}),  # gathers the ablation runs in a group:
            ("h", 140, 140, "FINISHED", {"stage": "ablate", "mlflow.parentRunId": "r", **tiny}),
            (
                "g",
                122,
                124,
                "FINISHED",
                {"stage": "ablate", "preset": "full", "seed": "1", "mlflow.parentRunId": "h", **tiny},
            ),
            ("f", 130, None, "RUNNING", {"stage": "ablate", "preset": "full", "seed": "1", **tiny}),  # unfinished
        ],
    )
    m = pipeline_time.measure(tmp_path, tmp_path / "mlflow.db", "tiny", 12.0)
    rows = {r["stage"]: r for r in m["each stage instance's latest run"]}
    assert set(rows) == {"synthesize", "ablate@full-s0", "ablate@full-s1", "report"} and m["missing"] == []
    assert rows["synthesize"]["minutes"] == pytest.approx(10.0) and rows["synthesize"]["commit"] == "abc-dirty"
    assert rows["ablate@full-s1"]["minutes"] == pytest.approx(2.0)  # the finished one, not the running one
    assert m["total_minutes"] == pytest.approx(18.0) and m["over_budget_minutes"] == pytest.approx(6.0)
    assert m["minutes by stage (ablation presets summed over seeds)"] == pytest.approx(
        {"synthesize": 10.0, "ablate@full": 7.0, "report": 1.0}
    )
    with pytest.raises(FileNotFoundError, match="no MLflow store"):
        pipeline_time.latest_runs(tmp_path / "absent.db", "tiny")


def test_the_bench_writes_its_json_and_figure(tmp_path, monkeypatch):
    (tmp_path / "dvc.yaml").write_text(yaml.safe_dump({"stages": {"synthesize": {"cmd": "a"}}}))
    (tmp_path / "params.yaml").write_text(yaml.safe_dump({"profile": "tiny"}))
    _store(tmp_path / "mlflow.db", [("a", 0, 3, "FINISHED", {"stage": "synthesize", "profile": "tiny"})])
    monkeypatch.setattr(pipeline_time, "project_root", lambda: tmp_path)
    monkeypatch.setattr("pipeline.bench.common.bench_dir", lambda: tmp_path / "bench")
    path = pipeline_time.main(["--budget", "2"])
    data = json.loads(path.read_text())
    assert data["measured"]["over_budget_minutes"] == pytest.approx(1.0) and data["provenance"]["command"]
    assert path.with_suffix(".png").stat().st_size > 5_000
