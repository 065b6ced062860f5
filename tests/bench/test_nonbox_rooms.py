"""`bench.nonbox_rooms` on the micro profile: the groups' rooms rendered with their shapes and cases, scored
by group, every later export paired with the first; bad options refused by name."""

import json
import math

import pytest


def test_nonbox_rooms_renders_scores_and_pairs_by_group(micro_shards, micro_exports, tmp_path):
    from pipeline.bench import nonbox_rooms

    light = str(micro_exports / "light.pt")
    report = nonbox_rooms.run(
        {"first": light, "again": light},
        groups=("box", "l_shaped", "sloped"),
        rooms=2,
        data_dir=str(micro_shards),
        material_path=str(micro_exports / "material.pt"),
        profile="micro",
        resamples=50,
        workers=1,
        keep=str(tmp_path / "kept"),
    )
    kept = tmp_path / "kept"
    scenes = (kept / "rooms" / "test.txt").read_text().split()
    assert scenes == [f"{g}_{i:04d}" for g in ("box", "l_shaped", "sloped") for i in range(2)]
    for i in range(2):  # the reshaped groups are the box group's rooms, reshaped
        box, el = (
            json.loads((kept / "rooms" / f"{g}_{i:04d}" / "scene.json").read_text()) for g in ("box", "l_shaped")
        )
        assert box["size"] == el["size"] and box["seed"] == el["seed"]
        assert sum(s["kind"] == "cube" and s["role"] == "wall" for s in el["shapes"]) == 1  # one corner block
        assert not any(s["kind"] == "cube" and s["role"] == "wall" for s in box["shapes"])
        sloped = json.loads((kept / "rooms" / f"sloped_{i:04d}/scene.json").read_text())  # after an L, same worker
        assert not any(s["kind"] == "cube" and s["role"] == "wall" for s in sloped["shapes"])
    assert report["rooms_rendered"]["sloped"]["rooms"] == 2 and len(report["rooms_rendered"]["sloped"]["tilt_deg"]) == 2
    manifest = json.loads((kept / "shards" / "manifest.json").read_text())
    assert set(manifest["splits"]) == {"train", "val", "test"} and len(manifest["splits"]["test"]["views"]) == 6
    assert (
        kept / "shards" / manifest["splits"]["train"]["shards"][0]["file"]
    ).resolve().parent == micro_shards.resolve()
    scored = report["groups_scored"]
    assert list(scored) == ["box", "l_shaped", "sloped"]
    for row in scored.values():
        assert row["first"]["views"] == row["again"]["views"] == 2  # one view a room
        assert all(math.isfinite(row["again"][k]) for k in nonbox_rooms.VIEW_METRICS)
        assert row["again"]["views_minus_first"]["render_psnr"]["diff"] == pytest.approx(0.0, abs=1e-9)
        if "all" in row["first"]["insertion"]:  # the same export on the same cases: no difference
            assert row["again"]["insertion"]["all"]["minus_reference"] == pytest.approx(0.0, abs=1e-9)
            assert row["again"]["insertion"]["all"]["psnr"] == row["first"]["insertion"]["all"]["psnr"]
            assert set(row["baselines"]["nearest_probe"]) >= {"all"}
    assert sum(row["first"]["cases"] for row in scored.values()) > 0
    each, paired = report["summary"].values()
    assert [(r["group"], r["light"]) for r in each[:4]] == [
        ("box", "first"),
        ("box", "again"),
        ("box", "nearest probe"),
        ("box", "scaled constant"),
    ]
    assert len(each) == 12 and all(p["diff"] == pytest.approx(0.0, abs=1e-9) for p in paired)
    sample = report["samples"]["l_shaped"][0]
    assert sample["id"] == "l_shaped_0000/000" and nonbox_rooms.png_image(sample["png"]).shape == (48, 64, 3)
    nonbox_rooms.plot(report, tmp_path / "n.png")
    assert (tmp_path / "n.png").stat().st_size > 10_000


def test_nonbox_rooms_refuses_bad_options(micro_exports, tmp_path):
    from pipeline.bench import nonbox_rooms

    light = {"a": str(micro_exports / "light.pt")}
    for kwargs, match in (
        ({"exports": {}}, "at least one --light-net"),
        ({"exports": light, "groups": ("box", "dome")}, "--groups box dome"),
        ({"exports": light, "rooms": 0}, "--rooms 0"),
    ):
        with pytest.raises(ValueError, match=match):
            nonbox_rooms.run(**kwargs)
    material = str(micro_exports / "material.pt")
    empty = tmp_path / "main"
    empty.mkdir()
    kept = tmp_path / "kept"
    (kept / "rooms").mkdir(parents=True)
    for kwargs, error, match in (  # refused before any room is rendered
        ({"exports": {"a": str(tmp_path / "x.pt")}}, FileNotFoundError, "--light-net a: .*x.pt not found"),
        ({"exports": light, "material_path": str(tmp_path / "m.pt")}, FileNotFoundError, "--material .*m.pt"),
        ({"exports": light, "data_dir": str(empty)}, FileNotFoundError, "--data-dir .*main: no manifest.json"),
    ):
        with pytest.raises(error, match=match):
            nonbox_rooms.run(**{"material_path": material, **kwargs})
    with pytest.raises(ValueError, match="--light-net 'a': give NAME=PATH"):
        nonbox_rooms.parse_light_nets(["a"])
    (empty / "manifest.json").write_text(json.dumps({"splits": {"test": {}}}))
    with pytest.raises(ValueError, match="has no train split"):
        nonbox_rooms.run(light, data_dir=str(empty), material_path=material)
    (empty / "manifest.json").write_text(json.dumps({"splits": {"train": {}, "val": {}}}))
    with pytest.raises(FileExistsError, match="--keep .*kept: already holds"):
        nonbox_rooms.run(light, data_dir=str(empty), material_path=material, keep=str(kept))
    assert not (kept / "shards").exists()
    for folder, splits in (("shards", {}), ("test_only", {"test": {}})):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "manifest.json").write_text(json.dumps({"splits": splits}))
    with pytest.raises(ValueError, match="has no train split"):
        nonbox_rooms.link_main_splits(tmp_path / "shards", tmp_path / "test_only")


def test_the_groups_draw_the_stage_rooms_or_the_ood_style_with_cases_and_one_view():
    from pipeline.bench import nonbox_rooms
    from pipeline.bench.common import compose

    configs = nonbox_rooms.group_configs("micro", ("box", "ood"), 3)
    stage = compose("synthesize", ["profile=micro"])
    for cfg in configs.values():
        assert cfg.scenes == 3 and cfg.views == 1 and cfg.cases.enabled
        assert cfg.splits == {"train": 0.0, "val": 0.0, "test": 1.0}
        assert (cfg.width, cfg.height, cfg.spp) == (stage.synth.width, stage.synth.height, stage.synth.spp)
    assert configs["box"].room.palette == stage.synth.get("room", {}).get("palette", "standard")
    assert configs["ood"].room.palette == stage.ood.synth.room.palette == "loft"
    assert configs["ood"].room.lamps == tuple(stage.ood.synth.room.lamps)
