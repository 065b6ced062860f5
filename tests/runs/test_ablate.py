"""Ablations: every conf/ablation/ preset composes onto its stage and takes a training step on micro;
the `ablate` stage and a Hydra multirun of the stage with the same preset and seed give the same
metrics; the `report` stage's verdicts follow the seed spread; pareto fronts are fronts."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import mlflow
import numpy as np
import pytest
import torch

from tests.conftest import CONF, ROOT, compose_cfg, run_stage_process

PRESETS = sorted(p.stem for p in (CONF / "ablation").glob("*.yaml"))


# presets that test no paper claim: a Hydra multirun sweep runs them (README, Ablations), not dvc repro
SWEEP_ONLY = {"spp_2", "spp_4", "spp_16", "gt_gbuffers", "no_mc", "uniform_sampling", "material_resnet34"}


def _preset_file(name: str) -> dict:
    import yaml

    return yaml.safe_load((CONF / "ablation" / f"{name}.yaml").read_text())


def test_dvc_runs_every_claim_at_enough_seeds_and_only_existing_presets():
    import yaml

    entries = yaml.safe_load((ROOT / "params.yaml").read_text())["ablations"]
    listed = {v["preset"] for v in entries.values()}
    assert listed | SWEEP_ONLY == set(PRESETS) and not listed & SWEEP_ONLY
    claims = yaml.safe_load((CONF / "claims" / "paper.yaml").read_text())
    assert set(claims) <= set(PRESETS), "a claim for a preset that does not exist"
    for name in PRESETS:
        meta = {**_preset_file(name)["preset"], **claims.get(name, {})}
        seeds = sorted(v["seed"] for v in entries.values() if v["preset"] == name)
        if meta.get("claim") or name in ("full", "material_small"):  # claims and the references they need
            lighting = "common/lighting" in _preset_file(name)["defaults"]
            render_time = _preset_file(name)["preset"].get("weights_from")  # its units: the views, given weights
            assert seeds == list(range(1 if render_time else 3 if lighting else 2)), (name, seeds)
        else:
            assert name in SWEEP_ONLY, name
    for key, v in entries.items():
        assert key == f"{v['preset']}-s{v['seed']}"
        render_time = _preset_file(v["preset"])["preset"].get("weights_from")
        # a render-time preset waits for (and re-runs after) the weights it scores
        assert v["needs"] == (
            f"outputs/ablate/full-s{v['seed']}" if render_time else f"conf/ablation/{v['preset']}.yaml"
        )


def test_every_claim_declares_one_primary_metric_that_measures_it():
    """conf/claims/: each claim one `primary` (its verdict), secondaries as a list; no primary on a metric a
    degenerate network wins (log-L1: the untrained network; per-texel relative MSE: SSRT alone, dark where
    it misses); every metric one the ablate stage writes."""
    import yaml

    from pipeline.runs.report import LIGHT_COLUMNS, MATERIAL_COLUMNS, expectations

    written = {k for k, _, _ in LIGHT_COLUMNS + MATERIAL_COLUMNS} | {
        "test/surf_light_nmse",
        "test/free_light_nmse",
        "edit/insert/all/lightnet/psnr",
    }
    claims = yaml.safe_load((CONF / "claims" / "paper.yaml").read_text())
    for name, claim in claims.items():
        assert isinstance(claim["primary"], dict) and isinstance(claim.get("secondary", []), list), name
        metrics = expectations({"name": name, **claim})
        assert metrics[0]["role"] == "primary" and all(m["role"] == "secondary" for m in metrics[1:]), name
        primary = metrics[0]["metric"]
        assert not any(bad in primary for bad in ("log_l1", "relmse")), (name, primary)
        assert {m["metric"] for m in metrics} <= written, name


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


# what each preset changes against its reference, as resolved config keys (its `preset.` metadata aside)
ONE_CHANGE = {
    "full": set(),
    "material_small": set(),
    "gt_gbuffers": {"gbuffers"},
    "material_perceptual": {"loss.perceptual_weights"},
    "material_resnet34": {"model.material_net.backbone", "model.material_net.decoder_widths"},  # one backbone
    "no_mc": {"render.estimator"},  # training only: scored with the reference's layer
    "no_mc_render": {"scoring.render"},  # evaluation only: `full`'s weights
    "uniform_sampling": {"render.estimator"},
    "uniform_render": {"scoring.render"},
    "no_rerender_loss": {"lighting.render_weight"},
    "rerender_only": {"lighting.light_weight"},
    "out_of_view_only": {"model.light_net.mode"},
    "ssrt_only": {"model.light_net.mode"},
    "spp_2": {"render.spp"},
    "spp_4": {"render.spp"},
    "spp_16": {"render.spp"},
}


@pytest.mark.parametrize("profile", ["tiny", "paper"])
def test_every_preset_changes_one_thing_against_its_reference(profile, monkeypatch):
    from omegaconf import OmegaConf

    from pipeline.tracking.compose import preset_stage

    monkeypatch.setenv("INVRENDER_VGG16_WEIGHTS", "/weights/vgg16.pth")  # the perceptual preset's one change
    assert set(ONE_CHANGE) == set(PRESETS), "a new preset: say what it changes"

    def resolved(stage, preset):
        return _flat(
            OmegaConf.to_container(compose_cfg(stage, [f"ablation={preset}", f"profile={profile}"]), resolve=True)
        )

    for name in PRESETS:
        stage = preset_stage(name)
        mine = resolved(stage, name)
        ref = resolved(stage, mine["preset.reference"])
        changed = {k for k in set(mine) | set(ref) if not k.startswith("preset.") and mine.get(k) != ref.get(k)}
        assert changed == ONE_CHANGE[name], (name, changed)


def _vgg16_weights(path: Path, layers) -> Path:
    """A torchvision VGG16 state dict with seeded random weights at `path` (tests download no ImageNet
    weights): He-initialised convolutions up to the deepest of `layers`, the ones the perceptual loss
    reads, and the unused rest a single zero broadcast to its shape, so the file holds 7 MB, not 528."""
    from torchvision.models import vgg16

    from pipeline.systems.material_losses import VGG_LAYERS

    with torch.device("meta"):  # shapes only, nothing allocated
        shapes = {k: v.shape for k, v in vgg16(weights=None).state_dict().items()}
    deepest = max(VGG_LAYERS[name] for name in layers)
    g = torch.Generator().manual_seed(0)
    state = {}
    for key, shape in shapes.items():
        read = key.startswith("features.") and int(key.split(".")[1]) <= deepest
        if read and key.endswith(".weight"):
            state[key] = torch.randn(shape, generator=g) * math.sqrt(2 / math.prod(shape[1:]))
        else:
            state[key] = torch.zeros(()).expand(shape)
    torch.save(state, path)
    return path


@pytest.mark.slow
@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_composes_and_takes_a_training_step(micro_shards, micro_exports, preset, tmp_path, monkeypatch):
    from pipeline.runs import ablate
    from pipeline.systems import lighting_training, material_training
    from pipeline.systems.material_training import build_datamodule
    from pipeline.tracking.compose import preset_stage

    base = ["profile=micro", f"ablation={preset}", f"data_dir={micro_shards}"]
    stage = preset_stage(preset)
    overrides = [*base, f"material_path={micro_exports / 'material.pt'}"] if stage == "train_lighting" else base
    vgg_weights = None
    if preset == "material_perceptual":  # without VGG16 weights: reported unavailable, never faked
        monkeypatch.delenv("INVRENDER_VGG16_WEIGHTS", raising=False)
        cfg = compose_cfg(stage, overrides)
        assert "loss.perceptual_weights" in (ablate.unavailable(cfg) or "")
        vgg_weights = _vgg16_weights(tmp_path / "vgg16.pth", cfg.loss.perceptual_layers)
        monkeypatch.setenv("INVRENDER_VGG16_WEIGHTS", str(vgg_weights))
    cfg = compose_cfg(stage, overrides)
    assert cfg.preset.name == preset and cfg.preset.reference in PRESETS
    assert ablate.unavailable(cfg) is None
    if stage == "train_lighting":
        from pipeline.data.datamodules import InteriorVerseDataModule

        system = lighting_training.build_system(cfg)
        batch = next(iter(InteriorVerseDataModule(micro_shards, batch_size=2, lighting=True).train_dataloader()))
        assert cfg.epochs.train_lighting == cfg.ablation_schedule.train_lighting.epochs
    else:
        system = material_training.build_system(cfg)
        batch = next(iter(build_datamodule(cfg).train_dataloader()))
    opt = system.configure_optimizers()
    opt = opt["optimizer"] if isinstance(opt, dict) else opt
    system.trainer = None
    loss = system.training_step(batch, 0) if stage == "train_material" else _lighting_step(system, batch)
    loss.backward()
    opt.step()
    assert torch.isfinite(loss)
    if vgg_weights is not None:  # the perceptual term is on, with the file's weights, and scores the maps
        vgg = system.loss.vgg
        assert system.loss.perceptual_on and system.loss.perceptual_weight > 0
        assert torch.equal(vgg.features[0].weight, torch.load(vgg_weights, weights_only=True)["features.0.weight"])
        with torch.no_grad():
            _, terms = system.loss(system.net(batch["im"]), batch)
        assert torch.isfinite(terms["perceptual"]) and terms["perceptual"] > 0


def _lighting_step(system, batch):
    from unittest import mock

    with mock.patch.object(type(system), "log", lambda *a, **k: None):
        return system.training_step(batch, 0)


@pytest.fixture(scope="module")
def pipeline_outputs(micro_root, micro_shards, micro_exports, tmp_path_factory):
    """An outputs/ folder as the pipeline leaves it before `ablate`: synthesize, preprocess and
    train_material's export (untrained, micro)."""
    out = tmp_path_factory.mktemp("ablate") / "outputs"
    (out / "train_material").mkdir(parents=True)
    os.symlink(micro_root, out / "synthesize")
    os.symlink(micro_shards, out / "preprocess")
    os.symlink(micro_exports / "material.pt", out / "train_material" / "model.pt")
    return out


@pytest.mark.slow
def test_ablate_stage_and_hydra_multirun_give_the_same_metrics(pipeline_outputs, tmp_path):
    from pipeline.runs.ablate import run

    reports = tmp_path / "reports"
    cfg_overrides = [
        "profile=micro",
        "preset=full",
        "seed=0",
        f"paths.outputs={pipeline_outputs}",
        f"paths.reports={reports}",
        "progress=false",
        "timing_views=1",
        "bootstrap=50",
        "tracking.experiment=test-ablate",
    ]
    metrics = run(compose_cfg("ablate", cfg_overrides))
    folder = reports / "ablate" / "full-s0"
    assert json.loads((folder / "metrics.json").read_text()) == pytest.approx(metrics)
    timings = json.loads((folder / "timings.json").read_text())
    assert timings["seconds_per_image"] > 0 and timings["train_minutes"] > 0
    phases = ("train_minutes", "scoring_minutes", "timing_minutes", "test_time_thresholds_minutes", "insertion_minutes")
    assert all(timings[k] > 0 for k in phases) and sum(timings[k] for k in phases) <= timings["stage_minutes"]
    assert {"out_threshold_0.5/seconds_per_image", "out_threshold_0.9/seconds_per_image"} <= set(timings)
    assert "edit/insert/all/lightnet/psnr" in metrics and "out_threshold_0.9/test/render_psnr" in metrics
    assert metrics["health/diverged"] == 0.0 and metrics["health/logged_train_losses"] > 0
    assert len(json.loads((folder / "worst_views.json").read_text())) >= 1
    assert (folder / "insertion_scatter.png").stat().st_size > 10_000
    assert (folder / "worst_views.png").stat().st_size > 10_000
    assert metrics["test/glossy_views"] >= 1 and np.isfinite(metrics["test/glossy_render_psnr"])
    views = (folder / "views.csv").read_text().splitlines()  # per-view scores: a render-time claim pairs by view
    assert views[0] == "id,test/glossy_render_psnr" and len(views) - 1 == metrics["test/glossy_views"]
    mean = np.mean([float(line.rsplit(",", 1)[1]) for line in views[1:]])
    assert mean == pytest.approx(metrics["test/glossy_render_psnr"], rel=1e-9)
    [ablate_run] = mlflow.search_runs(
        experiment_names=["test-ablate"], filter_string="tags.preset = 'full'", output_format="list"
    )
    logged = [a.path for a in mlflow.MlflowClient().list_artifacts(ablate_run.info.run_id, "figures")]
    assert logged == ["figures/insertion_scatter.png", "figures/worst_views.png"]

    # a render-time preset: `full`'s weights (nothing trained) under Li's layer; the light errors are the
    # network's alone, so they equal full's, while everything rendered changes
    render_cfg = compose_cfg("ablate", [o.replace("preset=full", "preset=no_mc_render") for o in cfg_overrides])
    rendered = run(render_cfg)
    render_out = pipeline_outputs / "ablate" / "no_mc_render-s0"
    assert json.loads((render_out / "weights.json").read_text())["weights"] == str(
        pipeline_outputs / "ablate" / "full-s0" / "model.pt"
    )
    assert not (render_out / "checkpoints").exists() and "train_minutes" not in json.loads(
        (reports / "ablate" / "no_mc_render-s0" / "timings.json").read_text()
    )
    for key in ("test/surf_light_log_l1", "test/free_light_log_l1"):
        assert rendered[key] == pytest.approx(metrics[key], rel=1e-6)
    # scored with Li's layer (micro's barely trained network renders near black under either layer, so
    # the scores themselves need not differ here)
    from pipeline.runs.ablate import scoring_config, stage_config

    assert scoring_config(render_cfg, stage_config(render_cfg)).render.estimator == "li2020"
    assert np.isfinite(rendered["test/render_psnr"]) and np.isfinite(rendered["test/glossy_render_psnr"])
    assert (reports / "ablate" / "no_mc_render-s0" / "layers.png").stat().st_size > 10_000
    render_views = (reports / "ablate" / "no_mc_render-s0" / "views.csv").read_text().splitlines()
    assert [v.split(",")[0] for v in render_views] == [v.split(",")[0] for v in views]  # the same views, paired
    missing = compose_cfg(
        "ablate", [o.replace("seed=0", "seed=5").replace("preset=full", "preset=no_mc_render") for o in cfg_overrides]
    )
    with pytest.raises(FileNotFoundError, match="full-s5/model.pt is missing"):
        run(missing)

    run_stage_process(
        "train_lighting",
        ["-m", "ablation=full", "seed=0", "profile=micro", f"paths.outputs={pipeline_outputs}", "progress=false"]
        + ["hydra.sweep.dir=sweep", "tracking.experiment=test-ablate-multirun"],
        tmp_path,
    )
    # the job's report under its own sweep folder (paths.reports is relative)
    job = json.loads((tmp_path / "sweep" / "0" / "reports" / "train_lighting" / "metrics.json").read_text())
    job = {k.removeprefix("mixed/"): v for k, v in job.items()}
    shared = [k for k in job if k.startswith(("test/", "baseline/"))]
    assert shared and all(job[k] == metrics[k] for k in shared), {
        k: (job[k], metrics[k]) for k in shared if job[k] != metrics[k]
    }

    # the report stage gathers it: table, figure, summary, and the run attached to an `ablate` parent
    from pipeline.runs.report import run as report

    numbers = report(
        compose_cfg("report", ["profile=micro", f"paths.reports={reports}", "tracking.experiment=test-ablate"])
    )
    out = reports / "report"
    table = (out / "ablations.md").read_text()
    assert "| full |" in table and "### Stability" in table and numbers["runs"] == 2.0
    assert "no_mc_render-s0/layers.png" in table and "full-s0/worst_views.png" in table
    assert (out / "pareto.png").stat().st_size > 10_000 and "pareto.png" in (out / "summary.md").read_text()
    runs = mlflow.search_runs(experiment_names=["test-ablate"], output_format="list")
    [parent] = [r for r in runs if r.info.run_name == "ablate-micro" and r.data.tags.get("sweep") == "true"]
    children = [r for r in runs if r.data.tags.get("preset") in ("full", "no_mc_render")]
    assert len(children) == 2 and all(c.data.tags["mlflow.parentRunId"] == parent.info.run_id for c in children)


def _fake_runs(tmp_path: Path, values: dict[tuple[str, int], float]) -> Path:
    root = tmp_path / "ablate"
    for (preset, seed), v in values.items():
        d = root / f"{preset}-s{seed}"
        d.mkdir(parents=True)
        meta = {"name": preset, "stage": "train_lighting", "changes": preset, "reference": "full", "seed": seed}
        if preset != "full":
            meta.update(
                claim="c",
                expect={"metric": "test/render_psnr", "higher_is_better": True, "holds_if": "reference_better"},
            )
        (d / "preset.json").write_text(json.dumps(meta))
        (d / "metrics.json").write_text(json.dumps({"test/render_psnr": v, "health/diverged": 0.0}))
        (d / "timings.json").write_text(json.dumps({"seconds_per_image": 1.0 + seed, "train_minutes": 2.0}))
    return root


def test_report_verdicts_are_tested_over_seeds_as_one_family(tmp_path):
    from pipeline.runs.report import claim_verdicts, claims_table, compare, expected_sign, read_runs

    values = {("full", s): 20.0 + 0.2 * s for s in range(3)}
    values.update({("no_mc", s): 19.0 + 0.2 * s + 0.01 * s * s for s in range(3)})  # -1.0, -0.99, -0.96
    values.update({("spp_2", s): 20.0 + (0.3, -0.4, 0.2)[s] for s in range(3)})  # mean near 0, wide
    values.update({("ssrt_only", s): 20.0 + 0.2 * s + 0.5 for s in range(2)})  # the preset better, 2 seeds
    runs = read_runs(_fake_runs(tmp_path, values))
    c = compare(runs, "no_mc", "full", "test/render_psnr")
    assert c["seeds"] == 3 and c["diff"] == pytest.approx(-0.9833, abs=1e-3) and c["hi"] < 0
    v = claim_verdicts(runs)
    key = "test/render_psnr"
    assert v["no_mc", key]["verdict"] == "supported"  # the claim: the reference better, and it is
    assert v["spp_2", key]["verdict"] == "inconclusive"
    # two seeds exactly +0.5 apart from the reference: the seeds varied nothing, so nothing to test against
    assert v["ssrt_only", key]["verdict"] == "not testable" and math.isnan(v["ssrt_only", key]["p_holm"])
    assert v["no_mc", key]["p_holm"] >= v["no_mc", key]["p"]  # adjusted over the family of three claims
    assert 0 < v["spp_2", key]["power"] < 1 and v["no_mc", key]["effect_size"] == 0.5
    assert expected_sign({"higher_is_better": False, "holds_if": "reference_better"}) == 1
    with pytest.raises(ValueError, match="holds_if"):
        expected_sign({"higher_is_better": True, "holds_if": ""})
    rows, numbers = claims_table(runs)
    assert any("| no_mc | **test/render_psnr** |" in r and "| supported |" in r for r in rows)  # the primary, bold
    assert any("| spp_2 |" in r and "inconclusive: no effect larger than" in r for r in rows)
    assert any("| ssrt_only |" in r and "not testable: every seed the same difference" in r for r in rows)
    assert numbers["no_mc/vs_reference/test/render_psnr/hi"] < 0
    assert v["spp_2", key]["mde"] > v["spp_2", key]["effect_size"]  # power < 0.8 at 0.5 dB: the bound is wider
    assert v["spp_2", key]["seeds_needed"] > 3  # and more seeds than were run would be needed


def test_a_material_claim_against_a_half_trained_reference_is_not_comparable(tmp_path):
    """A MaterialNet reference more than 10 % above the main model's normal error makes its presets' claims
    `not comparable` (left out of the family, the reason printed); within 10 % they are judged."""
    from pipeline.runs.report import claim_verdicts, claims_table, read_runs, reference_comparability

    root = tmp_path / "ablate"
    expect = {"metric": "test/normal_angle_deg", "higher_is_better": False, "holds_if": "preset_better"}
    for preset, base in (("material_small", 30.0), ("material_perceptual", 25.0)):
        for seed in range(3):
            d = root / f"{preset}-s{seed}"
            d.mkdir(parents=True)
            meta = {"name": preset, "stage": "train_material", "changes": preset, "reference": "material_small"}
            if preset != "material_small":
                meta.update(claim="c", expect=expect)
            (d / "preset.json").write_text(json.dumps({**meta, "seed": seed}))
            jitter = 0.3 * seed if preset == "material_small" else (0.0, 0.5, 0.9)[seed]
            metrics = {"test/normal_angle_deg": base + jitter, "health/diverged": 0.0}
            (d / "metrics.json").write_text(json.dumps(metrics))
            (d / "timings.json").write_text(json.dumps({"train_minutes": 1.0}))
    runs = read_runs(root)
    key = ("material_perceptual", "test/normal_angle_deg")
    assert reference_comparability(runs, None) == {}  # no main model to compare with: nothing marked
    assert reference_comparability(runs, {"test/normal_angle_deg": 28.0}) == {}  # 30.3 is within 10 % of 28
    far = reference_comparability(runs, {"test/normal_angle_deg": 16.0})
    assert set(far) == {"material_perceptual"} and "30.3°" in far["material_perceptual"]
    assert claim_verdicts(runs)[key]["verdict"] == "supported"  # about 5° better on every seed
    v = claim_verdicts(runs, not_comparable=far)[key]
    assert v["verdict"] == "not comparable" and math.isnan(v["p_holm"])
    rows, _ = claims_table(runs, claim_verdicts(runs, not_comparable=far))
    assert any("| material_perceptual |" in r and "not comparable: reference `material_small`" in r for r in rows)


def test_a_preset_that_diverges_on_a_seed_is_counted_not_judged_on_survivors(tmp_path):
    from pipeline.runs.report import claim_verdicts, claims_table, read_runs

    values = {("full", s): 20.0 + 0.2 * s for s in range(3)}
    values.update({("no_mc", s): 19.0 + 0.2 * s + 0.01 * s * s for s in range(3)})  # clearly worse on 3 seeds
    root = _fake_runs(tmp_path, values)
    path = root / "no_mc-s2" / "metrics.json"
    path.write_text(json.dumps({"test/render_psnr": float("nan"), "health/diverged": 1.0}))
    v = claim_verdicts(read_runs(root))["no_mc", "test/render_psnr"]
    assert v["verdict"] == "diverged" and v["diverged"] == 1 and v["seeds"] == 2 and math.isnan(v["p_holm"])
    rows, numbers = claims_table(read_runs(root))
    assert any("| no_mc |" in r and "diverged (1 of 3 seeds): unstable" in r for r in rows)
    assert numbers["no_mc/vs_reference/test/render_psnr/diverged"] == 1.0


def test_only_the_primary_metric_of_a_claim_is_in_the_family(tmp_path):
    """A claim is decided on its one primary metric; a secondary metric gets its interval and no verdict,
    and adding it leaves the family (and so every Holm p) as it was."""
    from pipeline.runs.report import claim_verdicts, claims_table, expectations, read_runs

    values = {("full", s): 20.0 + 0.2 * s for s in range(3)}
    values.update({("no_mc", s): 19.0 + 0.2 * s + 0.01 * s * s for s in range(3)})
    values.update({("spp_2", s): 20.0 + (0.3, -0.4, 0.2)[s] for s in range(3)})
    root = _fake_runs(tmp_path, values)
    psnr = {"higher_is_better": True, "holds_if": "reference_better"}
    for s in range(3):  # a second metric on which the preset is clearly worse (-2 +- 0.05 over seeds)
        folder = root / f"no_mc-s{s}"
        meta = json.loads((folder / "preset.json").read_text())
        meta.pop("expect")
        meta["primary"] = {"metric": "test/render_psnr", **psnr}
        meta["secondary"] = [{"metric": "test/glossy_render_psnr", **psnr}]
        (folder / "preset.json").write_text(json.dumps(meta))
        for preset, g in (("no_mc", 13.0 + (0.05, -0.05, 0.0)[s]), ("full", 15.0)):
            path = root / f"{preset}-s{s}" / "metrics.json"
            path.write_text(json.dumps({**json.loads(path.read_text()), "test/glossy_render_psnr": g}))
    alone = claim_verdicts(read_runs(_fake_runs(tmp_path / "one", values)))
    v = claim_verdicts(read_runs(root))
    assert set(v) == set(alone) | {("no_mc", "test/glossy_render_psnr")}
    secondary = v["no_mc", "test/glossy_render_psnr"]
    assert secondary["role"] == "secondary" and secondary["verdict"] == "secondary" and "p_holm" not in secondary
    assert secondary["diff"] == pytest.approx(-2.0) and secondary["hi"] < 0  # its interval is still reported
    for key in alone:  # the family is the two primaries, with or without the secondary
        assert v[key]["p_holm"] == pytest.approx(alone[key]["p_holm"]) and v[key]["verdict"] == alone[key]["verdict"]
    rows, numbers = claims_table(read_runs(root))
    claim_rows = rows[: rows.index("")] if "" in rows else rows  # the seed design table follows
    assert sum("| no_mc |" in r for r in claim_rows) == 2
    assert any("| (secondary) | no_mc | test/glossy_render_psnr |" in r and "no verdict" in r for r in rows)
    assert "no_mc/vs_reference/test/glossy_render_psnr/p_holm" not in numbers
    # a claim must say which metric decides it
    several = {"name": "x", "claim": "c", "expect": [{"metric": "a", **psnr}, {"metric": "b", **psnr}]}
    with pytest.raises(ValueError, match="'x'.*primary"):
        expectations(several)
    assert [e["role"] for e in expectations({"claim": "c", "expect": {"metric": "a", **psnr}})] == ["primary"]


def test_a_claim_with_one_seed_is_not_testable(tmp_path):
    from pipeline.runs.report import claim_verdicts, read_runs

    runs = read_runs(_fake_runs(tmp_path, {("full", 0): 20.0, ("no_mc", 0): 19.0}))
    assert claim_verdicts(runs)["no_mc", "test/render_psnr"]["verdict"] == "not testable"


def test_report_refuses_a_run_folder_missing_its_metrics(tmp_path):
    from pipeline.runs.report import read_runs

    root = _fake_runs(tmp_path, {("full", 0): 20.0})
    (root / "full-s0" / "metrics.json").unlink()
    with pytest.raises(FileNotFoundError, match="full-s0: an ablation run without .*metrics.json"):
        read_runs(root)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match="no ablation run folders"):
        read_runs(empty)


def test_pareto_front_is_the_set_no_point_dominates():
    from pipeline.tracking.figures import pareto_front

    xs = [1.0, 2.0, 3.0, 1.5, float("nan")]
    ys = [10.0, 12.0, 11.0, 9.0, 20.0]
    assert pareto_front(xs, ys) == [0, 1]  # (3, 11) is beaten by (2, 12), (1.5, 9) by (1, 10); NaN never


def test_report_lists_the_test_time_thresholds_paired_with_their_weights(tmp_path):
    from pipeline.runs.report import pareto_points, read_runs, table, threshold_runs

    root = _fake_runs(tmp_path, {("full", 0): 20.0, ("full", 1): 20.4})
    for seed, psnr in ((0, 19.5), (1, 19.8)):  # each seed's own weights at u >= 0.5: -0.5, -0.6
        path = root / f"full-s{seed}" / "metrics.json"
        metrics = json.loads(path.read_text())
        path.write_text(json.dumps({**metrics, "out_threshold_0.5/test/render_psnr": psnr}))
        timings = root / f"full-s{seed}" / "timings.json"
        timings.write_text(json.dumps({**json.loads(timings.read_text()), "out_threshold_0.5/seconds_per_image": 0.5}))
    runs = read_runs(root)
    derived = threshold_runs(runs)
    assert list(derived) == ["full:out_threshold_0.5"] and sorted(derived["full:out_threshold_0.5"]) == [0, 1]
    lines, numbers = table({**runs, **derived}, "train_lighting", [("test/render_psnr", "re-render PSNR", True)])
    [row] = [line for line in lines if line.startswith("| full:out_threshold_0.5 |")]
    # paired seed by seed (-0.5, -0.6): the mean and its t interval over the two seeds (t_1 = 12.7)
    assert "19.65 ± 0.15" in row and "0.500" in row and "-0.55 [-1.19, +0.0853] (seeds: -0.5, -0.6)" in row
    assert numbers["full:out_threshold_0.5/vs_reference/test/render_psnr"] == pytest.approx(-0.55)
    [point] = [p for p in pareto_points(runs) if p["label"] == "full:out_threshold_0.5"]
    assert point["seconds"] == 0.5 and point["render_psnr"] == pytest.approx(19.65)
    assert np.isnan(point["train_minutes"]) and np.isnan(point["insertion_psnr"])


def _render_time_runs(tmp_path: Path, shift: float, views: int = 20, with_views=(0, 1, 2)) -> Path:
    """`full` and a render-time preset (`full`'s weights, another layer) on 3 seeds, each with a views.csv
    of `views` glossy scores; the preset's view v under seed s is full's plus `shift` plus view noise."""
    rng = np.random.default_rng(7)
    values = {("full", s): 20.0 + 0.3 * s for s in range(3)}
    values.update({("no_mc_render", s): 20.0 + 0.3 * s + shift for s in range(3)})
    root = _fake_runs(tmp_path, values)
    for s in range(3):
        meta_path = root / f"no_mc_render-s{s}" / "preset.json"
        meta = json.loads(meta_path.read_text())
        meta["weights_from"] = "full"
        meta_path.write_text(json.dumps(meta))
        base = 20.0 + rng.normal(0, 2.0, views)
        moved = base + shift + rng.normal(0, 0.2, views)
        for preset, scores in (("full", base), ("no_mc_render", moved)):
            if s not in with_views:
                continue
            rows = "".join(f"scene_{v:04d}/000,{float(x)!r}\n" for v, x in enumerate(scores))
            (root / f"{preset}-s{s}" / "views.csv").write_text("id,test/render_psnr\n" + rows)
    return root


def test_a_render_time_claim_is_paired_by_view(tmp_path):
    """A render-time preset scores the reference's own weights: the views are the units (conditional on each
    seed's weights), so a shift the seeds alone cannot show (3 seeds) is decided over 20 views; without a
    seed's views.csv the claim falls back to seeds."""
    from pipeline.runs.report import claim_verdicts, claims_table, compare_by_views, read_runs

    runs = read_runs(_render_time_runs(tmp_path / "a", shift=-0.3))
    c = compare_by_views(runs, "no_mc_render", "full", "test/render_psnr")
    assert c["unit"] == "views" and c["seeds"] == 20 and c["weights"] == 3 and len(c["diffs"]) == 20
    assert c["diff"] == pytest.approx(-0.3, abs=0.1) and c["hi"] < 0
    v = claim_verdicts(runs)["no_mc_render", "test/render_psnr"]
    assert v["unit"] == "views" and v["verdict"] == "supported"
    rows, _ = claims_table(runs)
    assert any("| no_mc_render |" in r and "20 views, each the mean over 3 seeds' weights" in r for r in rows)
    fallback = read_runs(_render_time_runs(tmp_path / "b", shift=-0.3, with_views=(0, 1)))
    assert compare_by_views(fallback, "no_mc_render", "full", "test/render_psnr") is None
    assert claim_verdicts(fallback)["no_mc_render", "test/render_psnr"]["unit"] == "seeds"
    bad = _render_time_runs(tmp_path / "c", shift=0.0)
    (bad / "full-s1" / "views.csv").write_text("id,test/render_psnr\nscene_0000/000,nan\n")
    with pytest.raises(ValueError, match=r"full-s1/views.csv: row 2 \(scene_0000/000\): a non-finite score"):
        read_runs(bad)


@pytest.mark.parametrize("noise", ["student_t3", "lognormal"])
def test_render_time_claims_by_view_keep_the_false_positive_rate(noise):
    """No true effect, view differences heavy-tailed (Student t, 3 df) or skewed (centred log-normal), each
    seed's weights moving every view of that seed (which the view-unit question conditions on): the
    two-sided test over 54 views rejects in at most 5 % of studies (+ 3 binomial standard errors)."""
    from pipeline.runs.report import compare_by_views

    rng = np.random.default_rng(3)
    studies, views, rejected = 1000, 54, 0
    for _ in range(studies):
        runs = {"full": {}, "x": {}}
        for s in range(3):
            if noise == "student_t3":
                d = rng.standard_t(3, views)
            else:
                d = rng.lognormal(0.0, 1.0, views) - math.exp(0.5)
            ids = [f"v{v}" for v in range(views)]
            runs["full"][s] = {"views": {i: {"m": 0.0} for i in ids}}
            runs["x"][s] = {"views": {i: {"m": float(x)} for i, x in zip(ids, d, strict=True)}}
        c = compare_by_views(runs, "x", "full", "m")
        rejected += c["p"] <= 0.05
    rate = rejected / studies
    assert rate <= 0.05 + 3 * math.sqrt(0.05 * 0.95 / studies), rate


def test_seeds_are_designed_from_the_references_spread(tmp_path):
    """Before a preset runs, its seed count comes from the reference's own seeds: their spread on the
    claim's primary metric times sqrt(2) (a paired difference), at the family's level; render-time claims
    (views as units) are not designed over seeds."""
    from pipeline.metrics.verdicts import minimal_detectable_effect, seeds_needed
    from pipeline.runs.report import claims_table, read_runs, seed_design

    values = {("full", s): 20.0 + (0.0, 0.4, 0.8)[s] for s in range(3)}  # sd 0.4
    values.update({("no_mc", s): 19.0 for s in range(2)})
    values.update({("no_mc_render", s): 19.5 for s in range(3)})
    root = _fake_runs(tmp_path, values)
    for s in range(3):
        path = root / f"no_mc_render-s{s}" / "preset.json"
        path.write_text(json.dumps({**json.loads(path.read_text()), "weights_from": "full"}))
    [row] = seed_design(read_runs(root))
    sd = 0.4 * math.sqrt(2.0)
    assert row["preset"] == "no_mc" and row["reference_sd"] == pytest.approx(0.4) and row["effect_size"] == 0.5
    assert row["seeds_needed"] == seeds_needed(0.5, sd, 0.05 / 2)  # two claims in the family
    assert row["seeds_run"] == 2 and row["mde_at_seeds"] == pytest.approx(minimal_detectable_effect(sd, 2, 0.025))
    lines, numbers = claims_table(read_runs(root))
    assert any(line.startswith("| no_mc | test/render_psnr | 3 | 0.4 | 0.5 |") for line in lines)
    assert numbers["no_mc/design/seeds_needed"] == row["seeds_needed"]
