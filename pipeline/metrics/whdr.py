"""IIW Weighted Human Disagreement Rate (docs/design.md, section 6.4).

Points are looked up at row int(y * H), column int(x * W) (truncation, no interpolation); a point's
reflectance is the mean of its three channels, floored at 1e-10. A comparison is skipped when its
`darker` is not one of "1", "2", "E", its weight (`darker_score`) is missing or <= 0, or either point
is not opaque. The algorithm says "1" (point 1 darker) when l2 / l1 > 1 + delta, "2" when
l1 / l2 > 1 + delta, else "E". WHDR = sum of the weights of disagreements / sum of weights.

Conventions: `gamma` scores R^(1/2.2) (as Li et al. 2020 and CGIntrinsics do; comparable with the
paper's IIW number), `linear` scores R itself (the official script's `--linear` path after its sRGB
decode).
"""

from __future__ import annotations

import math

import numpy as np

CONVENTIONS = ("gamma", "linear")
LABELS = ("1", "2", "E")


class JudgementError(ValueError):
    """A malformed IIW judgement file (the message names the offending entry)."""


def _points(judgements: dict) -> dict:
    try:
        points = judgements["intrinsic_points"]
        judgements["intrinsic_comparisons"]
    except (KeyError, TypeError) as exc:
        raise JudgementError(f"judgements lack {exc} (need intrinsic_points and intrinsic_comparisons)") from exc
    out = {}
    for p in points:
        try:
            out[p["id"]] = (float(p["x"]), float(p["y"]), bool(p["opaque"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise JudgementError(f"intrinsic point {p!r}: needs id, x, y and opaque ({exc})") from exc
    return out


def whdr(reflectance, judgements: dict, delta: float = 0.1, convention: str = "gamma") -> float:
    """WHDR of one image as a fraction in [0, 1] (papers print x100); NaN when no comparison counts.

    reflectance: (H, W, 3) linear float array (any global scale); judgements: the parsed IIW JSON."""
    if convention not in CONVENTIONS:
        raise ValueError(f"convention={convention!r}: choose one of {CONVENTIONS}")
    if not delta >= 0:
        raise ValueError(f"delta={delta}: must be >= 0")
    r = np.asarray(reflectance, dtype=np.float64)
    if r.ndim != 3 or r.shape[2] != 3:
        raise ValueError(f"reflectance must be (H, W, 3), got {r.shape}")
    if not np.isfinite(r).all() or (r < 0).any():
        raise ValueError("reflectance has NaN, inf or negative values")
    if convention == "gamma":
        r = r ** (1 / 2.2)
    H, W = r.shape[:2]
    points = _points(judgements)
    wrong = total = 0.0
    for c in judgements["intrinsic_comparisons"]:
        darker, weight = c.get("darker"), c.get("darker_score")
        if darker not in LABELS or weight is None or not float(weight) > 0:
            continue
        ids = (c.get("point1"), c.get("point2"))
        for pid in ids:
            if pid not in points:
                raise JudgementError(f"comparison {c.get('id')!r}: point {pid!r} is not an intrinsic point")
        (x1, y1, o1), (x2, y2, o2) = points[ids[0]], points[ids[1]]
        if not (o1 and o2):
            continue
        l1, l2 = _lookup(r, x1, y1, H, W, ids[0]), _lookup(r, x2, y2, H, W, ids[1])
        if l2 / l1 > 1 + delta:
            guess = "1"
        elif l1 / l2 > 1 + delta:
            guess = "2"
        else:
            guess = "E"
        total += float(weight)
        wrong += float(weight) * (guess != darker)
    return wrong / total if total > 0 else math.nan


def _lookup(r: np.ndarray, x: float, y: float, H: int, W: int, pid) -> float:
    row, col = int(y * H), int(x * W)
    if not (0 <= row < H and 0 <= col < W):
        raise JudgementError(f"point {pid!r} at x={x}, y={y} lies outside the image (normalised coords in [0, 1))")
    return max(1e-10, float(r[row, col].mean()))
