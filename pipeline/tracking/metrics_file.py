"""`reports/<stage>/metrics.json`: the DVC metrics of a stage (flat name -> number)."""

from __future__ import annotations

import json
import math
from pathlib import Path


def write_metrics(path: str | Path, metrics: dict[str, float]) -> Path:
    """Write metrics as sorted, indented JSON. Non-finite values are refused (DVC and JSON cannot
    represent them faithfully) with an error naming the key."""
    clean = {}
    for key, value in metrics.items():
        v = float(value)
        if not math.isfinite(v):
            raise ValueError(f"{path}: metric {key!r} is not finite ({value})")
        clean[key] = int(v) if isinstance(value, (int, bool)) else v
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(clean, indent=2, sort_keys=True) + "\n")
    return path
