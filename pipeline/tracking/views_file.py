"""`reports/<stage>/test_views.csv`: a stage's per-view test scores, one row per test view, for the
intervals the report computes over views (`pipeline.metrics.bootstrap`).

The first column is the view id; every other column is `<predictor>/<metric>` (the model's, then each
baseline's), a number written at full precision, `nan` where the view has nothing that metric scores.
The file is committed with git (a DVC out with `cache: false`), so it holds nothing that changes from run
to run of the same seed.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

ID = "id"


def write_views(path: str | Path, rows: list[dict]) -> Path:
    """Write `rows` ({"id": view id, column: number, ...}, in test order) as CSV: the columns in the order
    they first appear, a row without a column gets `nan`. Refuses an empty list, a row without an id, a
    repeated id and a value that is not a real number, naming the file (and row)."""
    path = Path(path)
    if not rows:
        raise ValueError(f"{path}: no test views to write")
    columns = list(dict.fromkeys(k for r in rows for k in r if k != ID))
    seen = set()
    out = []
    for i, r in enumerate(rows):
        if ID not in r:
            raise ValueError(f"{path}: row {i} has no {ID!r}")
        if r[ID] in seen:
            raise ValueError(f"{path}: view {r[ID]!r} appears twice")
        seen.add(r[ID])
        line = {ID: str(r[ID])}
        for k in columns:
            v = r.get(k, math.nan)
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise ValueError(f"{path}: view {r[ID]!r}, column {k!r}: {v!r} is not a number")
            line[k] = repr(float(v))
        out.append(line)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=[ID, *columns], lineterminator="\n")
        writer.writeheader()
        writer.writerows(out)
    return path
