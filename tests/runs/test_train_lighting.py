"""Stage `train_lighting` on the micro profile: every LightNet option takes a step; the stage reports,
per view too, and its DVC out is the same bytes for the same seed."""

import csv
import hashlib

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


STAGE = ["lighting.pixels=16", "lighting.eval_stride=8"]


@pytest.fixture(scope="module")
def tested(micro_shards, tmp_path_factory):
    """[(out root, metrics)] of two runs of the stage with the same seed (test_weights=last), each in its
    own folders and MLflow run."""
    from stages import train_lighting

    runs = []
    for k in range(2):
        tmp = tmp_path_factory.mktemp(f"train_lighting{k}")
        runs.append((tmp, train_lighting.run(_cfg(micro_shards, tmp, *STAGE, "test_weights=last"))))
    return runs


@pytest.mark.xdist_group("train_lighting")  # the worker that runs the module fixture
@pytest.mark.parametrize("test_weights", ["last", "best"])
def test_stage_reports_mode_metrics_and_baselines(micro_shards, tmp_path, test_weights, request):
    from stages import train_lighting

    if test_weights == "last":  # the module's first run
        tmp_path, metrics = request.getfixturevalue("tested")[0]
    else:  # two epochs, so that there is an earlier epoch to choose
        metrics = train_lighting.run(_cfg(micro_shards, tmp_path, *STAGE, "test_weights=best", "trainer.max_epochs=2"))
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
    for name in ("metrics.json", "test_views.csv", "rerender.png", "envmaps.png"):
        assert (tmp_path / "reports" / "train_lighting" / name).is_file(), name
    # model.pt holds the weights the test split was scored with: the last epoch's, or with test_weights=best
    # the best validated checkpoint's when it beat the last epoch
    from pipeline.models.light_net import load_light_export

    ckpts = tmp_path / "outputs" / "checkpoints" / "train_lighting"  # beside the DVC out, not in it
    chosen = metrics["mixed/val/render_psnr_after_training"] > metrics["mixed/val/render_psnr_last_epoch"]
    assert chosen or metrics["mixed/val/render_psnr_after_training"] == metrics["mixed/val/render_psnr_last_epoch"]
    assert not chosen or test_weights == "best"
    state = torch.load(ckpts / ("best.ckpt" if chosen else "last.ckpt"), weights_only=True)["state_dict"]
    net, _ = load_light_export(tmp_path / "outputs" / "train_lighting" / "model.pt")
    for k, v in net.state_dict().items():
        assert torch.equal(v, state[f"net.{k}"]), k


def tree_digest(root) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in root.rglob("*") if p.is_file()
    }


@pytest.mark.xdist_group("train_lighting")
def test_same_seed_gives_a_byte_identical_dvc_out(tested):
    """Every file DVC hashes for the stage (the out and the per-view CSV) has the same bytes in two runs of
    one seed in other folders and MLflow runs; the checkpoints, which name both, live beside the out."""
    (a, metrics_a), (b, metrics_b) = tested
    assert metrics_a == metrics_b
    out_a, out_b = tree_digest(a / "outputs" / "train_lighting"), tree_digest(b / "outputs" / "train_lighting")
    assert out_a == out_b and set(out_a) == {"model.pt"}
    views = "reports/train_lighting/test_views.csv"
    assert (a / views).read_bytes() == (b / views).read_bytes()
    assert (a / "outputs" / "checkpoints" / "train_lighting" / "last.ckpt").is_file()


def metric_key(column: str, mode: str = "mixed") -> str:
    """metrics.json's key for a test_views.csv column."""
    who, metric = column.split("/", 1)
    if who != mode:
        return f"baseline/{column}"
    if metric.startswith("untrained/"):
        return f"{mode}/untrained/test/{metric.removeprefix('untrained/')}"
    return f"baseline/model/{metric}" if metric == "render_psnr_at_probes" else f"{mode}/test/{metric}"


@pytest.mark.xdist_group("train_lighting")
def test_per_view_scores_pool_to_the_test_metrics(tested, micro_shards):
    """test_views.csv holds each test view's own scores on the texels and pixels the batch's evaluation
    scored (the same draws). The stage's numbers pool a batch's views, then average batches weighted by
    their size: a mean over samples (relMSE, log-L1) is the sample-count-weighted mean of the views', and
    a PSNR the PSNR of their count-weighted mean squared error."""
    from pipeline.data.datamodules import InteriorVerseDataModule
    from pipeline.data.lighting import probe_rays
    from pipeline.ops.camera import grid_pixels

    tmp, metrics = tested[0]
    with (tmp / "reports" / "train_lighting" / "test_views.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    columns = list(rows[0])[1:]
    assert columns[0].startswith("mixed/")  # the model first: the report pairs every baseline with it
    assert {metric_key(c) for c in columns} <= set(metrics)
    for column in ("constant/render_psnr", "mixed/free_light_nmse", "probe_median_oracle/surf_light_log_l1"):
        assert column in columns and "mixed/untrained/render_psnr" in columns

    counts, ids = [], []  # per view: texels of each kind and re-rendered pixels, in test order
    dm = InteriorVerseDataModule(micro_shards, batch_size=2, lighting=True)  # the stage's test batches
    for batch in dm.test_dataloader():
        B, _, H, W = batch["im"].shape
        per = {kind: torch.bincount(probe_rays(batch["light"], kind).image, minlength=B) for kind in ("surf", "free")}
        per["render"] = torch.bincount(grid_pixels(batch["mask"][:, 0], 8) // (H * W), minlength=B)
        counts += [{k: int(v[i]) for k, v in per.items()} for i in range(B)]
        ids += batch["id"]
    assert [r["id"] for r in rows] == ids

    def pooled(column: str, weight: str, psnr: bool = False) -> float:
        """metrics.json's number rebuilt from the views': batches of 2 (the stage's batch_size)."""
        total, n = 0.0, 0
        for i in range(0, len(rows), 2):
            w = np.array([c[weight] for c in counts[i : i + 2]], float)
            x = np.array([float(r[column]) for r in rows[i : i + 2]])
            value = -10 * np.log10(w @ 10 ** (-x / 10) / w.sum()) if psnr else w @ x / w.sum()
            total, n = total + value * len(x), n + len(x)
        return total / n

    checked = 0
    for column in columns:
        metric = column.rsplit("/", 1)[1]
        kind = metric.split("_")[0]
        if metric.endswith(("light_relmse", "light_log_l1")):
            assert pooled(column, kind) == pytest.approx(metrics[metric_key(column)], rel=1e-5), column
        elif metric in ("render_relmse", "render_psnr"):
            got = pooled(column, "render", psnr=metric == "render_psnr")
            assert got == pytest.approx(metrics[metric_key(column)], rel=1e-5), column
        else:
            continue
        checked += 1
    assert checked >= 30


def test_unknown_test_weights_are_refused_by_name(micro_shards, tmp_path):
    from stages import train_lighting

    with pytest.raises(ValueError, match="test_weights='newest'"):
        train_lighting.run(_cfg(micro_shards, tmp_path, "test_weights=newest"))


def test_init_light_path_loads_an_exports_weights_or_names_what_differs(micro_shards, micro_exports, tmp_path):
    from pipeline.models.export import ExportError, save_light_export
    from pipeline.models.light_net import LightNet
    from pipeline.systems.lighting_training import build_system, initialise_from_export

    system = build_system(_cfg(micro_shards, tmp_path))
    export = micro_exports / "light.pt"
    checked = initialise_from_export(system, export)
    assert "out_of_view" in checked
    blob = torch.load(export, weights_only=True)
    for k, v in system.net.state_dict().items():
        assert torch.equal(v, blob["state_dict"][k]), k
    other = dict(blob["light_net"], k=3.0)
    save_light_export(tmp_path / "other.pt", other, LightNet(**other))
    with pytest.raises(ExportError, match=r"other.pt.*k: export 3.0, config 10.0"):
        initialise_from_export(build_system(_cfg(micro_shards, tmp_path)), tmp_path / "other.pt")
    with pytest.raises(ExportError, match="missing.pt"):
        initialise_from_export(system, tmp_path / "missing.pt")
