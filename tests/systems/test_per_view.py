"""Per-view test scores: the split of a batch's pooled evaluation by view, the rows of a distributed test
gathered in the split's order, and test_views.csv."""

from __future__ import annotations

import csv
import math

import pytest
import torch

from pipeline.metrics.image import psnr_tonemapped
from pipeline.metrics.lighting import light_errors
from pipeline.systems.per_view import split_views
from pipeline.systems.trainer import gather_rows
from pipeline.tracking.views_file import write_views


def test_split_views_scores_each_view_on_its_own_samples():
    g = torch.Generator().manual_seed(0)
    view = torch.tensor([0, 0, 2, 0, 2, 2, 2])  # view 1 has no samples
    pred, target = torch.rand(7, 3, generator=g), torch.rand(7, 3, generator=g)
    scale = torch.rand(7, generator=g) + 0.5
    views = [{"id": "a"}, {"id": "b"}, {"id": "c"}]
    split_views(views, view, light_errors, pred, target, scale, prefix="surf_")
    assert views[1] == {"id": "b"}  # nothing to score: nothing added, as in the pooled value
    for v in (0, 2):
        sel = view == v
        assert views[v]["surf_light_nmse"] == light_errors(pred[sel], target[sel], scale[sel])["light_nmse"]
    # a mean over samples pools as the sample-count-weighted mean of the views'
    pooled = light_errors(pred, target, scale)["light_relmse"]
    assert pooled == pytest.approx((3 * views[0]["surf_light_relmse"] + 4 * views[2]["surf_light_relmse"]) / 7)
    # a PSNR pools as the PSNR of the count-weighted mean squared error, not as a mean of PSNRs
    psnr = {v: float(psnr_tonemapped(pred[view == v], target[view == v], scale[view == v])) for v in (0, 2)}
    mse = (3 * 10 ** (-psnr[0] / 10) + 4 * 10 ** (-psnr[2] / 10)) / 7
    assert float(psnr_tonemapped(pred, target, scale)) == pytest.approx(-10 * math.log10(mse), rel=1e-5)
    split_views(None, view, light_errors, pred, target, scale)  # no views: nothing to do


def test_gather_rows_in_one_process_returns_the_rows():
    rows = [{"id": "a", "x": 1.0}]
    assert gather_rows(rows) is rows


def _gather_worker(rank: int, world: int, init: str, out: str) -> None:
    import json

    import torch.distributed as dist

    dist.init_process_group("gloo", init_method=init, rank=rank, world_size=world)
    # 5 views dealt round-robin to 2 processes, the first repeated to even out the last batch
    dealt = {0: ["v0", "v2", "v4"], 1: ["v1", "v3", "v0"]}[rank]
    rows = gather_rows([{"id": v, "rank": float(rank)} for v in dealt])
    if rank == 0:
        with open(out, "w") as f:
            json.dump(rows, f)
    dist.destroy_process_group()


@pytest.mark.slow
def test_gather_rows_restores_the_split_order_across_processes(tmp_path):
    import json

    import torch.multiprocessing as mp

    out = tmp_path / "rows.json"
    mp.spawn(_gather_worker, args=(2, f"file://{tmp_path / 'store'}", str(out)), nprocs=2, join=True)
    rows = json.loads(out.read_text())
    assert [r["id"] for r in rows] == ["v0", "v1", "v2", "v3", "v4"]
    assert rows[0]["rank"] == 0.0  # a repeated view keeps the row of the process it was dealt to first


def test_write_views_writes_exact_numbers_and_nan_for_missing(tmp_path):
    rows = [{"id": "s/000", "model/a": 0.1, "base/a": 1 / 3}, {"id": "s/001", "model/a": 2.5}]
    path = write_views(tmp_path / "r" / "test_views.csv", rows)
    with path.open(newline="") as f:
        back = list(csv.DictReader(f))
    assert list(back[0]) == ["id", "model/a", "base/a"]
    assert float(back[0]["base/a"]) == 1 / 3 and back[1]["id"] == "s/001"
    assert math.isnan(float(back[1]["base/a"]))  # the view has nothing that metric scores
    first = path.read_bytes()
    write_views(path, rows)
    assert path.read_bytes() == first


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        ([], "no test views"),
        ([{"model/a": 1.0}], "row 0 has no 'id'"),
        ([{"id": "v", "model/a": 1.0}, {"id": "v", "model/a": 2.0}], "'v' appears twice"),
        ([{"id": "v", "model/a": "1.0"}], "column 'model/a'"),
    ],
)
def test_write_views_refuses_bad_rows_naming_the_file(tmp_path, rows, message):
    with pytest.raises(ValueError, match=message):
        write_views(tmp_path / "test_views.csv", rows)
    assert not (tmp_path / "test_views.csv").exists()
