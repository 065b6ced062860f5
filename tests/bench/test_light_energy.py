"""The light-energy diagnostic: its split of the squared error is exact, and its summary reads biases right."""

import pytest
import torch

from pipeline.bench import light_energy as le


def _probes(seed: int = 0, P: int = 5, T: int = 32) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    # heavy-tailed texels, as lamps make them: a few texels hold most of the energy
    return torch.rand(P, T, 3, generator=g, dtype=torch.float64) ** 8 * 10


def test_energy_and_placement_parts_add_up_to_the_error():
    pred, target = _probes(0), _probes(1)
    s = le.energy_placement_split(pred, target)
    assert s["energy"] > 0 and s["placement"] > 0
    assert float(s["energy"] + s["placement"]) == pytest.approx(float(s["error"]), rel=1e-12)
    assert float(s["target"]) == pytest.approx(float((target**2).sum()), rel=1e-12)


def test_predictors_on_known_cases():
    target = _probes(2)
    # a prediction of the right shape at a third of the energy: rescaling to the true energy is exact
    e = le.predictor_errors(target / 3, target)
    assert float(e["lightnet_placement_true_energy"]) == pytest.approx(0.0, abs=1e-18)
    assert float(e["lightnet"]) > 0
    # the oracle's error is the placement part of any prediction that is flat at the true mean
    flat = target.mean(1, keepdim=True).expand_as(target)
    assert float(e["probe_mean_oracle"]) == pytest.approx(float(le.energy_placement_split(flat, target)["placement"]))
    assert float(le.energy_placement_split(flat, target)["energy"]) == pytest.approx(0.0, abs=1e-18)
    # a probe predicted black stays black when rescaled (no division by zero)
    black = torch.zeros_like(target)
    e0 = le.predictor_errors(black, target)
    assert torch.isfinite(e0["lightnet_placement_true_energy"])
    assert float(e0["lightnet_placement_true_energy"]) == pytest.approx(float((target**2).sum()))


def test_tally_summary_reads_a_uniform_underestimate():
    t = le.EnergyTally()
    for seed in range(3):
        target = _probes(seed)
        hit = torch.zeros(target.shape[:2], dtype=torch.bool)
        hit[:, : target.shape[1] // 2] = True
        u = torch.where(hit, torch.tensor(0.2), torch.tensor(1.0))
        u[0] = 0.7  # one probe's hits are uncertain
        t.add(target / 2, target, hit, u)
    s = t.summary()
    assert s["best_gain"] == pytest.approx(2.0) and s["nmse_at_best_gain"] == pytest.approx(0.0, abs=1e-12)
    assert s["median_predicted_over_true_probe_mean"] == pytest.approx(0.5)
    assert s["nmse"]["lightnet"] == pytest.approx(0.25)  # (L/2 - L)^2 / L^2
    assert s["nmse"]["lightnet_placement_true_energy"] == pytest.approx(0.0, abs=1e-12)
    assert s["lightnet_energy_part"] + s["lightnet_placement_part"] == pytest.approx(s["nmse"]["lightnet"])
    assert sum(c["ray_fraction"] for c in s["classes"].values()) == pytest.approx(1.0)
    assert sum(c["nmse_contribution"] for c in s["classes"].values()) == pytest.approx(s["nmse"]["lightnet"])
    assert all(c["predicted_over_true_energy"] == pytest.approx(0.5) for c in s["classes"].values())
    assert all(c["best_gain"] == pytest.approx(2.0) for c in s["classes"].values())
    assert s["nmse_at_best_class_gains"] == pytest.approx(0.0, abs=1e-12)
    assert s["probes"] == 15


def test_class_gains_fix_a_bias_of_one_class_only():
    target = _probes(4)
    hit = torch.zeros(target.shape[:2], dtype=torch.bool)
    hit[:, ::2] = True
    u = torch.zeros(target.shape[:2])
    pred = torch.where(hit[..., None], target, target / 3)  # hits exact, misses a third of the energy
    t = le.EnergyTally()
    t.add(pred, target, hit, u)
    s = t.summary()
    assert s["classes"]["miss"]["best_gain"] == pytest.approx(3.0) and s["classes"]["hit"][
        "best_gain"
    ] == pytest.approx(1.0)
    assert s["nmse_at_best_class_gains"] == pytest.approx(0.0, abs=1e-12)
    assert s["nmse_at_best_gain"] > 0.01  # one gain cannot fix both classes


def test_best_gains_match_a_search_where_error_is_left():
    t = le.EnergyTally()
    preds, targets, hits = [], [], []
    for seed in range(2):
        target, pred = _probes(10 + seed), _probes(20 + seed)  # unrelated: every fit leaves error
        hit = torch.rand(target.shape[:2], generator=torch.Generator().manual_seed(seed)) < 0.4
        t.add(pred, target, hit, torch.zeros(target.shape[:2]))
        preds.append(pred), targets.append(target), hits.append(hit)
    s = t.summary()
    pred, target, hit = torch.cat(preds), torch.cat(targets), torch.cat(hits)
    den = float((target**2).sum())
    gains = torch.linspace(0.0, 3.0, 30001, dtype=torch.float64)

    def best(p, q):  # the least summed squared error over a fine grid of gains
        return float(((gains[:, None] * p.reshape(1, -1) - q.reshape(1, -1)) ** 2).sum(1).min())

    assert s["nmse_at_best_gain"] * den == pytest.approx(best(pred, target), rel=1e-6)
    by_class = best(pred[hit], target[hit]) + best(pred[~hit], target[~hit])
    assert s["nmse_at_best_class_gains"] * den == pytest.approx(by_class, rel=1e-6)
    assert 0 < s["best_gain"] < 3  # inside the grid
    assert 0 < s["nmse_at_best_class_gains"] < s["nmse_at_best_gain"] < s["nmse"]["lightnet"]


def test_empty_tally_is_refused():
    with pytest.raises(ValueError, match="no probe texel"):
        le.EnergyTally().summary()


def test_missing_exports_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="light.pt"):
        le.run(model_path=tmp_path / "light.pt", material_path=tmp_path / "material.pt")


def test_runs_on_the_micro_data(micro_shards, micro_exports, tmp_path):
    from pipeline.data.datamodules import InteriorVerseDataModule

    report = le.run(micro_exports / "light.pt", str(micro_shards), micro_exports / "material.pt")
    assert report["kinds"], "the micro test views have probes"
    # the oracle's nMSE straight from the stored probes: it holds only if the rays were cut per view and probe
    dm = InteriorVerseDataModule(str(micro_shards), batch_size=1, lighting=True)
    dm.setup("test")
    for kind in report["kinds"]:
        err = den = 0.0
        for batch in dm.plain_loader("test"):
            r = batch["light"][0].kind(kind).texels()[1].double()
            if len(r):
                err += float(((r - r.mean(1, keepdim=True)) ** 2).sum())
                den += float((r**2).sum())
        assert report["kinds"][kind]["nmse"]["probe_mean_oracle"] == pytest.approx(err / den, rel=1e-9)
    for kind, k in report["kinds"].items():
        assert k["probes"] == len(report["probe_means"][kind]) > 0
        assert k["lightnet_energy_part"] + k["lightnet_placement_part"] == pytest.approx(k["nmse"]["lightnet"])
    le.plot(report, tmp_path / "e.png")
    assert (tmp_path / "e.png").stat().st_size > 5_000
