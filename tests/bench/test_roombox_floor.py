"""bench.roombox_floor on the micro dataset: the free-texture fit lowers its loss, the summary is computed
from the rows, the figure is written; a dataset whose room files are gone is refused naming the file."""

import math

import pytest

from pipeline.bench import roombox_floor


def test_floor_bench_fits_and_summarises(micro_shards, tmp_path):
    report = roombox_floor.run(str(micro_shards), views=(0,), texture_size=8, steps=40, lr=0.05, layout_views=2)
    view = report["views"][0]
    for layout in roombox_floor.LAYOUTS:
        curve = view[layout]["curve"]
        assert curve[-1]["loss"] < curve[0]["loss"]  # the fit moves the textures towards the probes
        assert view[layout]["surf"]["nmse"] >= 0 and math.isfinite(view[layout]["surf"]["nmse"])
    s = report["summary"]
    assert s["gt_box_miss_nmse_median"] == view["gt"]["miss_nmse"]
    assert s["views"][0]["predicted box: miss nMSE"] == view["predicted"]["miss_nmse"]
    assert s["layout_views"] == 2 and s["rotation_error_deg_median"] >= 0
    roombox_floor.plot(report, tmp_path / "floor.png")
    assert (tmp_path / "floor.png").stat().st_size > 0


def test_floor_bench_needs_the_room_files(micro_shards_without_rooms):
    with pytest.raises(FileNotFoundError, match="manifest.json: source_root"):
        roombox_floor.run(str(micro_shards_without_rooms), views=(0,), steps=1, layout_views=1)
