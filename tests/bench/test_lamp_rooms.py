"""bench.lamp_rooms: the extra rooms' photos are the stage's own, their targets read the room as the
stage's views are read, and the cache resumes, refuses other settings and names a broken file."""

import json

import numpy as np
import pytest
import torch

from pipeline.bench import lamp_placement as lp
from pipeline.bench import lamp_rooms as lr
from pipeline.bench.roombox_floor import true_box
from pipeline.bench.visible_light import room_lamps
from pipeline.data.formats.exr import read_exr
from pipeline.data.synth import mitsuba_backend as mb


def test_a_room_is_rendered_as_the_stage_renders_it(micro_root):
    """Room 0 of the stage's seed comes out as `synthesize` wrote it: the same camera, the same photo
    (to float16), the same box and lamps."""
    cfg, _ = lr.synth_config("micro")
    (record,) = lr.render_photos([0], 0, cfg, mb.choose_variant("auto"), 1, 16)
    scene = micro_root / "scene_0000"
    camera = json.loads((scene / "cameras.json").read_text())["000"]
    assert np.array_equal(np.array(record["world_from_view"]), np.array(camera["world_from_view"]))
    photo = torch.from_numpy(np.asarray(read_exr(scene / "000_im.exr"), np.float32)).permute(2, 0, 1)
    expected = lp.photo_input(photo, 16)
    assert record["x"].dtype == torch.float16 and record["x"].shape == expected.shape
    assert float((record["x"].float() - expected).abs().max()) < 4e-3  # float16 rounding of values up to ~3
    x, cells = lp.room_targets([record], 4)
    stage_cells = lp.ceiling_lamps(room_lamps(micro_root, "scene_0000/000"), true_box(micro_root, "scene_0000/000"), 4)
    assert torch.allclose(cells[0], stage_cells) and float(stage_cells.sum()) > 0
    assert torch.equal(x[0], record["x"].float())


def test_the_cache_resumes_and_refuses_other_settings(tmp_path, monkeypatch):
    monkeypatch.setattr(lr, "CHUNK", 2)
    cache = tmp_path / "rooms"
    rooms = lr.extra_rooms(cache, 3, seed=0, profile="micro", height=8, workers=1)
    assert [r["index"] for r in rooms] == [0, 1, 2]
    assert sorted(p.name for p in cache.glob("chunk_*.pt")) == ["chunk_00000.pt", "chunk_00002.pt"]
    assert json.loads((cache / "meta.json").read_text())["seed"] == lr.SEED_OFFSET

    def no_rendering(*args, **kwargs):
        raise AssertionError("rendered again")

    monkeypatch.setattr(lr, "ProcessPoolExecutor", no_rendering)
    again = lr.extra_rooms(cache, 4, seed=0, profile="micro", height=8, workers=1)  # chunks hold 4 rooms
    assert [r["index"] for r in again] == [0, 1, 2, 3]
    assert all(torch.equal(a["x"], b["x"]) for a, b in zip(rooms, again[:3], strict=True))
    with pytest.raises(ValueError, match="height=8.*16"):
        lr.extra_rooms(cache, 2, seed=0, profile="micro", height=16)
    with pytest.raises(ValueError, match="seed"):
        lr.extra_rooms(cache, 2, seed=1, profile="micro", height=8)
    (cache / "chunk_00002.pt").write_bytes(b"truncated")
    with pytest.raises(ValueError, match="chunk_00002.pt"):
        lr.extra_rooms(cache, 4, seed=0, profile="micro", height=8)
    with pytest.raises(ValueError, match="--curve: -1 extra rooms"):
        lr.extra_rooms(cache, -1)
    assert lr.extra_rooms(tmp_path / "unused", 0) == [] and not (tmp_path / "unused").exists()


def test_the_placement_learns_with_extra_rooms(micro_shards, tmp_path, monkeypatch):
    """A learning curve on the micro data: one network per number of extra rooms, each paired with the
    same seed's network trained without them."""
    monkeypatch.setattr(lr, "CHUNK", 2)
    report = lp.run(
        str(micro_shards),
        grid=2,
        height=8,
        epochs=2,
        seeds=1,
        curve=(0, 2),
        extra_dir=tmp_path / "rooms",
        profile="micro",
    )
    assert report["training_rooms"]["from the photo, +2 rooms, seed 0"] == report["train_views"] + 2
    assert report["training_rooms"]["from the photo, seed 0"] == report["train_views"]
    assert set(report["differences_with_more_rooms"]) == {
        "surf: from the photo, +2 rooms, seed 0 - from the photo, seed 0",
        "free: from the photo, +2 rooms, seed 0 - from the photo, seed 0",
    }
    nmse = {row["placement"]: row["surface nMSE"] for row in report["summary"]["each placement"]}
    d = report["differences_with_more_rooms"]["surf: from the photo, +2 rooms, seed 0 - from the photo, seed 0"]
    assert d["diff"] == pytest.approx(
        nmse["from the photo, +2 rooms, seed 0"] - nmse["from the photo, seed 0"], rel=1e-6, abs=1e-9
    )
    rows = lp.curve_rows(report)
    assert [r["rooms"] for r in rows] == [report["train_views"], report["train_views"] + 2]
    lp.plot(report, tmp_path / "curve.png")
    assert (tmp_path / "curve.png").stat().st_size > 5_000
    with pytest.raises(ValueError, match="--curve"):
        lp.run(str(micro_shards), grid=2, height=8, epochs=1, seeds=1, curve=(-1,))
