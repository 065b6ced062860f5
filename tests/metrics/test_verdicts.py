"""The ablation verdict rule: its false-positive rate over simulated studies with no effect (per claim and
over a Holm family), its power against the noncentral t, its four outcomes and its refusals.

Simulated studies follow the ablations' shape: 3 seeds, 54 test views, a between-seed term and
per-view noise (Gaussian, and heavy-tailed t_3 for views). A rate estimated from N studies has Monte
Carlo standard error sqrt(r (1 - r) / N); the bounds below allow 3 of them."""

import math

import numpy as np
import pytest
from scipy import stats

from pipeline.metrics import verdicts as vd

N_STUDIES = 4000
SEEDS, VIEWS = 3, 54


def _studies(rng, seed_sd: float, view_sd: float, effect: float = 0.0, heavy: bool = False) -> np.ndarray:
    """(N, S, V) paired differences d = effect + a_s + e_sv."""
    a = rng.normal(0, seed_sd, size=(N_STUDIES, SEEDS, 1))
    e = (
        rng.standard_t(3, size=(N_STUDIES, SEEDS, VIEWS)) / math.sqrt(3)
        if heavy
        else rng.normal(size=(N_STUDIES, SEEDS, VIEWS))
    )
    return effect + a + view_sd * e


def _reject_rate(d: np.ndarray, alpha: float = 0.05) -> float:
    p = np.array([vd.seed_effect(list(study))["p"] for study in d])
    return float((p <= alpha).mean())


def _bound(rate: float) -> float:
    return rate + 3 * math.sqrt(rate * (1 - rate) / N_STUDIES)


@pytest.mark.parametrize(
    "seed_sd, view_sd, heavy",
    [(0.0, 1.0, False), (0.3, 1.0, False), (1.0, 0.5, False), (0.3, 1.5, True)],
)
def test_false_positive_rate_is_at_most_five_percent(seed_sd, view_sd, heavy):
    rate = _reject_rate(_studies(np.random.default_rng(7), seed_sd, view_sd, heavy=heavy))
    assert rate <= _bound(0.05), rate


def test_pooling_views_as_independent_is_what_the_rule_avoids():
    """The same null studies tested as if all S x V differences were independent (a z test on the pooled
    mean) reject far more often once seeds differ: the rule's seed-level test is needed."""
    d = _studies(np.random.default_rng(8), 0.3, 1.0)
    pooled = d.reshape(N_STUDIES, -1)
    z = pooled.mean(1) / (pooled.std(1, ddof=1) / math.sqrt(pooled.shape[1]))
    assert (np.abs(z) > 1.96).mean() > 0.3
    assert _reject_rate(d) <= _bound(0.05)


def test_holm_family_error_rate_is_at_most_five_percent():
    """Six null claims per report: the chance that any is called real stays at most 5 %."""
    rng = np.random.default_rng(9)
    family = [_studies(rng, 0.2, 1.0) for _ in range(6)]
    any_false = 0
    for i in range(N_STUDIES):
        claims = {f"c{k}": {"diffs": list(family[k][i]), "expected_sign": 1} for k in range(6)}
        out = vd.decide(claims)
        any_false += any(c["verdict"] in ("supported", "contradicted") for c in out.values())
    assert any_false / N_STUDIES <= _bound(0.05), any_false / N_STUDIES


def test_power_matches_simulation():
    """Seed means of sd sqrt(0.25^2 + 1/54) and a 0.5 effect: the rejection rate over simulated studies
    equals the noncentral-t power within Monte Carlo error."""
    seed_sd, view_sd, effect = 0.25, 1.0, 0.5
    expected = vd.power(effect, math.sqrt(seed_sd**2 + view_sd**2 / VIEWS), SEEDS)
    rate = _reject_rate(_studies(np.random.default_rng(10), seed_sd, view_sd, effect))
    assert abs(rate - expected) <= 3 * math.sqrt(expected * (1 - expected) / N_STUDIES), (rate, expected)
    assert 0.05 < expected < 1
    # more seeds, more power; no spread to measure with one seed
    assert vd.power(effect, 0.3, 5) > vd.power(effect, 0.3, 3)
    assert math.isnan(vd.power(effect, 0.3, 1))


def test_power_is_finite_where_few_seeds_meet_a_large_effect():
    """3 seeds 0.059 apart and a 0.5 effect at a 13-claim family's level (noncentrality 14.6 on 2 df,
    where scipy's noncentral t gives NaN): the power equals the rejection rate of simulated t tests."""
    seed_sd, effect, alpha = 0.0593, 0.5, 0.05 / 13
    expected = vd.power(effect, seed_sd, 3, alpha)
    rng = np.random.default_rng(11)
    means = effect + seed_sd * rng.standard_normal((N_STUDIES, 3))
    t = means.mean(1) / (means.std(1, ddof=1) / math.sqrt(3))
    rate = float(np.mean(np.abs(t) > stats.t.ppf(1 - alpha / 2, 2)))
    assert 0 < expected < 1 and abs(rate - expected) <= 4 * math.sqrt(expected * (1 - expected) / N_STUDIES)


def test_seed_effect_is_the_t_interval_of_seed_means():
    diffs = [np.array([1.0, 2.0, 3.0]), np.array([2.0, 3.0, 4.0]), np.array([0.0, 1.0, 2.0])]
    e = vd.seed_effect(diffs)
    means = np.array([2.0, 3.0, 1.0])
    se = means.std(ddof=1) / math.sqrt(3)
    assert e["diff"] == pytest.approx(2.0) and e["se"] == pytest.approx(se)
    assert e["hi"] - e["diff"] == pytest.approx(4.302652729911275 * se)
    assert e["seeds"] == 3 and e["views"] == 3
    one = vd.seed_effect([np.array([1.0, 2.0])])
    assert one["diff"] == 1.5 and math.isnan(one["p"]) and math.isnan(one["lo"])


def test_holm_steps_down_and_skips_untestable():
    adj = vd.holm({"a": 0.01, "b": 0.04, "c": 0.03, "d": float("nan")})
    assert adj["a"] == pytest.approx(0.03) and adj["c"] == pytest.approx(0.06) and adj["b"] == pytest.approx(0.06)
    assert math.isnan(adj["d"])


def test_four_outcomes():
    up = [np.full(10, 1.0) + s * 0.01 + np.linspace(-0.1, 0.1, 10) for s in range(3)]
    flat = [np.linspace(-1, 1, 10) + s for s in (-0.5, 0.0, 0.5)]
    out = vd.decide(
        {
            "shown": {"diffs": up, "expected_sign": 1},
            "against": {"diffs": [-x for x in up], "expected_sign": 1},
            "noise": {"diffs": flat, "expected_sign": 1},
            "one seed": {"diffs": up[:1], "expected_sign": 1},
            "unavailable": {"diffs": [], "expected_sign": -1},
        }
    )
    assert {k: v["verdict"] for k, v in out.items()} == {
        "shown": "supported",
        "against": "contradicted",
        "noise": "inconclusive",
        "one seed": "not testable",
        "unavailable": "not testable",
    }
    assert set(vd.VERDICTS) >= {v["verdict"] for v in out.values()}


def test_zero_spread_and_diverged_seeds_are_not_tested():
    """Every seed the same difference: the seeds varied nothing, so no test (p NaN), whatever the mean. A
    claim with a diverged seed is `diverged` and leaves the Holm family."""
    same = [np.full(5, 0.5), np.full(5, 0.5)]
    assert math.isnan(vd.seed_effect(same)["p"])
    up = [np.full(10, 1.0) + s * 0.01 + np.linspace(-0.1, 0.1, 10) for s in range(3)]
    out = vd.decide(
        {
            "same": {"diffs": same, "expected_sign": -1},
            "diverged": {"diffs": up[:2], "expected_sign": 1, "diverged": 1},
            "shown": {"diffs": up, "expected_sign": 1},
        }
    )
    assert {k: v["verdict"] for k, v in out.items()} == {
        "same": "not testable",
        "diverged": "diverged",
        "shown": "supported",
    }
    assert out["shown"]["p_holm"] == pytest.approx(out["shown"]["p"])  # a family of one: no multiplier


@pytest.mark.parametrize("seeds", [3, 5, 10])
def test_minimal_detectable_effect_is_where_the_power_reaches_the_target(seeds):
    sd, alpha = 0.3, 0.05 / 4
    mde = vd.minimal_detectable_effect(sd, seeds, alpha)
    assert vd.power(mde, sd, seeds, alpha) == pytest.approx(vd.POWER_TARGET, abs=1e-6)
    assert vd.minimal_detectable_effect(sd, seeds + 1, alpha) < mde  # more seeds, smaller bound
    rng = np.random.default_rng(seeds)  # and by simulation: t tests at that effect reject 80 % of the time
    means = rng.normal(mde, sd, size=(4000, seeds))
    t = means.mean(1) / (means.std(1, ddof=1) / math.sqrt(seeds))
    rate = float(np.mean(2 * stats.t.sf(np.abs(t), seeds - 1) <= alpha))
    assert abs(rate - vd.POWER_TARGET) <= 4 * math.sqrt(0.8 * 0.2 / 4000)
    assert math.isnan(vd.minimal_detectable_effect(sd, 1, alpha))
    needed = vd.seeds_needed(mde, sd, alpha)  # the seed count that reaches the target at that effect
    assert needed <= seeds and vd.power(mde, sd, needed, alpha) >= vd.POWER_TARGET
    assert vd.seeds_needed(1e-6, sd, alpha) is None


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="seed 1: differences hold NaN"):
        vd.seed_effect([np.ones(3), np.array([1.0, np.nan])])
    with pytest.raises(ValueError, match="seed 0: need a non-empty"):
        vd.seed_effect([np.array([])])
    with pytest.raises(ValueError, match="expected_sign"):
        vd.verdict({"seeds": 3, "diff": 1.0}, 0, 0.01)
    with pytest.raises(ValueError, match="seed_sd"):
        vd.power(0.5, 0.0, 3)
