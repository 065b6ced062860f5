"""Stage `train_material` on the micro profile: every backbone trains a step, the stage is deterministic,
resumes, reports baselines and a gate, and `invrender predict` round-trips a view."""

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
    from pipeline.runs.train_material import build_datamodule, build_system

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
    assert (tmp / "outputs" / "train_material" / "checkpoints" / "best.ckpt").is_file() and (
        tmp / "outputs" / "train_material" / "checkpoints" / "last.ckpt"
    ).is_file()
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

    evil = tmp_path / "evil" / "outputs" / "train_material" / "checkpoints" / "last.ckpt"
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
    ckpt = trained[0][0] / "outputs" / "train_material" / "checkpoints" / "last.ckpt"
    assert main(["predict", str(photo), "--out", str(tmp_path / "o"), "--checkpoint", str(ckpt)]) == 2
    assert "holds no depth scale" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()  # nothing written by a refused call
    assert main(["predict", str(photo), "--out", str(tmp_path / "o"), "--checkpoint", str(model)]) == 0
    assert (tmp_path / "o" / "photo_albedo.exr").is_file()
