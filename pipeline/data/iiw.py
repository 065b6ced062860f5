"""Intrinsic Images in the Wild (IIW): `<root>/<id>.png` (sRGB photo) + `<root>/<id>.json` (judgements).

JSON: `intrinsic_points` [{id, x, y, opaque, ...}] with x normalised by width and y by height in [0, 1),
and `intrinsic_comparisons` [{id, point1, point2, darker in "1"|"2"|"E"|null, darker_score, ...}].
The test split is every 5th id of all ids sorted *as strings* (positions 0, 5, 10, ...), the rest train
(the split behind the published numbers; numeric sorting gives a different one).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np


class IIWError(ValueError):
    """A missing or malformed IIW file; the message names it."""


def list_ids(root: str | Path) -> list[str]:
    """Ids with both files present, sorted as strings. A photo without judgements (or the reverse) is an
    error rather than a silently smaller benchmark."""
    root = Path(root)
    if not root.is_dir():
        raise IIWError(f"{root}: IIW root is not a folder")
    pngs = {p.stem for p in root.glob("*.png")}
    jsons = {p.stem for p in root.glob("*.json")}
    if not pngs and not jsons:
        raise IIWError(f"{root}: no <id>.png / <id>.json pairs")
    for orphan in sorted(pngs ^ jsons):
        kind = "judgements" if orphan in pngs else "photo"
        raise IIWError(f"{root / orphan}: has no {kind} ({orphan}.{'json' if orphan in pngs else 'png'} missing)")
    return sorted(pngs)


def split_ids(ids: list[str]) -> dict[str, list[str]]:
    """{"test": every 5th id of the string-sorted list starting with the first, "train": the rest}."""
    ordered = sorted(ids)
    test = ordered[::5]
    chosen = set(test)
    return {"train": [i for i in ordered if i not in chosen], "test": test}


def read_photo(root: str | Path, image_id: str) -> np.ndarray:
    """(H, W, 3) uint8 sRGB photo."""
    from PIL import Image, UnidentifiedImageError

    path = Path(root) / f"{image_id}.png"
    try:
        with Image.open(path) as img:
            return np.asarray(img.convert("RGB"))
    except (FileNotFoundError, UnidentifiedImageError, OSError) as exc:
        raise IIWError(f"{path}: cannot read photo ({exc})") from exc


def read_judgements(root: str | Path, image_id: str) -> dict:
    """The parsed JSON, checked: both lists present, points with id/x/y/opaque and coordinates in [0, 1),
    comparisons naming known points with a label in {"1", "2", "E", null} and a numeric or null weight."""
    path = Path(root) / f"{image_id}.json"
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise IIWError(f"{path}: no such file") from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise IIWError(f"{path}: not valid JSON ({exc})") from exc
    validate_judgements(data, path)
    return data


def validate_judgements(data, path) -> None:
    if not isinstance(data, dict):
        raise IIWError(f"{path}: expected a JSON object")
    for key in ("intrinsic_points", "intrinsic_comparisons"):
        if not isinstance(data.get(key), list):
            raise IIWError(f"{path}: missing list {key!r}")
    ids = set()
    for p in data["intrinsic_points"]:
        if not isinstance(p, dict) or not {"id", "x", "y", "opaque"} <= p.keys():
            raise IIWError(f"{path}: intrinsic point {p!r} needs id, x, y and opaque")
        if not isinstance(p["id"], int | str) or isinstance(p["id"], bool):
            raise IIWError(f"{path}: intrinsic point id {p['id']!r} is not an integer or a string")
        if not all(_is_number(p[k]) and 0 <= p[k] < 1 for k in ("x", "y")):
            raise IIWError(f"{path}: point {p['id']!r} has x={p['x']!r}, y={p['y']!r}: outside [0, 1) or not numbers")
        ids.add(p["id"])
    for c in data["intrinsic_comparisons"]:
        if not isinstance(c, dict) or not {"point1", "point2", "darker", "darker_score"} <= c.keys():
            raise IIWError(f"{path}: comparison {c!r} needs point1, point2, darker and darker_score")
        for end in ("point1", "point2"):
            if not isinstance(c[end], int | str) or c[end] not in ids:
                raise IIWError(f"{path}: comparison {c.get('id')!r} points at unknown point {c[end]!r}")
        if c["darker"] not in ("1", "2", "E", None):
            raise IIWError(f"{path}: comparison {c.get('id')!r} has darker={c['darker']!r} (1, 2, E or null)")
        if c["darker_score"] is not None and not (_is_number(c["darker_score"]) and c["darker_score"] >= 0):
            raise IIWError(
                f"{path}: comparison {c.get('id')!r} has darker_score={c['darker_score']!r} "
                "(a finite weight >= 0 or null)"
            )


def _is_number(v) -> bool:
    """A finite JSON number (not a bool, not NaN/inf, which Python's json accepts)."""
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
