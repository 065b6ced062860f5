"""`profile=paper` is the published configuration: every keyed row of docs/method.md's table is what the
composed `paper` and `tiny` configs hold, the built networks have the parameter counts of the released
layer shapes (recomputed here from those shapes), and the profile runs one step of every stage on
micro-sized data on a CPU."""

import re
import shutil

import numpy as np
import pytest
import torch
import yaml
from omegaconf import OmegaConf

from tests.conftest import ROOT, compose_cfg

METHOD = ROOT / "docs" / "method.md"
ROW = re.compile(r"^\|(?P<cells>.*)\|\s*$")


def _table_rows() -> list[dict]:
    """Rows of method.md's configuration tables that name a key: {key, stage, paper, tiny, line}."""
    rows = []
    for n, line in enumerate(METHOD.read_text().splitlines(), 1):
        m = ROW.match(line)
        if not m:
            continue
        cells = [c.strip() for c in m["cells"].split("|")]
        if len(cells) != 7:
            continue
        key = cells[3].strip("`")
        if ":" not in key or key.startswith("-"):
            continue
        stage, dotted = key.split(":", 1)
        rows.append({"stage": stage, "key": dotted, "paper": cells[4], "tiny": cells[5], "line": n})
    return rows


ROWS = _table_rows()


def test_the_method_table_has_keyed_rows_for_every_network_and_training():
    stages = {r["stage"] for r in ROWS}
    assert {"train_material", "train_lighting", "preprocess", "finetune"} <= stages
    assert len(ROWS) >= 60


@pytest.mark.parametrize("profile", ["paper", "tiny"])
def test_every_table_value_is_what_the_profile_composes(profile):
    configs = {}
    wrong = []
    for row in ROWS:
        if row["stage"] not in configs:  # compose each stage once (setdefault would compose on every row)
            configs[row["stage"]] = compose_cfg(row["stage"], [f"profile={profile}"])
        cfg = configs[row["stage"]]
        node = OmegaConf.select(cfg, row["key"], default=None)
        actual = OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node
        cell = row[profile]
        assert cell.startswith("`") and cell.endswith("`"), f"method.md:{row['line']}: value not in backticks"
        expected = yaml.safe_load(cell.strip("`"))
        if actual != expected:
            wrong.append(f"method.md:{row['line']} {row['stage']}:{row['key']}: table {expected!r}, config {actual!r}")
    assert not wrong, "\n".join(wrong)


def _conv_gn(cin: int, cout: int) -> int:
    """A 3x3 convolution with bias followed by an affine GroupNorm."""
    return 9 * cin * cout + cout + 2 * cout


def _linear(cin: int, cout: int) -> int:
    return cin * cout + cout


def released_mgnet_decoder(out: int) -> int:
    """mgnet/models/network.py:160-176: dconv1 1024->512 on the bottleneck; then the skips x4 (512),
    x3 (256), x2 (128), x1 (64) are concatenated before the convolutions to 256, 128, 64, 64; a 3x3
    output convolution 64 -> out."""
    chain = [(1024, 512), (512 + 512, 256), (256 + 256, 128), (128 + 128, 64), (64 + 64, 64)]
    return sum(_conv_gn(cin, cout) for cin, cout in chain) + 9 * 64 * out + out


def released_local_mlp(d: int) -> int:
    """lightnet/models/network/local.py:107-117: Linear(D, 512), 8 more hidden layers of 512 with the
    input concatenated again after hidden layer 4, Linear(512, 3)."""
    hidden = [_linear(d, 512)] + [_linear(512 + (d if i == 5 else 0), 512) for i in range(1, 9)]
    return sum(hidden) + _linear(512, 3)


def released_hypernetworks(layer_shapes: list[tuple[int, int]]) -> int:
    """lightnet/models/network/hyper.py:70-100, 158-159: a weight and a bias hypernetwork, each a trunk
    512 -> 1024 -> 1024 and per generated layer a block 1024 -> 4096 -> 4096 -> its parameters."""
    trunk = _linear(512, 1024) + _linear(1024, 1024)
    block = _linear(1024, 4096) + _linear(4096, 4096)
    weights = trunk + sum(block + _linear(4096, cout * cin) for cin, cout in layer_shapes)
    biases = trunk + sum(block + _linear(4096, cout) for _, cout in layer_shapes)
    return weights + biases


def _count(module) -> int:
    return sum(p.numel() for p in module.parameters())


def test_mgnet_has_the_released_parameter_count():
    from torchvision.models import densenet121

    from pipeline.models.material_net import MaterialNet

    cfg = compose_cfg("train_material", ["profile=paper"])
    net = MaterialNet(**OmegaConf.to_container(cfg.model.material_net, resolve=True))
    assert _count(net.encoder) == _count(densenet121(weights=None).features)
    decoders = {k: _count(d) for k, d in net.decoders.items()}
    assert decoders == {
        "albedo": released_mgnet_decoder(3),
        "normal": released_mgnet_decoder(3),
        "material": released_mgnet_decoder(2),
        "depth": released_mgnet_decoder(3),  # three channels, averaged (network.py:214-216)
    }
    assert sum(decoders.values()) == 31_574_219  # the released decoders, as docs/method.md states


def test_light_net_has_the_released_parameter_counts():
    from torchvision.models import resnet34

    from pipeline.models.light_net import LightNet

    cfg = compose_cfg("train_lighting", ["profile=paper"])
    ln = OmegaConf.to_container(cfg.model.light_net, resolve=True)
    net = LightNet(**ln)
    plain = resnet34(weights=None)
    encoder = _count(plain) - _count(plain.fc)
    assert _count(net.local.encoder) == encoder and _count(net.out_of_view.encoder) == encoder
    # D = 512 features + 2 map_dim per encoded input: direction, normal, Kd, Ks, roughness (local.py:201-239)
    d = 512 + 2 * ln["local"]["rff_features"] * 5
    assert _count(net.local.mlp) == released_local_mlp(d)
    shapes = [(39, 64), (64, 64), (64, 64), (64, 4)]  # hyper.py:152-157
    assert _count(net.out_of_view.hyper) == released_hypernetworks(shapes) == 216_628_100
    params = net.out_of_view.hyper(torch.zeros(1, 512))
    assert sum(w.numel() + b.numel() for w, b in params) == sum(_linear(i, o) for i, o in shapes) == 11_140
    assert net.out_of_view.far is None and isinstance(net.out_of_view.to_feature, torch.nn.Identity)
    assert _count(net) == 2 * encoder + released_local_mlp(d) + 216_628_100


@pytest.fixture
def paper_tmp_path(tmp_path):
    """tmp_path whose `outputs` (about 5 GB of paper-sized weights and checkpoints) is removed whatever
    the test's outcome: pytest keeps a failed test's tmp_path, and kept ones of this size fill a disk."""
    yield tmp_path
    shutil.rmtree(tmp_path / "outputs", ignore_errors=True)


@pytest.mark.slow
def test_paper_profile_runs_one_step_of_every_stage_on_micro_data(paper_tmp_path):
    """Every stage under profile=paper with only the data sizes, step counts and evaluation samples cut to
    micro: the released networks, loss and optimiser all run on a CPU. (The evaluation's 1024 spp is the
    profile's, checked by the method table; at micro sizes it only multiplies the paper local MLP's
    evaluations, the render layer's chunking is tested on its own.)"""
    tmp_path = paper_tmp_path
    from stages import evaluate, finetune, preprocess, synthesize, train_lighting, train_material

    common = [
        "profile=paper",
        f"paths.outputs={tmp_path}/outputs",
        f"paths.reports={tmp_path}/reports",
        "progress=false",
        "num_workers=0",
        "tracking.experiment=test-paper-profile",
    ]
    micro_synth = [
        "synth.scenes=3",
        "synth.views=2",  # stand-ins need test views for both IIW and NYUv2 splits
        "synth.width=64",
        "synth.height=48",
        "synth.spp=8",
        "synth.lighting={surface_stride: 16, hemi_size: [4, 8], free_points: 2, sphere_size: [8, 16], spp: 4}",
        "ood.scenes=2",
    ]
    one_step = ["trainer.limit_train_batches=1", "trainer.limit_val_batches=1", "trainer.limit_test_batches=1"]
    synthesize.run(compose_cfg("synthesize", [*common, *micro_synth]))
    preprocess.run(
        compose_cfg("preprocess", [*common, "preprocess.height=48", "preprocess.width=64", "preprocess.shard_size=4"])
    )
    tm = train_material.run(
        compose_cfg(
            "train_material", [*common, *one_step, "trainer.max_epochs=1", "batch_size=2", "system_metrics=false"]
        )
    )
    assert tm["global_step"] == 1 and np.isfinite(tm["test/normal_angle_deg"])
    tl = train_lighting.run(
        compose_cfg(
            "train_lighting",
            [
                *common,
                *one_step,
                "trainer.max_epochs=1",
                "batch_size=2",
                "lighting.pixels=8",
                "lighting.figure_views=1",
                "lighting.eval_stride=16",
                # the untrained network's scores repeat the validation and test passes the stage runs anyway
                "lighting.validate_before=false",
                "lighting.test_before=false",
                "render.eval_spp=16",
            ],
        )
    )
    assert np.isfinite(tl["mixed/test/render_psnr"])
    ft = finetune.run(compose_cfg("finetune", [*common, *one_step, "trainer.max_epochs=1", "finetune.batch_size=2"]))
    assert ft["global_step"] >= 1
    light = 'light_overrides=["render.eval_spp=16","lighting.eval_stride=16"]'  # as the training run above
    ev = evaluate.run(compose_cfg("evaluate", [*common, light]))
    assert np.isfinite(ev["finetuned/synthetic/normal_angle_deg"])
    assert np.isfinite(ev["trained/synthetic_ood/gate/mean_material/roughness_mse"])
    assert np.isfinite(ev["lightnet/synthetic_ood/render_psnr"])
