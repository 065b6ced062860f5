"""Stage `train_lighting` on the micro profile: every LightNet option takes a step; the stage reports."""

import numpy as np
import pytest
import torch

from tests.conftest import CONF, compose_cfg

pytestmark = pytest.mark.slow
# the options themselves, not the profile aliases (tiny.yaml, micro.yaml: `defaults: [small]`)
OPTIONS = sorted(p.stem for p in (CONF / "model" / "light_net").glob("*.yaml") if "defaults:" not in p.read_text())


def _cfg(shards, tmp, *extra):
    return compose_cfg(
        "train_lighting",
        [
            "profile=micro",
            f"data_dir={shards}",
            f"paths.outputs={tmp}/outputs",
            f"paths.reports={tmp}/reports",
            "progress=false",
            "gbuffers=ground_truth",
            "batch_size=2",
            *extra,
        ],
    )


# every mode on the small option; the paper-sized options in the paper's mode
CASES = [(o, m) for o in OPTIONS for m in ("mixed", "ssrt_only", "out_of_view_only") if o == "small" or m == "mixed"]


@pytest.mark.parametrize(("option", "mode"), CASES)
def test_every_light_net_option_takes_a_training_step(micro_shards, tmp_path, option, mode):
    from pipeline.data.datamodules import InteriorVerseDataModule
    from pipeline.systems.lighting import LightingSystem

    cfg = _cfg(
        micro_shards,
        tmp_path,
        f"model/light_net={option}",
        f"model.light_net.mode={mode}",
        "model.light_net.ssrt_compiled=false",
        "lighting.pixels=8",
        "render.spp=2",
    )
    system = LightingSystem(
        light_net=dict(cfg.model.light_net),
        material=None,
        render=dict(cfg.render),
        gbuffers="ground_truth",
        pixels=8,
        probes=2,
        texels=4,
        free_probes=1,
        optimizer=lambda p: torch.optim.AdamW(p, 1e-3),
    )
    dm = InteriorVerseDataModule(micro_shards, batch_size=2, lighting=True)
    batch = next(iter(dm.train_dataloader()))
    loss = system.training_step(batch, 0)
    loss.backward()
    assert torch.isfinite(loss)
    grads = [p.grad for p in system.net.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)


@pytest.mark.parametrize("test_weights", ["last", "best"])
def test_stage_reports_mode_metrics_and_baselines(micro_shards, tmp_path, test_weights):
    from stages import train_lighting

    overrides = ["lighting.pixels=16", "lighting.eval_stride=8", f"test_weights={test_weights}"]
    if test_weights == "best":  # two epochs, so that there is an earlier epoch to choose
        overrides.append("trainer.max_epochs=2")
    metrics = train_lighting.run(_cfg(micro_shards, tmp_path, *overrides))
    for key in (
        "mixed/test/surf_light_relmse",
        "mixed/test/render_psnr",
        "baseline/constant/render_psnr",
        "baseline/scaled_constant/render_psnr",
        "baseline/scaled_constant/free_light_relmse",
        "baseline/probe_mean_oracle/surf_light_nmse",
        "baseline/probe_median_oracle/free_light_log_l1",
        "baseline/probe_profile_oracle/surf_light_nmse",
        "baseline/gt_probes/render_psnr_at_probes",
        "baseline/model/render_psnr_at_probes",
        "mixed/val/render_psnr_before_training",
        "mixed/untrained/test/surf_light_nmse",
        "mixed/untrained/test/free_light_log_l1",
        "mixed/untrained/test/render_psnr",
    ):
        assert np.isfinite(metrics[key]), key
    # the untrained network is scored on the same split and keys as the trained one, not on its own
    untrained = {k.removeprefix("mixed/untrained/test/") for k in metrics if k.startswith("mixed/untrained/test/")}
    assert untrained == {k.removeprefix("mixed/test/") for k in metrics if k.startswith("mixed/test/")}
    for kind in ("surf", "free"):  # every probe ray falls in exactly one ray class
        shares = [metrics[f"mixed/test/{kind}_rays_{c}"] for c in ("hit", "uncertain", "miss")]
        assert sum(shares) == pytest.approx(1.0), kind
        assert np.isfinite(metrics[f"mixed/test/{kind}_light_relmse_miss"])
    assert (tmp_path / "outputs" / "train_lighting" / "model.pt").is_file()
    for name in ("metrics.json", "rerender.png", "envmaps.png"):
        assert (tmp_path / "reports" / "train_lighting" / name).is_file(), name
    # model.pt holds the weights the test split was scored with: the last epoch's, or with test_weights=best
    # the best validated checkpoint's when it beat the last epoch
    from pipeline.models.light_net import load_light_export

    ckpts = tmp_path / "outputs" / "train_lighting" / "checkpoints"
    chosen = metrics["mixed/val/render_psnr_after_training"] > metrics["mixed/val/render_psnr_last_epoch"]
    assert chosen or metrics["mixed/val/render_psnr_after_training"] == metrics["mixed/val/render_psnr_last_epoch"]
    assert not chosen or test_weights == "best"
    state = torch.load(ckpts / ("best.ckpt" if chosen else "last.ckpt"), weights_only=True)["state_dict"]
    net, _ = load_light_export(tmp_path / "outputs" / "train_lighting" / "model.pt")
    for k, v in net.state_dict().items():
        assert torch.equal(v, state[f"net.{k}"]), k


def test_unknown_test_weights_are_refused_by_name(micro_shards, tmp_path):
    from stages import train_lighting

    with pytest.raises(ValueError, match="test_weights='newest'"):
        train_lighting.run(_cfg(micro_shards, tmp_path, "test_weights=newest"))
