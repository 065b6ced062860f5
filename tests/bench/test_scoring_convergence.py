"""`bench.scoring_convergence`: how the convergence of the `edit` stage's scoring is judged (every row's
paired PSNR change at 4x its samples per pixel), and the refusals of the scoring's sample counts and layer."""

import pytest

from pipeline.bench import scoring_convergence as sc
from tests.conftest import compose_cfg


def _records(values: dict[int, float], views: int = 4) -> list[dict]:
    return [
        {"view": f"v{i}", "class": "insert/mirror", "psnr": {n: {"lightnet": v + 0.01 * i} for n, v in values.items()}}
        for i in range(views)
    ]


def test_converged_scale_is_the_first_whose_change_at_4x_is_within_tolerance():
    out = sc.summarise(_records({4: 10.0, 16: 11.0, 64: 11.05, 256: 11.06}), [4, 16, 64, 256], ("lightnet",), 0.1)
    assert out["converged_scale"] == {"lightnet": 16}  # 4 -> 16 moves 1 dB; 16 -> 64 moves 0.05
    change = out["classes"]["insert/mirror"]["rows"]["lightnet"]["change_at_4x"]
    assert change["4"]["diff"] == pytest.approx(1.0) and change["16"]["diff"] == pytest.approx(0.05)
    assert sc.summarise(_records({4: 10.0, 16: 11.0}), [4, 16], ("lightnet",), 0.1)["converged_scale"] == {
        "lightnet": None
    }


def test_bad_sample_counts_and_layers_are_refused():
    from pipeline.systems.insertion_scoring import row_spp, scoring_layer

    with pytest.raises(ValueError, match="increasing positive"):
        sc.run([], [4, 1], 0.1, None, progress=False)
    with pytest.raises(ValueError, match="scoring.spp=0"):
        scoring_layer(compose_cfg("edit", ["scoring.spp=0"]))
    with pytest.raises(ValueError, match="scoring.row_spp.oracle=0"):
        row_spp(compose_cfg("edit", ["scoring.row_spp.oracle=0"]), "oracle")
    with pytest.raises(ValueError, match="unknown rows \\['lightnett'\\]"):
        row_spp(compose_cfg("edit", ["+scoring.row_spp.lightnett=64"]), "lightnet")
    with pytest.raises(ValueError, match="scoring.layer='exact'"):
        scoring_layer(compose_cfg("edit", ["scoring.layer=exact"]))
    with pytest.raises(ValueError, match="render.estimator='uniform' is scored with scoring.layer=render"):
        scoring_layer(compose_cfg("edit", ["render=uniform"]))
    cfg = compose_cfg("edit", [])
    assert row_spp(cfg, "lightnet") == cfg.scoring.spp and row_spp(cfg, "oracle") == cfg.scoring.row_spp.oracle


def test_plot_draws_each_class_against_spp(tmp_path):
    scales = [4, 16, 64]
    summary = sc.summarise(_records({4: 10.0, 16: 11.0, 64: 11.05}), scales, ("lightnet",), 0.1)
    report = {"scales": scales, "row_spp": {"lightnet": 256}, **summary}
    sc.plot(report, tmp_path / "c.png")
    assert (tmp_path / "c.png").stat().st_size > 1000


def test_headline_reads_each_rows_change_at_4x_its_configured_samples():
    summary = sc.summarise(_records({1: 20.0, 4: 20.05}), [1, 4], ("lightnet",), 0.1)
    (row,) = sc.headline(summary, {"lightnet": 256}, 0.1)
    assert row["row"] == "lightnet" and row["spp"] == 256 and row["converged"] == "yes"
    assert row["change at 4x, all cases (dB)"] == pytest.approx(0.05)
    moved = sc.summarise(_records({1: 20.0, 4: 20.3}), [1, 4], ("lightnet",), 0.1)
    assert sc.headline(moved, {"lightnet": 256}, 0.1)[0]["converged"] == "no"
