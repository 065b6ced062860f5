"""The one bootstrap of the project: percentile intervals of per-view (or per-case) means, resampling
whole groups (the views cases come from) with replacement. Every interval a stage, the report or
docs/results.md prints comes from here.

- `paired_bootstrap`: the mean of paired differences a - b (same views, same seed) and its interval;
- `ratio_bootstrap`: a ratio of means, mean(a) / mean(b) over the same views (e.g. a model's error over a
  baseline's), resampled jointly so the pairing is kept;
- `mean_bootstrap`: the interval of one mean (no pairing).
"""

from __future__ import annotations

import numpy as np


def _labels(n: int, groups) -> tuple[np.ndarray, int]:
    """Integer group labels (n,) in [0, k) and k; each value its own group when `groups` is None."""
    labels = np.arange(n) if groups is None else np.unique(np.asarray(groups), return_inverse=True)[1]
    if len(labels) != n:
        raise ValueError(f"bootstrap: {len(labels)} group labels for {n} values")
    return labels.astype(np.int64), int(labels.max()) + 1


def _checked(values, name: str) -> np.ndarray:
    v = np.asarray(values, np.float64)
    if v.ndim != 1 or not len(v):
        raise ValueError(f"{name}: need a non-empty 1-D array, got shape {v.shape}")
    if not np.isfinite(v).all():
        raise ValueError(f"{name}: values hold NaN/inf")
    return v


def _group_means(columns: list[np.ndarray], groups, resamples: int, seed: int):
    """Resampled means (resamples, len(columns)): whole groups drawn with replacement, each draw's mean
    weighted by the number of values in the drawn groups. None when there are fewer than two groups."""
    labels, k = _labels(len(columns[0]), groups)
    if k < 2:
        return None
    counts = np.bincount(labels, minlength=k).astype(np.float64)
    draws = np.random.default_rng(seed).integers(0, k, size=(resamples, k))
    n = counts[draws].sum(1)
    return np.stack([np.bincount(labels, c, k)[draws].sum(1) / n for c in columns], axis=1)


def _interval(stat: float, draws, level: float, n: int) -> dict[str, float]:
    out = {"diff": stat, "n": float(n)}
    if draws is None:
        return {**out, "lo": float("nan"), "hi": float("nan")}
    tail = (1 - level) / 2 * 100
    lo, hi = np.percentile(draws, [tail, 100 - tail])
    return {**out, "lo": float(lo), "hi": float(hi)}


def paired_bootstrap(diff, resamples: int = 2000, seed: int = 0, level: float = 0.95, groups=None) -> dict[str, float]:
    """Mean of paired per-case differences (n,) and its percentile bootstrap interval. With `groups` (n,)
    (the view each case comes from) whole groups are resampled, since cases of one view share its photo,
    its predictions and so their errors; else single cases. Returns {"diff", "lo", "hi", "n"}; with fewer
    than two groups there is no spread to resample and lo, hi are NaN."""
    d = _checked(diff, "paired_bootstrap")
    return _interval(float(d.mean()), _group_means([d], groups, resamples, seed), level, len(d))


def mean_bootstrap(values, resamples: int = 2000, seed: int = 0, level: float = 0.95, groups=None) -> dict[str, float]:
    """Mean of per-view values (n,) and its percentile interval: {"mean", "lo", "hi", "n"}."""
    out = paired_bootstrap(_checked(values, "mean_bootstrap"), resamples, seed, level, groups)
    return {"mean": out.pop("diff"), **out}


def ratio_bootstrap(
    num, den, resamples: int = 2000, seed: int = 0, level: float = 0.95, groups=None
) -> dict[str, float]:
    """mean(num) / mean(den) over the same views (n,) each, and its percentile interval, the two means
    resampled with the same draws: {"ratio", "lo", "hi", "n"}. The denominator's mean must be positive."""
    a, b = _checked(num, "ratio_bootstrap (numerator)"), _checked(den, "ratio_bootstrap (denominator)")
    if a.shape != b.shape:
        raise ValueError(f"ratio_bootstrap: {len(a)} numerators for {len(b)} denominators")
    if b.mean() <= 0:
        raise ValueError("ratio_bootstrap: the denominator's mean is not positive")
    draws = _group_means([a, b], groups, resamples, seed)
    ratios = None if draws is None else draws[:, 0] / np.maximum(draws[:, 1], np.finfo(float).tiny)
    out = _interval(float(a.mean() / b.mean()), ratios, level, len(a))
    return {"ratio": out.pop("diff"), **out}
