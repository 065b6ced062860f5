import json

import mlflow
import pytest
from omegaconf import OmegaConf

from pipeline.tracking import project_root, stage_run, tracking_uri, write_metrics


def test_project_root_inside_a_dvc_temp_experiment(tmp_path):
    (tmp_path / "dvc.yaml").write_text("stages: {}\n")
    inner = tmp_path / ".dvc" / "tmp" / "exps" / "tmpabc123" / "stages"
    inner.mkdir(parents=True)
    (inner.parent / "dvc.yaml").write_text("stages: {}\n")
    assert project_root(inner) == tmp_path
    assert project_root(tmp_path / ".dvc") == tmp_path


def test_tracking_uri_is_absolute(monkeypatch, tmp_path):
    monkeypatch.delenv("MLFLOW_TRACKING_URI")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "dvc.yaml").write_text("stages: {}\n")
    uri, artifacts = tracking_uri()
    assert uri == f"sqlite:///{tmp_path / 'mlflow.db'}" and artifacts == (tmp_path / "mlartifacts").as_uri()
    assert tracking_uri("sqlite:///sub/x.db")[0] == f"sqlite:///{tmp_path / 'sub' / 'x.db'}"
    with pytest.raises(ValueError, match="tracking.uri"):
        tracking_uri(str(tmp_path / "mlruns"))


def test_write_metrics_refuses_non_finite_values(tmp_path):
    path = write_metrics(tmp_path / "r" / "metrics.json", {"b": 2, "a": 0.5})
    assert json.loads(path.read_text()) == {"a": 0.5, "b": 2}
    with pytest.raises(ValueError, match="'loss' is not finite"):
        write_metrics(tmp_path / "m.json", {"loss": float("nan")})


def test_stage_run_tags_params_config_and_nesting(monkeypatch):
    monkeypatch.setenv("DVC_EXP_NAME", "exp-test")
    cfg = OmegaConf.create({"profile_name": "micro", "seed": 3, "synth": {"spp": 8}, "tracking": {"uri": None}})
    with stage_run("unit_stage", cfg) as parent:
        with stage_run("unit_stage", cfg, tags={"extra": "1"}) as child:
            mlflow.log_metric("x", 1.0)
    run = mlflow.get_run(child.info.run_id)
    assert run.data.tags["mlflow.parentRunId"] == parent.info.run_id
    assert run.data.tags["stage"] == "unit_stage" and run.data.tags["profile"] == "micro"
    assert run.data.tags["dvc_exp_name"] == "exp-test" and run.data.tags["extra"] == "1" and run.data.tags["git_sha"]
    assert run.data.params["synth.spp"] == "8" and run.data.metrics["x"] == 1.0
    assert run.info.run_name == "unit_stage-micro"
    arts = [a.path for a in mlflow.MlflowClient().list_artifacts(run.info.run_id, "config")]
    assert arts == ["config/unit_stage.yaml"]


def test_sweep_callback_nests_job_runs_under_one_parent():
    from pipeline.tracking.hydra_callbacks import MLflowSweepParent

    cfg = OmegaConf.create({"stage": "unit_sweep", "profile_name": "micro", "tracking": {"uri": None}})
    cb = MLflowSweepParent()
    cb.on_multirun_start(cfg)
    parent = mlflow.active_run().info.run_id
    children = []
    for _ in range(2):
        with stage_run("unit_sweep", cfg) as run:
            children.append(run.info.run_id)
    cb.on_multirun_end(cfg)
    assert mlflow.active_run() is None
    assert {mlflow.get_run(c).data.tags["mlflow.parentRunId"] for c in children} == {parent}
    assert mlflow.get_run(parent).data.tags["sweep"] == "true"


def test_experiment_is_typed_as_model_training(tmp_path):
    """MLflow 3's UI opens an experiment tagged `mlflow.experimentKind=custom_model_development` in its
    model-training view: a new experiment gets the tag, an existing one without it gains it, a kind
    someone chose is kept."""
    from pipeline.tracking.mlflow_run import EXPERIMENT, activate_experiment

    client = mlflow.MlflowClient()

    def kind(name: str) -> str | None:
        return client.get_experiment_by_name(name).tags.get("mlflow.experimentKind")

    def activate(name: str) -> None:
        activate_experiment(OmegaConf.create({"tracking": {"uri": None, "experiment": name}}))

    new, old, chosen = (f"kind-{k}-{tmp_path.name}" for k in ("new", "old", "chosen"))
    activate(new)
    assert kind(new) == "custom_model_development"
    client.create_experiment(old, artifact_location=(tmp_path / "old").as_uri())
    assert kind(old) is None
    activate(old)
    assert kind(old) == "custom_model_development"
    client.create_experiment(
        chosen, artifact_location=(tmp_path / "chosen").as_uri(), tags={"mlflow.experimentKind": "genai_development"}
    )
    activate(chosen)
    assert kind(chosen) == "genai_development"
    activate(EXPERIMENT)  # back to the project's experiment for the tests that follow in this process
