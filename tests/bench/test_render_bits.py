"""`bench.render_bits`: one micro room rendered as `synthesize` renders it, and two runs compared value by
value in float32 units in the last place."""

import numpy as np
import pytest

from pipeline.bench import render_bits


def test_ulp_distance_counts_adjacent_floats_across_zero():
    x = np.array([1.0, -1.0, 0.0, 3.5], np.float32)
    up = np.nextafter(x, np.float32(np.inf))
    assert render_bits.ulp_distance(x, up).tolist() == [1, 1, 1, 1]
    two = np.nextafter(up, np.float32(np.inf))
    assert render_bits.ulp_distance(x, two).tolist() == [2, 2, 2, 2]
    tiny = np.nextafter(np.float32(0), np.float32(1))  # the smallest positive float and its negative
    assert render_bits.ulp_distance(np.array([-tiny]), np.array([tiny])).tolist() == [2]
    assert render_bits.ulp_distance(np.array([-0.0], np.float32), np.array([0.0], np.float32)).tolist() == [0]


def test_compare_arrays_finds_every_difference_and_nothing_else():
    rng = np.random.default_rng(0)
    a = {"im": rng.random((4, 5, 3), dtype=np.float32), "depth": rng.random((4, 5), dtype=np.float32)}
    same = render_bits.compare_arrays(a, {k: v.copy() for k, v in a.items()})
    assert same["identical"] and same["summary"]["values differing (%)"] == 0
    b = {k: v.copy() for k, v in a.items()}
    b["im"][1, 2, 0] = np.nextafter(b["im"][1, 2, 0], np.float32(2))
    b["im"][3, 4, 2] = np.nextafter(np.nextafter(b["im"][3, 4, 2], np.float32(2)), np.float32(2))
    b["extra"] = np.zeros(3, np.float32)
    out = render_bits.compare_arrays(a, b)
    im = out["arrays"]["im"]
    assert not out["identical"] and im["differing_fraction"] == pytest.approx(2 / 60)
    assert (im["median_ulp"], im["max_ulp"]) == (1.5, 2)
    assert out["arrays"]["depth"]["differing_fraction"] == 0 and "max_ulp" not in out["arrays"]["depth"]
    assert out["only_in_second"] == ["extra"] and out["only_in_first"] == []
    assert out["summary"]["values differing (%)"] == pytest.approx(100 * 2 / 80)
    b["depth"] = b["depth"][:3]
    assert render_bits.compare_arrays(a, b)["shape_mismatch"] == [{"array": "depth", "shapes": [[4, 5], [3, 5]]}]
    nan = {"x": np.array([np.nan, 1.0], np.float32)}
    assert render_bits.compare_arrays(nan, {"x": nan["x"].copy()})["identical"]  # NaN where both have NaN


def test_bad_arguments_are_refused(capsys):
    with pytest.raises(FileNotFoundError, match="render_bits_no-such-run.json"):
        render_bits.load_run("no-such-run")
    for spec in ("haswell", "haswell:3", ":8", "haswell:x"):
        with pytest.raises(ValueError, match="--llvm-target"):
            render_bits.set_llvm_target(spec)
    with pytest.raises(SystemExit):
        render_bits.main([])  # neither --name nor --compare
    with pytest.raises(SystemExit):
        render_bits.main(["--name", "a/b"])
    assert "letters, digits" in capsys.readouterr().err


def test_one_micro_room_renders_under_an_overridden_llvm_target(tmp_path):
    cheap = [
        "synth.denoise=false",
        "synth.spp=2",
        "synth.cases.spp=4",
        "synth.cases.edit_spp=2",
        "synth.lighting.spp=4",
    ]
    report, arrays = render_bits.render("micro", target="haswell:4", overrides=cheap)
    assert report["variant"] == "llvm_ad_rgb"  # the suite's machines run the llvm variant (libLLVM 19)
    assert report["llvm_target"]["cpu"] == "haswell" and report["llvm_target"]["vector_width"] == 4
    assert not report["denoise"] and report["host"]["model"]
    views = sorted(k for k in report["files"] if k.endswith("_im.exr"))
    assert views == ["scene_0001/000_im.exr", "scene_0001/001_im.exr"]
    im = arrays["scene_0001/000_im.exr"]
    assert im.shape == (48, 64, 3) and np.isfinite(im).all() and im.mean() > 0
    assert any(k.endswith("_cases.npz:object0_radiance") for k in arrays)  # the cases are rendered too
    assert report["summary"]["arrays"] == len(arrays)
    render_bits.plot({"runs": {"a": {}, "b": {}}, **render_bits.compare_arrays(arrays, arrays)}, tmp_path / "r.png")
    assert (tmp_path / "r.png").stat().st_size > 5_000


def test_compare_counts_a_file_only_one_run_wrote(tmp_path, monkeypatch):
    import json

    monkeypatch.setattr(render_bits, "bench_dir", lambda: tmp_path)
    arrays = {"scene_0001/000_im.exr": np.ones((2, 2, 3), np.float32)}
    for name, files in (("a", {"x.exr": "1"}), ("b", {"x.exr": "1", "y.npz": "2"})):
        (tmp_path / f"render_bits_{name}.json").write_text(json.dumps({"files": files}))
        np.savez(tmp_path / f"render_bits_{name}.npz", **arrays)
    for first, second in (("a", "b"), ("b", "a")):
        report = render_bits.compare(first, second)
        assert report["files_differing"] == ["y.npz"] and report["summary"]["files"] == 2
