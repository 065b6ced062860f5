"""The training benches (`bench.overfit`, `bench.train_step`) run end to end on the micro data, and their
rules (plateau, variants) do what they say."""

import math

import pytest
import torch

from pipeline.bench import overfit, train_step


def test_plateau_rule():
    falling = [1.0 / (1 + i) for i in range(40)]
    assert not overfit.plateaued(falling[:19], 10, 0.02)  # fewer than two windows
    assert not overfit.plateaued(falling[:20], 10, 0.02)  # the last 10 steps fell by far more than 2 %
    flat = [1.0, 0.5] * 20  # noisy but no progress
    assert overfit.plateaued(flat, 10, 0.02)
    assert not overfit.plateaued(flat, 10, -1.0)  # a negative gain never stops
    rising = [float(i) for i in range(1, 41)]
    assert overfit.plateaued(rising, 10, 0.0)


def test_variant_parsing():
    assert overfit.parse_variant("base") == ("base", [])
    assert overfit.parse_variant("fast:optim.optimizer.lr=3e-3;lighting.probes=4") == (
        "fast",
        ["optim.optimizer.lr=3e-3", "lighting.probes=4"],
    )
    with pytest.raises(ValueError, match="name"):
        overfit.parse_variant(":a=1")


def test_step_schedule_decays_every_group_to_zero_over_the_run():
    w = torch.nn.Parameter(torch.zeros(1))
    table = torch.nn.Parameter(torch.zeros(1))
    opt = torch.optim.AdamW([{"params": [w]}, {"params": [table], "lr": 0.05}], lr=1e-3)
    assert overfit.step_schedule(opt, None, 10) is None and overfit.step_schedule(opt, "constant", 10) is None
    sched = overfit.step_schedule(opt, "cosine", 10)
    rates = []
    for _ in range(10):
        opt.step()
        sched.step()
        rates.append([g["lr"] for g in opt.param_groups])
    assert rates[4] == pytest.approx([0.5e-3, 0.025])  # half way: half of each group's own rate
    assert rates[-1] == pytest.approx([0.0, 0.0], abs=1e-12)
    with pytest.raises(ValueError, match="bench.schedule='linear'"):
        overfit.step_schedule(opt, "linear", 10)


def test_overfit_bench_runs_small(micro_shards, tmp_path):
    report = overfit.run(
        rooms=(2,),
        variants=(("cosine", ["+bench.schedule=cosine"]),),
        data_dir=str(micro_shards),
        max_steps=3,
        eval_every=2,
        window=1,
        min_gain=-1,
    )
    (run,) = report["runs"]
    assert run["steps"] == 3 and run["stopped_by"] == "max_steps" and len(run["loss"]) == 3
    assert run["schedule"] == "cosine"
    assert run["clip"] == 1.0  # the stage's optimiser: conf/trainer/default.yaml's gradient clip
    assert [c["step"] for c in run["curve"]] == [0, 2, 3]
    for c in run["curve"]:
        assert math.isfinite(c["render_psnr"])
        for kind in ("surf", "free"):
            if kind in c:
                k = c[kind]
                assert k["energy_part"] + k["placement_part"] == pytest.approx(k["nmse"])
                assert sum(v["ray_fraction"] for v in k["classes"].values()) == pytest.approx(1.0)
    walls = run["walls"]  # the NeRF's weight against the rooms' true walls, on miss rays
    assert walls["miss_rays"] > 0
    assert 0 <= walls["weight_within_20pc_of_wall"] <= 1 and 0 <= walls["opacity_mean"] <= 1
    assert walls["opacity_mean"] + walls["far_field_share_mean"] == pytest.approx(1.0, abs=1e-4)
    with pytest.raises(ValueError, match="training split"):
        overfit.run(rooms=(10_000,), data_dir=str(micro_shards), max_steps=1)
    overfit.plot(report, tmp_path / "o.png")
    assert (tmp_path / "o.png").stat().st_size > 5_000


def test_overfit_bench_room_embedding_and_roombox_variants(micro_shards):
    box = ["model.light_net.out_of_view.kind=roombox", "+bench.true_layout=true", "+bench.room_textures=true"]
    variants = (("table", ["+bench.room_embedding=true"]), ("box", box))
    written = []  # what a long bench has published after each run (it keeps the runs it finished)
    report = overfit.run(
        rooms=(2,),
        variants=variants,
        data_dir=str(micro_shards),
        max_steps=2,
        eval_every=2,
        window=1,
        min_gain=-1,
        on_run=lambda partial: written.append([r["variant"] for r in partial["runs"]]),
    )
    assert written == [["table"], ["table", "box"]]
    table, box = report["runs"]
    assert table["walls"]["miss_rays"] > 0 and box["walls"] is None  # walls: the NeRF's only
    assert all(math.isfinite(x) for x in table["loss"] + box["loss"])


def test_self_cpu_times_equal_the_profilers_key_averages():
    import torch
    from torch.profiler import ProfilerActivity, profile

    x = torch.randn(64, 64, requires_grad=True)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(20):  # nested ops, ops that re-dispatch to themselves (sum), a backward pass
            ((x @ x).relu().sum() + torch.cat([x, x]).std()).backward()
    ours = train_step.self_cpu_times(prof.profiler.kineto_results.events())
    theirs = {e.key: e for e in prof.key_averages()}
    assert set(ours) == set(theirs) and len(ours) > 10
    for name, e in theirs.items():
        assert ours[name]["count"] == e.count, name
        assert ours[name]["self_us"] == pytest.approx(e.self_cpu_time_total, rel=1e-9, abs=1e-3), name


def test_train_step_bench_runs_small(micro_shards, micro_exports, tmp_path, monkeypatch):
    # the compiled SSRT setting compiles for tens of seconds: the smoke test times the eager ones
    monkeypatch.setattr(train_step, "SETTINGS", train_step.SETTINGS[:3])
    report = train_step.run(
        batches=1,
        rounds=1,
        steps=2,
        test_views=2,
        data_dir=str(micro_shards),
        overrides=[f"material_path={micro_exports / 'material.pt'}", "profile=micro"],
        pair_seeds=2,
    )
    rows = report["settings"]
    assert [r["setting"] for r in rows] == [name for name, _ in train_step.SETTINGS[:3]]
    assert rows[0]["speedup"] == 1.0 and all(r["median_step_s"] > 0 for r in rows)
    assert set(report["profile_top_operations"]) == {rows[0]["setting"], rows[-1]["setting"]}
    scores = report["paired"]["scores"]
    assert "render_psnr" in scores and all(math.isfinite(v["diff"]) for v in scores.values())
    # the interval is over the training seeds: their per-seed differences are its data
    assert all(v["seeds"] == 2 and len(v["per_seed"]) == 2 for v in scores.values())
    assert all(v["diff"] == pytest.approx(sum(v["per_seed"]) / 2) for v in scores.values())
    train_step.plot(report, tmp_path / "t.png")
    assert (tmp_path / "t.png").stat().st_size > 5_000


def test_train_step_pairs_over_seeds_not_views():
    """Two seeds whose per-view differences are tight around opposite means: the interval over seeds
    holds 0 (the trajectory noise is in it), where a pooled per-view interval would exclude it."""
    first = {m: [1.0] * 8 for m in train_step.SCORES}
    ups = {m: [1.5 + 0.01 * i for i in range(8)] for m in train_step.SCORES}
    downs = {m: [0.6 + 0.01 * i for i in range(8)] for m in train_step.SCORES}
    out = train_step.paired_over_seeds([(first, ups), (first, downs)])
    psnr = out["render_psnr"]
    assert psnr["seeds"] == 2 and psnr["per_seed"] == pytest.approx([0.535, -0.365])
    assert psnr["lo"] < 0 < psnr["hi"] and psnr["diff"] == pytest.approx(0.085)


def test_overfit_bench_runs_materialnet_small(micro_shards, tmp_path):
    report = overfit.run(
        rooms=(2,),
        data_dir=str(micro_shards),
        max_steps=2,
        eval_every=1,
        window=1,
        min_gain=-1,
        network="material",
        variants=(("micro", ["profile=micro"]),),
    )
    (run,) = report["runs"]
    assert report["network"] == "material" and run["steps"] == 2
    for c in run["curve"]:
        for metric in overfit.MATERIAL_MAPS:
            m = c[metric]
            assert m["ratio"] == pytest.approx(m["model"] / max(m["mean_baseline"], 1e-12))
            assert math.isfinite(m["model"]) and m["mean_baseline"] >= 0
    overfit.plot(report, tmp_path / "m.png")
    assert (tmp_path / "m.png").stat().st_size > 5_000
    with pytest.raises(ValueError, match="--network"):
        overfit.run(rooms=(2,), data_dir=str(micro_shards), network="both")


def test_learning_curve_bench_runs_small(micro_root, micro_shards, micro_exports, tmp_path):
    """Two budgets on the micro rooms: each run trained and scored on the test split, insertion paired
    with the reference run (itself: exactly 0), the baselines scored once, and the figure drawn."""
    from pipeline.bench import learning_curve

    report = learning_curve.run(
        rooms=(2,),
        steps=2,
        budgets=(1,),
        seed=0,
        data_dir=str(micro_shards),
        resamples=50,
        overrides=["profile=micro", f"material_path={micro_exports / 'material.pt'}"],
        edit_overrides=["profile=micro", f"data_root={micro_root}", f"data_dir={micro_shards}"],
    )
    runs = {(r["rooms"], r["steps"]): r for r in report["runs"]}
    assert set(runs) == {(2, 1), (2, 2)} and report["reference"] == {"rooms": 2, "steps": 2}
    ref, short = runs[(2, 2)], runs[(2, 1)]
    assert ref["insertion"]["all"]["minus_reference"] == 0.0 and ref["insertion"]["all"]["cases"] >= 1
    assert "insertion/all/scaled_constant" in ref and "insertion/all/scaled_constant" not in short
    gap = short["insertion"]["all"]["psnr"] - ref["insertion"]["all"]["psnr"]
    assert short["insertion"]["all"]["minus_reference"] == pytest.approx(gap, abs=1e-9)
    for r in report["runs"]:
        assert all(math.isfinite(r[k]) for k in ("render_psnr", "surf_light_nmse", "train_minutes"))
    with pytest.raises(ValueError, match="--rooms 10000"):
        learning_curve.first_rooms_loader(str(micro_shards), 10_000, 2, 0)
    learning_curve.plot(report, tmp_path / "lc.png")
    assert (tmp_path / "lc.png").stat().st_size > 10_000


def test_optimiser_step_clips_the_gradient_norm_as_the_stage_does():
    import torch

    from pipeline.bench.common import optimiser_step

    class Quadratic(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.net = torch.nn.Linear(4, 1, bias=False)

        def training_step(self, batch, step):
            return 1e3 * self.net(batch).pow(2).sum()

    model = Quadratic()
    before = model.net.weight.detach().clone()
    opt = torch.optim.SGD(model.net.parameters(), lr=1.0)
    optimiser_step(model, opt, torch.ones(2, 4), 0, clip=0.5)
    assert float((model.net.weight - before).norm()) == pytest.approx(0.5, rel=1e-5)  # SGD moves by the clipped norm


def test_out_of_view_kinds_bench_runs_small(micro_root, micro_shards, micro_exports, tmp_path):
    """Both branches on the micro rooms at a budget of their warm-up steps: each scored on the test split,
    the second paired with the first (insertion by case, re-render by view), the figure drawn."""
    from pipeline.bench import out_of_view_kinds

    report = out_of_view_kinds.run(
        kinds=("nerf", "roombox"),
        minutes=0.0,
        warmup=2,
        seed=0,
        data_dir=str(micro_shards),
        resamples=50,
        overrides=["profile=micro", f"material_path={micro_exports / 'material.pt'}"],
        edit_overrides=["profile=micro", f"data_root={micro_root}", f"data_dir={micro_shards}"],
    )
    nerf, box = report["runs"]
    assert (nerf["kind"], box["kind"]) == ("nerf", "roombox") and nerf["steps"] == box["steps"] == 2
    assert "insertion/all/nearest_probe" in nerf and "insertion/all/nearest_probe" not in box
    gap = box["insertion"]["all"]["psnr"] - nerf["insertion"]["all"]["psnr"]
    assert box["insertion"]["all"]["minus_reference"] == pytest.approx(gap, abs=1e-9)
    assert nerf["insertion"]["all"]["minus_reference"] == 0.0
    assert "render_psnr" in box["views_minus_first"] and math.isfinite(box["test"]["render_psnr"])
    assert [r["kind"] for r in report["summary"]["kinds"]] == ["nerf", "roombox"]
    out_of_view_kinds.plot(report, tmp_path / "k.png")
    assert (tmp_path / "k.png").stat().st_size > 10_000


def test_out_of_view_kinds_scores_exports_of_either_kind_without_training(micro_exports, tmp_path):
    """`--exports NAME=PATH`: each export's kind is read from the export, its weights (not a fresh
    initialisation) are what gets scored, and malformed, repeated or missing exports are refused by name."""
    import torch
    from omegaconf import OmegaConf

    from pipeline.bench import out_of_view_kinds
    from pipeline.bench.common import training_system
    from pipeline.models.export import save_light_export
    from pipeline.models.light_net import LightNet

    overrides = ["profile=micro", f"material_path={micro_exports / 'material.pt'}"]
    cfg = training_system("train_lighting", [*overrides, "model.light_net.out_of_view.kind=roombox"], 1)[2]
    options = OmegaConf.to_container(cfg.model.light_net, resolve=True)
    options["out_of_view"]["roombox"]["texture_size"] = 8  # an option the system's own config does not have
    torch.manual_seed(1)
    save_light_export(tmp_path / "box.pt", options, LightNet(**options))
    assert out_of_view_kinds.export_kind(str(tmp_path / "box.pt")) == "roombox"
    assert out_of_view_kinds.export_kind(str(micro_exports / "light.pt")) == "nerf"
    system = training_system("train_lighting", [*overrides, "model.light_net.out_of_view.kind=roombox"], 0)[0]
    timing = out_of_view_kinds.load_export(system, str(tmp_path / "box.pt"))
    saved = torch.load(tmp_path / "box.pt", weights_only=False)["state_dict"]
    assert all(torch.equal(v, saved[k]) for k, v in system.net.state_dict().items())
    assert timing["steps"] is None and timing["export"] == str(tmp_path / "box.pt")
    assert system.net.out_of_view.texture_size == 8  # the export's configuration, not the composed one
    assert system.hparams["light_net"]["out_of_view"]["roombox"]["texture_size"] == 8
    good = {"nerf": str(micro_exports / "light.pt"), "box": str(tmp_path / "box.pt")}
    assert out_of_view_kinds.parse_exports([f"{k}={v}" for k, v in good.items()]) == good
    for bad, match in (
        (["nerf"], "give NAME=PATH"),
        (["a=x.pt"], "--exports a: x.pt not found"),
        ([f"a={good['nerf']}", f"a={good['box']}"], "'a' given twice"),
    ):
        with pytest.raises((ValueError, FileNotFoundError), match=match):
            out_of_view_kinds.parse_exports(bad)


def test_head_rates_move_each_heads_last_weight_to_a_rate_over_its_fan_in(micro_exports):
    """`+bench.head_rates=fan_in`: every hypernetwork head's last weight sits in one group of its own at the
    stage's rate over its fan-in; every other parameter keeps the stage's rate, none lost or doubled."""
    import torch

    from pipeline.bench.common import training_system

    overrides = ["profile=micro", "gbuffers=ground_truth", f"material_path={micro_exports / 'material.pt'}"]
    system, optimizer, cfg = training_system("train_lighting", overrides, 0)
    before = {id(p) for g in optimizer.param_groups for p in g["params"]}
    rates = overfit.use_head_rates(system, optimizer, "fan_in")
    after = [id(p) for g in optimizer.param_groups for p in g["params"]]
    assert sorted(after) == sorted(before)
    hyper = system.net.out_of_view.hyper
    heads = [*hyper.heads, *(hyper.bias_heads if hyper.split_bias else [])]
    lasts = [h[-1] if isinstance(h, torch.nn.Sequential) else h for h in heads]
    lr = float(cfg.optim.optimizer.lr)
    for last in lasts:
        (group,) = [g for g in optimizer.param_groups if any(p is last.weight for p in g["params"])]
        assert group["params"] == [last.weight] and group["lr"] == pytest.approx(lr / last.in_features)
        (bias_group,) = [g for g in optimizer.param_groups if any(p is last.bias for p in g["params"])]
        assert bias_group["lr"] == pytest.approx(lr)
    assert len(rates) == len(lasts)
    with pytest.raises(ValueError, match="head_rates='sqrt'"):
        overfit.use_head_rates(system, optimizer, "sqrt")
