"""`bench.scoring_convergence`: how the convergence of the `edit` stage's scoring is judged (every row's
paired PSNR change at 4x the samples per pixel), and its refusals."""

import pytest

from pipeline.bench import scoring_convergence as sc
from tests.conftest import compose_cfg


def _records(values: dict[int, float], views: int = 4) -> list[dict]:
    return [
        {"view": f"v{i}", "class": "insert/mirror", "psnr": {n: {"lightnet": v + 0.01 * i} for n, v in values.items()}}
        for i in range(views)
    ]


def test_converged_spp_is_the_first_count_whose_change_at_4x_is_within_tolerance():
    out = sc.summarise(_records({4: 10.0, 16: 11.0, 64: 11.05, 256: 11.06}), [4, 16, 64, 256], ("lightnet",), 0.1)
    assert out["converged_spp"] == {"lightnet": 16}  # 4 -> 16 moves 1 dB; 16 -> 64 moves 0.05
    change = out["classes"]["insert/mirror"]["rows"]["lightnet"]["change_at_4x"]
    assert change["4"]["diff"] == pytest.approx(1.0) and change["16"]["diff"] == pytest.approx(0.05)
    assert sc.summarise(_records({4: 10.0, 16: 11.0}), [4, 16], ("lightnet",), 0.1)["converged_spp"] == {
        "lightnet": None
    }


def test_bad_sample_counts_are_refused():
    with pytest.raises(ValueError, match="increasing positive"):
        sc.run([], [64, 16], 0.1, None, progress=False)
    with pytest.raises(ValueError, match="scoring.spp=0"):
        from pipeline.systems.insertion_scoring import scoring_layer

        scoring_layer(compose_cfg("edit", ["scoring.spp=0"]))


def test_plot_draws_each_class_against_spp(tmp_path):
    spps = [4, 16, 64]
    summary = sc.summarise(_records({4: 10.0, 16: 11.0, 64: 11.05}), spps, ("lightnet",), 0.1)
    report = {"spp": spps, "configured_spp": 16, **summary}
    sc.plot(report, tmp_path / "c.png")
    assert (tmp_path / "c.png").stat().st_size > 1000
