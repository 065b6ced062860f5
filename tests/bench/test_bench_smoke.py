"""The benchmark harnesses run end to end on tiny inputs and their summaries are computed from the rows."""

import pytest

from pipeline.bench import render_layer, ssrt


def test_render_layer_bench_runs_small():
    report = render_layer.run(quick=True, repeats=1, ref_spp=64, size=(12, 16))
    names = {r["estimator"] for r in report["results"]}
    assert names == {"importance", "uniform", "adaptive", "adaptive_uniform", "li2020"}
    imp = {r["samples_per_pixel"]: r for r in report["results"] if r["estimator"] == "importance"}
    assert imp[16]["relmse_glossy"] < imp[1]["relmse_glossy"]  # error falls with samples (~1/N)
    ratios = report["summary"]["li2020_over_importance_glossy_error_at_equal_time"]
    assert len(ratios) == 2 and all(r["ratio"] > 0 for r in ratios)


def test_equal_time_ratio_interpolates_in_log_log():
    rows = [
        {"estimator": "importance", "seconds": 0.1, "relmse_glossy": 1.0},
        {"estimator": "importance", "seconds": 10.0, "relmse_glossy": 0.01},
        {"estimator": "li2020", "seconds": 1.0, "relmse_glossy": 0.5, "li_size": [8, 16]},
    ]
    (r,) = render_layer.equal_time_ratio(rows, "glossy")
    assert r["importance_error_at_equal_time"] == pytest.approx(0.1) and r["ratio"] == pytest.approx(5.0)


def test_ssrt_bench_runs_small():
    report = ssrt.run(resolutions=((24, 32),), levels=(0, None), rays_per_pixel=2, repeats=1, compiled=(False,))
    assert len(report["results"]) == 2 and all(r["rays_per_second"] > 0 for r in report["results"])
    assert report["results"][0]["recall"] == report["results"][1]["recall"]


def test_light_net_bench_runs_small(tmp_path):
    from pipeline.bench import light_net

    report = light_net.run(resolutions=((24, 32),), repeats=1, model_path=str(tmp_path / "none.pt"), hyper_points=512)
    assert {r["mode"] for r in report["speed"]} == {"mixed", "ssrt_only", "out_of_view_only"}
    assert len(report["speed"]) == 3 and {(r["height"], r["width"]) for r in report["speed"]} == {(24, 32)}
    assert report["thresholds"] == [] and "not found" in report["thresholds_note"]


@pytest.mark.slow
def test_material_net_bench_runs_small(micro_shards, tmp_path):
    from pipeline.bench import material_net

    report = material_net.run(
        backbones=("small",), resolutions=((24, 32),), repeats=1, train_seconds=2.0, data_dir=str(micro_shards)
    )
    (row,) = report["results"]
    assert row["parameters"] > 0 and row["speed"][0]["images_per_second"] > 0
    assert row["accuracy"]["steps"] >= 1 and row["accuracy"]["normal_angle_deg"] > 0
    material_net.plot(report, tmp_path / "m.png")
    assert (tmp_path / "m.png").stat().st_size > 5_000
