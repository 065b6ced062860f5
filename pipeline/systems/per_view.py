"""Per-view scores from a batch's pooled evaluation: the same metric function, on the same samples (probe
texels, re-rendered pixels, the same Monte Carlo draws), restricted to one view at a time.

A test step scores a batch by pooling its views' samples (one relMSE over every texel of the batch, one
PSNR over every pixel); the stage's number is the mean of those batch values weighted by batch size. Per
view, each metric is computed on that view's samples alone, so a batch of one view gives the batch's value,
and in a larger batch a mean over samples (relMSE, log-L1) is the sample-count-weighted mean of its views'
values; a PSNR or an nMSE (a ratio of sums) is not a mean of its views'.
"""

from __future__ import annotations

from collections.abc import Callable

import torch


def split_views(
    views: list[dict] | None,
    view: torch.Tensor,
    score: Callable[..., dict[str, float]],
    *samples: torch.Tensor,
    prefix: str = "",
) -> None:
    """When `views` (one dict per view of the batch, in batch order) is given: for every view v with
    samples, `score(*[s[view == v] for s in samples])` merged into views[v] with `prefix` on its keys.
    view (N,): the view of each of the N samples. A view without samples gets nothing, as it adds
    nothing to the pooled value. None: nothing to do (the pooled evaluation alone)."""
    if views is None:
        return
    for v, row in enumerate(views):
        sel = view == v
        if bool(sel.any()):
            row.update({f"{prefix}{k}": float(x) for k, x in score(*(s[sel] for s in samples)).items()})
