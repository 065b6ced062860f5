"""Stage `train_material` on the micro profile: every backbone trains a step, the stage is deterministic
(its DVC out byte for byte), resumes, reports baselines, a gate and per-view scores, and `invrender
predict` round-trips a view."""

import csv
import hashlib
import json
import pickle
import shutil
from pathlib import Path

import mlflow
import numpy as np
import pytest
import torch
import yaml

from tests.conftest import CONF, compose_cfg

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("train_material")]  # one worker runs the module fixture
# the options themselves, not the profile aliases (tiny.yaml, micro.yaml: `defaults: [small]`)
BACKBONES = sorted(p.stem for p in (CONF / "model" / "material_net").glob("*.yaml") if "defaults:" not in p.read_text())


def _cfg(shards, tmp, *extra):
    return compose_cfg(
        "train_material",
        [
            "profile=micro",
            f"data_dir={shards}",
            f"paths.outputs={tmp}/outputs",
            f"paths.reports={tmp}/reports",
            "progress=false",
            "system_metrics=false",
            "tracking.experiment=test-train-material",  # other test modules train too, in parallel
            *extra,
        ],
    )


@pytest.mark.parametrize("option", BACKBONES)
def test_every_backbone_composes_and_takes_a_training_step(micro_shards, tmp_path, option):
    from pipeline.systems.material_training import build_datamodule, build_system

    cfg = _cfg(micro_shards, tmp_path, f"model/material_net={option}")
    preset = yaml.safe_load((CONF / "model" / "material_net" / f"{option}.yaml").read_text())
    assert cfg.model.material_net.backbone == preset["backbone"]
    assert cfg.model.material_net.layout == preset["layout"]
    system = build_system(cfg)
    dm = build_datamodule(cfg)
    batch = next(iter(dm.train_dataloader()))
    opt = system.configure_optimizers()["optimizer"]
    before = [p.detach().clone() for p in system.parameters()]
    loss = system.training_step(batch, 0)
    loss.backward()
    opt.step()
    assert torch.isfinite(loss)
    assert any(not torch.equal(a, b) for a, b in zip(before, system.parameters(), strict=True))
    pred = system(batch["im"])
    assert pred["albedo"].shape == batch["albedo"].shape and pred["depth"].shape == batch["depth"].shape


@pytest.fixture(scope="module")
def trained(micro_shards, tmp_path_factory):
    from stages import train_material

    runs = []
    for k in range(2):  # the same seed twice
        tmp = tmp_path_factory.mktemp(f"train_material{k}")
        metrics = train_material.run(_cfg(micro_shards, tmp))
        runs.append((tmp, metrics))
    return runs


def test_stage_writes_reports_checkpoints_and_tracks(trained):
    tmp, metrics = trained[0]
    on_disk = json.loads((tmp / "reports" / "train_material" / "metrics.json").read_text())
    assert on_disk == pytest.approx(metrics)
    for key in ("test/albedo_mse", "baseline/mean_albedo/albedo_mse", "gate/constant_depth/depth_log_mse"):
        assert np.isfinite(metrics[key])
    gates = [v for k, v in metrics.items() if k.startswith("gate/") and k != "gate/passed"]
    assert metrics["gate/passed"] == float(all(g <= 0.8 for g in gates)) and metrics["global_step"] == 1
    ckpts = tmp / "outputs" / "checkpoints" / "train_material"  # beside the DVC out, not in it
    assert (ckpts / "best.ckpt").is_file() and (ckpts / "last.ckpt").is_file()
    assert (tmp / "reports" / "train_material" / "test_maps.png").stat().st_size > 5_000
    runs = mlflow.search_runs(
        experiment_names=["test-train-material"],
        filter_string="tags.stage = 'train_material' and attributes.status = 'FINISHED'",
    )
    row = runs.iloc[0]
    assert row["tags.data_source"] == "synthetic" and row["params.loss.perceptual_on"] == "False"
    assert row["params.model.material_net.backbone"] == "small" and np.isfinite(row["metrics.train/loss_epoch"])
    assert np.isfinite(row["metrics.val/normal_angle_deg"])


def test_same_seed_gives_identical_metrics(trained):
    (_, a), (_, b) = trained
    assert a == b


def tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in root.rglob("*") if p.is_file()
    }


def test_same_seed_gives_a_byte_identical_dvc_out(trained):
    """Two runs of one seed, in other folders and MLflow runs: every file DVC hashes for the stage (the
    out and the per-view CSV) has the same bytes, so `dvc.lock` does not change on a re-run. The
    checkpoints, which name their run and folder, live outside the out."""
    from pipeline.systems.trainer import resume_checkpoint

    (a, _), (b, _) = trained
    out_a, out_b = tree_digest(a / "outputs" / "train_material"), tree_digest(b / "outputs" / "train_material")
    assert out_a == out_b and set(out_a) == {"model.pt"}
    views = "reports/train_material/test_views.csv"
    assert (a / views).read_bytes() == (b / views).read_bytes()
    run_ids = [resume_checkpoint("last", t / "outputs" / "checkpoints" / "train_material")[1] for t in (a, b)]
    assert run_ids[0] and run_ids[1] and run_ids[0] != run_ids[1]  # what would have changed the out's hash


def read_views(path: Path) -> dict[str, list]:
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    return {k: [r[k] if k == "id" else float(r[k]) for r in rows] for k in rows[0]}


def test_per_view_scores_average_to_the_test_metrics(trained, micro_shards):
    """test_views.csv: one row per test view, the model's and every baseline's score on it; each column's
    mean over views is the stage's test number (the test pass averages the same per-image values)."""
    from pipeline.data.datasets import ShardDataset
    from pipeline.systems.material import METRICS
    from pipeline.systems.material_baselines import BASELINE_MAPS

    tmp, metrics = trained[0]
    views = read_views(tmp / "reports" / "train_material" / "test_views.csv")
    test_split = ShardDataset(micro_shards, "test", lighting=False)
    assert views["id"] == [test_split[i]["id"] for i in range(len(test_split))]
    expected = [f"model/{m}" for m in METRICS] + [f"{b}/{m}" for b, ms in BASELINE_MAPS.items() for m in ms]
    assert list(views)[1:] == expected
    for column in expected:
        values = np.array(views[column])
        assert np.isfinite(values).all(), column
        key = f"test/{column.removeprefix('model/')}" if column.startswith("model/") else f"baseline/{column}"
        assert values.mean() == pytest.approx(metrics[key], rel=1e-5), column  # float32 in the test pass
    runs = mlflow.search_runs(
        experiment_names=["test-train-material"], filter_string="tags.stage = 'train_material'", output_format="list"
    )
    artifacts = {a.path for r in runs for a in mlflow.MlflowClient().list_artifacts(r.info.run_id, "reports")}
    assert "reports/test_views.csv" in artifacts


def test_resume_from_last_continues_the_step_count(trained, micro_shards, tmp_path):
    from stages import train_material

    src, _ = trained[0]
    shutil.copytree(src / "outputs", tmp_path / "outputs")
    metrics = train_material.run(_cfg(micro_shards, tmp_path, "resume=last", "trainer.max_epochs=2"))
    assert metrics["global_step"] == 2 and metrics["epochs"] == 2
    with pytest.raises(FileNotFoundError, match="resume=last"):
        train_material.run(_cfg(micro_shards, tmp_path / "fresh", "resume=last"))
    # a checkpoint whose unpickling would run code is refused before Lightning loads it, and runs nothing
    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return (Path.touch, (marker,))

    evil = tmp_path / "evil" / "outputs" / "checkpoints" / "train_material" / "last.ckpt"
    evil.parent.mkdir(parents=True)
    evil.write_bytes(pickle.dumps({"state_dict": {}, "x": Payload()}))
    with pytest.raises(ValueError, match="not a weights-only checkpoint"):
        train_material.run(_cfg(micro_shards, tmp_path / "evil", "resume=last"))
    assert not marker.exists()


def test_predict_round_trips_a_view(trained, micro_root, tmp_path):
    from pipeline.cli import main
    from pipeline.data import interiorverse as iv

    model = trained[0][0] / "outputs" / "train_material" / "model.pt"
    scene = iv.read_split(micro_root, "test")[0]
    view = iv.list_views(micro_root, scene)[0]
    dst = tmp_path / "pred" / scene
    dst.mkdir(parents=True)
    for name in ("im", "mask"):
        shutil.copy(iv.map_path(micro_root, scene, view, name), dst / f"{view}_{name}.exr")
    assert main(["predict", str(dst / f"{view}_im.exr"), "--out", str(dst), "--checkpoint", str(model)]) == 0
    check = iv.read_view(tmp_path / "pred", scene, view)
    assert check.ok, check.rejections("test")
    src = iv.read_view(micro_root, scene, view)
    for name in ("albedo", "normal", "depth", "material"):
        assert check.maps[name].shape == src.maps[name].shape
    n = check.maps["normal"]
    assert np.allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-3)
    assert (dst / f"{view}_preview.png").stat().st_size > 5_000


def test_predict_rejects_bad_inputs_and_checkpoints(trained, tmp_path, capsys):
    from pipeline.cli import main

    model = trained[0][0] / "outputs" / "train_material" / "model.pt"
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"not a png")
    assert main(["predict", str(bad), "--out", str(tmp_path / "o"), "--checkpoint", str(model)]) == 2
    assert "broken.png" in capsys.readouterr().err
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"junk")
    photo = tmp_path / "photo.png"
    from PIL import Image

    Image.fromarray(np.full((30, 40, 3), 128, np.uint8)).save(photo)
    assert main(["predict", str(photo), "--out", str(tmp_path / "o"), "--checkpoint", str(junk)]) == 2
    assert "junk.pt" in capsys.readouterr().err
    assert main(["predict", str(photo), "--out", str(tmp_path / "o"), "--checkpoint", str(tmp_path / "nope.pt")]) == 2
    assert "nope.pt" in capsys.readouterr().err
    wrong = tmp_path / "wrong.pt"
    torch.save({"format": "invrender.material_net/1", "model": {"backbone": "small"}, "state_dict": {}}, wrong)
    assert main(["predict", str(photo), "--out", str(tmp_path / "o"), "--checkpoint", str(wrong)]) == 2
    assert "lacks input_size, depth_scale" in capsys.readouterr().err  # no silent depth scale of 1.0
    blob = {"format": "invrender.material_net/1", "model": {"backbone": "small"}, "state_dict": {}}
    torch.save({**blob, "input_size": [48, 64], "depth_scale": 1.0}, wrong)
    assert main(["predict", str(photo), "--out", str(tmp_path / "o"), "--checkpoint", str(wrong)]) == 2
    assert "incompatible" in capsys.readouterr().err
    ckpt = trained[0][0] / "outputs" / "checkpoints" / "train_material" / "last.ckpt"
    assert main(["predict", str(photo), "--out", str(tmp_path / "o"), "--checkpoint", str(ckpt)]) == 2
    assert "holds no depth scale" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()  # nothing written by a refused call
    assert main(["predict", str(photo), "--out", str(tmp_path / "o"), "--checkpoint", str(model)]) == 0
    assert (tmp_path / "o" / "photo_albedo.exr").is_file()
