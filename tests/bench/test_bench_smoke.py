"""The benchmark harnesses run end to end on tiny inputs, keep what they measured apart from what they quote,
derive nothing from a quoted figure, and compute their summaries from their own rows."""

import math

import pytest
import torch

from pipeline.bench import render_layer, ssrt


def _numbers(tree):
    """Every number (not bool) in a JSON-like tree."""
    if isinstance(tree, dict):
        return [x for v in tree.values() for x in _numbers(v)]
    if isinstance(tree, list):
        return [x for v in tree for x in _numbers(v)]
    return [tree] if isinstance(tree, int | float) and not isinstance(tree, bool) else []


def _keys(tree):
    if isinstance(tree, dict):
        return [k for k, v in tree.items() for k in (k, *_keys(v))]
    if isinstance(tree, list):
        return [k for v in tree for k in _keys(v)]
    return []


def _check_split(report: dict, quoted: dict) -> None:
    """`measured` and `quoted` only; every quoted figure has a number, a unit and a source; none of them
    (nor its key) shows up under `measured`."""
    assert set(report) == {"measured", "quoted"}
    assert report["quoted"] == quoted and quoted
    for key, q in quoted.items():
        assert set(q) == {"value", "unit", "source"}
        assert isinstance(q["value"], int | float) and q["unit"] and len(q["source"]) > 40
        assert key not in _keys(report["measured"])
    measured = report["measured"]
    assert measured["device"] == "cpu" and measured["torch_threads"] == torch.get_num_threads()
    assert not {q["value"] for q in quoted.values()} & set(_numbers(measured))


def _sentinel_quotes(monkeypatch, module) -> dict:
    """Replace the module's quoted values by 1e-300: anything derived from them would be huge or infinite."""
    fake = {k: {**q, "value": 1e-300} for k, q in module.QUOTED.items()}
    monkeypatch.setattr(module, "QUOTED", fake)
    return fake


def test_render_layer_bench_runs_small(monkeypatch):
    fake = _sentinel_quotes(monkeypatch, render_layer)
    report = render_layer.run(quick=True, repeats=1, ref_rounds=32, size=(12, 16))
    _check_split(report, fake)
    m = report["measured"]
    assert all(math.isfinite(x) and abs(x) < 1e100 for x in _numbers(m))
    names = {r["estimator"] for r in m["results"]}
    assert names == {"importance", "uniform", "adaptive", "adaptive_uniform", "li2020"}
    assert m["glossy_pixels"] > 0 and m["rough_pixels"] > 0
    imp = {r["samples_per_pixel"]: r for r in m["results"] if r["estimator"] == "importance"}
    for group in ("glossy", "rough"):
        assert all(f"relmse_{group}" in r and f"floor_limited_{group}" in r for r in m["results"])
        assert m["reference_noise_floor_relmse"][group] > 0
        rows = m[f"equal_time_vs_importance_{group}"]
        assert {r["estimator"] for r in rows} == {"li2020", "uniform"}
        assert all(r["ratio"] is None or r["ratio"] > 0 for r in rows)
    assert imp[16]["relmse_rough"] < imp[1]["relmse_rough"]  # error falls with samples (~1/N)
    assert m["reference_samples_per_pixel"] == 4 * 32 and m["reference_seconds"] > 0
    assert "memory_with_gradients" not in m  # quick: no probe processes


def test_render_layer_plot_has_both_pixel_classes(tmp_path):
    report = render_layer.run(quick=True, repeats=1, ref_rounds=8, size=(12, 16))
    render_layer.plot(report, tmp_path / "r.png")
    assert (tmp_path / "r.png").stat().st_size > 5_000


def test_reference_agrees_with_importance_sampling_within_their_noise():
    """Two unbiased estimators of the same integral, with nothing in common but the integrand: at high
    sample counts they differ by their noise only (relMSE ~1.5e-4 here). A wrong pdf in the reference biases
    it beyond that: without the GGX pdf's 1/(4 wo.h) by a relMSE of ~0.4, with every pdf 5 % high by ~2e-3."""
    view = render_layer.bench_view(12, 16)
    ref, var = render_layer.reference_image(view, rounds=1024)
    every = torch.ones(12, 16, dtype=torch.bool)
    floor = render_layer.noise_floor(ref, var, every)
    layer = render_layer.MCRenderLayer("importance", spp=16384)
    a, b = (render_layer.render(view, layer, seed=s).double() for s in (1, 2))
    own = render_layer.rel_mse(a, b, every) / 2  # the variance of one importance frame, relative
    assert render_layer.rel_mse(a, ref, every) < 3 * (floor + own)
    assert torch.isfinite(ref).all() and (ref > 0).all()


def test_equal_time_ratio_interpolates_in_log_log():
    rows = [
        {"estimator": "importance", "seconds": 0.1, "relmse_glossy": 1.0},
        {"estimator": "importance", "seconds": 10.0, "relmse_glossy": 0.01, "floor_limited_glossy": True},
        {"estimator": "li2020", "seconds": 1.0, "relmse_glossy": 0.5, "li_size": [8, 16], "samples_per_pixel": 128},
        {"estimator": "li2020", "seconds": 20.0, "relmse_glossy": 0.5, "li_size": [8, 16], "samples_per_pixel": 128},
    ]
    inside, outside = render_layer.equal_time_ratio(rows, "glossy")
    assert inside["importance_error_at_equal_time"] == pytest.approx(0.1) and inside["ratio"] == pytest.approx(5.0)
    assert inside["floor_limited"]  # interpolated towards a floor-limited importance error
    assert outside["ratio"] is None and outside["importance_error_at_equal_time"] is None


def test_ssrt_bench_runs_small(monkeypatch):
    fake = _sentinel_quotes(monkeypatch, ssrt)
    report = ssrt.run(resolutions=((24, 32),), levels=(0, None), rays_per_pixel=2, repeats=1, compiled=(False,))
    _check_split(report, fake)
    m = report["measured"]
    assert all(abs(x) < 1e100 for x in _numbers(m) if math.isfinite(x))
    assert len(m["results"]) == 2 and all(r["rays_per_second"] > 0 for r in m["results"])
    assert m["results"][0]["recall"] == m["results"][1]["recall"]
    assert not any("speedup" in k for k in _keys(m))  # no reference timed: no speed-up


def test_ssrt_bench_times_a_reference_file(tmp_path):
    path = tmp_path / "pixel_march.py"
    path.write_text(
        "from pipeline.ops import ssrt\n\n\n"
        "def trace(depth, normal, fov_x, origin, direction):\n"
        "    return ssrt.trace(depth, normal, fov_x, origin, direction, max_level=0)\n"
    )
    report = ssrt.run(
        resolutions=((24, 32),),
        levels=(None,),
        rays_per_pixel=2,
        repeats=1,
        compiled=(False,),
        reference=path,
        reference_resolutions=((24, 32),),
    )
    m = report["measured"]
    (ref,) = m["reference_results"]
    (row,) = m["results"]
    assert ref["recall"] == row["recall"] and ref["precision"] == row["precision"]  # the same hits
    (speedup,) = m["speedup_vs_reference"]
    assert speedup["speedup"] == pytest.approx(row["rays_per_second"] / ref["rays_per_second"])
    ssrt.plot(report, tmp_path / "s.png")
    assert (tmp_path / "s.png").stat().st_size > 5_000


def test_ssrt_reference_file_without_trace_is_refused(tmp_path):
    path = tmp_path / "empty.py"
    path.write_text("x = 1\n")
    with pytest.raises(ValueError, match="defines no trace"):
        ssrt.load_reference(path)


def test_light_net_bench_runs_small(tmp_path):
    from pipeline.bench import light_net

    report = light_net.run(resolutions=((24, 32),), repeats=1, model_path=str(tmp_path / "none.pt"), hyper_points=512)
    assert {r["mode"] for r in report["speed"]} == {"mixed", "ssrt_only", "out_of_view_only"}
    assert len(report["speed"]) == 3 and {(r["height"], r["width"]) for r in report["speed"]} == {(24, 32)}
    assert report["thresholds"] == [] and "not found" in report["thresholds_note"]
    # it times the profile's LightNet, volume options included, not a copy of them
    tiny = light_net.profile_sizes("tiny")["out_of_view"]
    assert report["sizes"]["out_of_view"] == tiny and {"bounds", "samples"} <= set(tiny)


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
