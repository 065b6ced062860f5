"""Verdicts of ablation claims: is a preset's difference from its reference real, across training seeds
and test views, with the error rate controlled over all the claims tested together?

A claim compares a preset with its reference on one metric, paired: the same test views under the same
seed. Its data are per-view differences d[s, v] = preset - reference for seeds s = 1..S and views
v = 1..V. Two sources of noise enter them: which views were drawn (and their Monte Carlo noise), and
which training seed was run (initialisation, batch order), the second shared by every view of a seed. A
rule that pools all S x V differences as independent, or reads only the spread of the reference, misses
the seed term and calls differences real far more often than its nominal rate.

The model here is the balanced one-way random-effects model d[s, v] = mu + a_s + e_sv, a_s ~ (0, sa^2)
between seeds and e_sv ~ (0, se^2) within. Its seed means m_s = mean_v d[s, v] are independent with
variance sa^2 + se^2 / V, so mu_hat = mean_s m_s with standard error sd(m_s) / sqrt(S) and a Student t
on S - 1 degrees of freedom is the exact test under normal seed means (the same interval as restricted
maximum likelihood with Satterthwaite's degrees of freedom on a balanced design). Both noise sources are
in it; the price of few seeds is a wide t quantile (S = 3: 4.30 instead of 1.96). A hierarchical
bootstrap (seeds, then views within a seed) estimates the same variance, but with three seeds it sees
(S - 1) / S of it and has normal tails: a nominal 5 % test would reject a true null with probability
P(|t_2| > 1.96 sqrt(3/2)), about 14 %.

Across the claims of one report the p-values are adjusted by Holm's step-down procedure, so the chance
of any false verdict over the family is at most `alpha`.

Verdicts: `supported` (the difference is real and in the direction the claim predicts), `contradicted`
(real, the other way), `inconclusive` (not shown either way at the family's level: read it as "no
effect larger than the minimal detectable effect", `minimal_detectable_effect`, not as "no effect"),
`not testable` (fewer than two seeds with data, every seed the same difference so that the seeds show no
spread to test against, or the preset cannot run here), `diverged` (a seed's run diverged: the method
failed a stability check, and judging it on the surviving seeds would hide that). Untestable and
diverged claims are not in the Holm family.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy import integrate, special, stats

VERDICTS = ("supported", "contradicted", "inconclusive", "not testable", "diverged")
POWER_TARGET = 0.8  # the power at which `minimal_detectable_effect` is stated


def _seed_means(diffs) -> np.ndarray:
    """Seed means (S,) of per-view paired differences: a list of 1-D arrays (one per seed) or (S, V)."""
    means = []
    for s, d in enumerate(diffs):
        v = np.asarray(d, np.float64)
        if v.ndim != 1 or not len(v):
            raise ValueError(
                f"seed_effect: seed {s}: need a non-empty 1-D array of per-view differences, got {v.shape}"
            )
        if not np.isfinite(v).all():
            raise ValueError(f"seed_effect: seed {s}: differences hold NaN/inf")
        means.append(v.mean())
    return np.asarray(means)


def seed_effect(diffs, level: float = 0.95) -> dict[str, float]:
    """The mean paired difference and its t interval over seeds. diffs: per seed, the per-view differences
    preset - reference (same views in each seed). Returns {"diff", "lo", "hi", "p", "se", "seeds",
    "views"}; with one seed there is no between-seed spread: lo, hi, p and se are NaN."""
    means = _seed_means(diffs)
    S = len(means)
    views = float(np.mean([len(np.asarray(d)) for d in diffs])) if S else 0.0
    out = {"diff": float(means.mean()) if S else float("nan"), "seeds": float(S), "views": views}
    if S < 2:
        return {**out, "lo": float("nan"), "hi": float("nan"), "p": float("nan"), "se": float("nan")}
    se = float(means.std(ddof=1) / math.sqrt(S))
    q = float(stats.t.ppf(0.5 + level / 2, S - 1))
    if se == 0.0:  # every seed the same mean: the seeds varied nothing, so there is no spread to test against
        p = float("nan")
    else:
        p = float(2 * stats.t.sf(abs(out["diff"]) / se, S - 1))
    return {**out, "lo": out["diff"] - q * se, "hi": out["diff"] + q * se, "p": p, "se": se}


def holm(pvalues: dict[str, float]) -> dict[str, float]:
    """Holm-adjusted p-values {name: p_adj} of a family {name: p}; NaN entries (untestable) stay NaN and do
    not count in the family. Reject a claim at family-wise level alpha when p_adj <= alpha."""
    tested = sorted((p, name) for name, p in pvalues.items() if math.isfinite(p))
    m = len(tested)
    out = {name: float("nan") for name in pvalues}
    running = 0.0
    for i, (p, name) in enumerate(tested):
        running = max(running, min(1.0, (m - i) * p))  # step-down: adjusted p-values never decrease
        out[name] = running
    return out


def verdict(effect: dict, expected_sign: int, p_adjusted: float, alpha: float = 0.05) -> str:
    """One claim's verdict from its `seed_effect`, the sign its claim predicts for preset - reference on
    the metric's scale (+1 or -1) and its Holm-adjusted p-value."""
    if expected_sign not in (1, -1):
        raise ValueError(f"verdict: expected_sign must be +1 or -1, got {expected_sign!r}")
    if effect.get("diverged", 0) > 0:
        return "diverged"
    if effect["seeds"] < 2 or not math.isfinite(p_adjusted):
        return "not testable"
    if p_adjusted > alpha:
        return "inconclusive"
    return "supported" if np.sign(effect["diff"]) == expected_sign else "contradicted"


def power(effect_size: float, seed_sd: float, seeds: int, alpha: float = 0.05) -> float:
    """Probability that the two-sided t test on `seeds` seed means rejects at level `alpha` when the true
    mean difference is `effect_size` and the seed means' standard deviation is `seed_sd` (same units)."""
    if seeds < 2:
        return float("nan")
    _check_seed_sd("power", seed_sd)
    return _power_at(effect_size / (seed_sd / math.sqrt(seeds)), seeds - 1, alpha)


def _check_seed_sd(caller: str, seed_sd: float) -> None:
    if not (seed_sd > 0 and math.isfinite(seed_sd)):
        raise ValueError(f"{caller}: seed_sd must be positive and finite, got {seed_sd}")


def _power_at(nc: float, df: int, alpha: float) -> float:
    """The two-sided t test's rejection probability at noncentrality `nc` on `df` degrees of freedom.

    The noncentral t's tails as an integral over the chi-square of the seeds' variance (scipy's `nct`
    returns NaN for few seeds and a large noncentrality, 2 df and nc 15, which this does not). The
    integrand uses scalar special functions: the report evaluates it some 10^5 times, and scipy's
    distribution objects cost ~100 us a call where these cost ~1 us."""
    q = float(stats.t.ppf(1 - alpha / 2, df))
    log_norm = 0.5 * df * math.log(2.0) + special.gammaln(0.5 * df)

    def rejects(v: float) -> float:
        s = q * math.sqrt(v / df)
        chi2_pdf = math.exp(special.xlogy(0.5 * df - 1.0, v) - 0.5 * v - log_norm)
        return (special.ndtr(nc - s) + special.ndtr(-nc - s)) * chi2_pdf

    return float(integrate.quad(rejects, 0.0, math.inf, limit=200)[0])


def minimal_detectable_effect(seed_sd: float, seeds: int, alpha: float = 0.05, target: float = POWER_TARGET) -> float:
    """The smallest true mean difference that the two-sided t test on `seeds` seed means (standard deviation
    `seed_sd`) detects at level `alpha` with probability `target`: `power` solved for the effect (NaN
    under two seeds)."""
    if seeds < 2:
        return float("nan")
    if not 0 < target < 1:
        raise ValueError(f"minimal_detectable_effect: target power must be in (0, 1), got {target}")
    _check_seed_sd("minimal_detectable_effect", seed_sd)
    # power depends on the effect only through nc = effect / (seed_sd / sqrt(seeds)): solve once for nc
    return _detectable_noncentrality(seeds - 1, alpha, target) * seed_sd / math.sqrt(seeds)


@functools.lru_cache(maxsize=256)
def _detectable_noncentrality(df: int, alpha: float, target: float) -> float:
    """The noncentrality at which the two-sided t test on `df` degrees of freedom reaches power `target`."""
    lo, hi = 0.0, 1.0
    while _power_at(hi, df, alpha) < target:  # power grows with nc: bracket, then bisect
        lo, hi = hi, 2 * hi
    for _ in range(60):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if _power_at(mid, df, alpha) < target else (lo, mid)
    return hi


def seeds_needed(
    effect_size: float, seed_sd: float, alpha: float = 0.05, target: float = POWER_TARGET, most: int = 64
) -> int | None:
    """The fewest seeds (at least 2) whose t test detects `effect_size` at level `alpha` with probability
    `target` when seed means spread by `seed_sd`; None if even `most` seeds do not."""
    for seeds in range(2, most + 1):
        if power(effect_size, seed_sd, seeds, alpha) >= target:
            return seeds
    return None


def decide(claims: dict[str, dict], alpha: float = 0.05, level: float = 0.95) -> dict[str, dict]:
    """Verdicts of a family of claims. claims: {name: {"diffs": per-seed per-view differences (empty when
    the preset is unavailable), "expected_sign": +1 | -1, "diverged": seeds whose run diverged (0 if
    absent)}}. Returns {name: seed_effect's fields + "diverged", "p_holm", "verdict"}; the family is every
    claim with at least two seeds, some spread between them and no diverged seed."""
    effects = {}
    for name, c in claims.items():
        diffs = c.get("diffs") or []
        e = seed_effect(diffs, level) if diffs else {"diff": float("nan"), "seeds": 0.0, "p": float("nan")}
        effects[name] = {**e, "diverged": float(c.get("diverged", 0))}
    adjusted = holm({name: e["p"] if not e["diverged"] else float("nan") for name, e in effects.items()})
    return {
        name: {
            **e,
            "p_holm": adjusted[name],
            "verdict": verdict(e, int(claims[name]["expected_sign"]), adjusted[name], alpha),
        }
        for name, e in effects.items()
    }
