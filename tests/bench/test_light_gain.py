"""The light-gain diagnostic: its premise (a render is linear in the light, same directions), its summary,
its refusals, and a run on the micro data whose gain-1 scores are the `edit` stage's own."""

import csv
import json

import numpy as np
import pytest
import torch

from pipeline.bench import light_gain as lg
from tests.conftest import compose_cfg


def _gbuffer(H: int = 6, W: int = 8) -> dict:
    g = torch.Generator().manual_seed(0)
    normal = torch.zeros(1, 3, H, W)
    normal[:, 2] = 1.0  # facing the camera
    material = torch.stack([torch.full((H, W), 0.3), (torch.rand(H, W, generator=g) > 0.5).float()])[None]
    return {
        "albedo": torch.rand(1, 3, H, W, generator=g),
        "normal": normal,
        "depth": torch.full((1, H, W), 2.0),
        "material": material,
    }


def test_a_render_is_linear_in_the_light():
    """The bench scores g * render(L) for render(g L): exact when both draw the same directions."""
    from pipeline.models.insertion import render_case
    from pipeline.models.render_layer import MCRenderLayer

    gb, pixels = _gbuffer(), torch.arange(0, 48, 3)

    def light(idx, origin, wi, image):
        return (1.0 + wi[:, 1:2] + 4.0 * (wi[:, 0:1] > 0.7)).expand(-1, 3) * torch.tensor([1.0, 0.8, 0.5])

    def brighter(idx, origin, wi, image):
        return 2.5 * light(idx, origin, wi, image)

    layer = MCRenderLayer(spp=8)
    a = render_case(layer, gb, 60.0, pixels, light, seed=3)
    b = render_case(layer, gb, 60.0, pixels, brighter, seed=3)
    assert torch.allclose(2.5 * a, b, rtol=1e-5, atol=1e-7)
    assert (a > 0).all()


def test_gain_psnr_is_the_edit_stage_psnr_of_the_scaled_render():
    from pipeline.metrics.insertion import case_scores

    g = torch.Generator().manual_seed(1)
    target = torch.rand(40, 3, generator=g) * 3
    photo, pixels = torch.rand(16, 16, 3, generator=g), torch.arange(10, 50)
    gains = (0.5, 1.0, 2.0, 4.0)
    curve = lg.case_gain_psnr(target / 2, target, 0.7, gains)
    # a render at half the truth is exact at gain 2, and worse the further the gain is from 2
    assert curve[2] == pytest.approx(120.0) and curve[0] < curve[1] < curve[2] > curve[3]
    for gain, value in zip(gains, curve, strict=True):
        assert value == pytest.approx(case_scores(target / 2 * gain, target, photo, pixels, 0.7)["psnr"], abs=1e-9)


def test_gains_are_checked_and_include_one():
    assert lg.check_gains([2, 0.5]) == (0.5, 1.0, 2.0)
    for bad in ([0.0], [-1.0], [float("nan")], [float("inf")], []):
        with pytest.raises(ValueError, match="--gains"):
            lg.check_gains(bad)


def test_summary_finds_each_class_best_gain():
    gains = (0.5, 1.0, 2.0)
    records = []
    for i, (label, peak) in enumerate((("mirror", 0), ("diffuse", 2), ("diffuse", 2), ("glossy", 1))):
        curve = [10.0 - abs(k - peak) for k in range(3)]
        records.append({"view": f"v{i}", "label": label, "lightnet@gains": curve, "scaled_constant@gains": [5, 6, 7]})
    s = lg.summarise(records, gains)
    assert s["mirror"]["rows"]["lightnet"]["best_gain"] == 0.5
    assert s["diffuse"]["rows"]["lightnet"]["best_gain"] == 2.0
    assert s["diffuse"]["cases"] == 2 and s["diffuse"]["views"] == 2
    assert s["glossy"]["rows"]["lightnet"]["psnr_at_1"] == 10.0
    assert s["all"]["rows"]["scaled_constant"]["best_gain"] == 2.0
    assert s["all"]["rows"]["lightnet"]["psnr"] == pytest.approx([8.75, 9.25, 9.25])
    assert s["all"]["rows"]["lightnet"]["best_gain"] == 1.0  # the first of equal maxima
    rows = {r["class"]: r for r in lg.headline(s)}
    assert rows["diffuse"]["best gain"] == 2.0 and rows["diffuse"]["LightNet at best gain (dB)"] == 10.0
    assert rows["all"]["scaled constant (dB)"] == 6.0 and rows["mirror"]["LightNet at gain 1 (dB)"] == 9.0


@pytest.mark.slow
def test_bench_on_micro_matches_the_edit_stage(micro_root, micro_shards, micro_exports, tmp_path):
    from pipeline.systems.insertion_scoring import score_rows

    common = [
        "profile=micro",
        f"data_root={micro_root}",
        f"data_dir={micro_shards}",
        f"material_path={micro_exports / 'material.pt'}",
        f"light_path={micro_exports / 'light.pt'}",
    ]
    out = tmp_path / "gain.json"
    lg.main(
        [
            "--model", str(micro_exports / "light.pt"),
            "--material", str(micro_exports / "material.pt"),
            "--gains", "0.5", "2",
            "--out", str(out),
            "--override", *common[:3],
        ]
    )  # fmt: skip
    report = json.loads(out.read_text())
    assert report["gains"] == [0.5, 1.0, 2.0] and out.with_suffix(".png").is_file()
    with open(tmp_path / "gain_cases.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert rows and all(r["kind"] == "object" for r in rows)
    assert report["classes"]["all"]["cases"] == len(rows)
    # the CSV is what compare_runs pairs: itself against itself is no difference anywhere
    from pipeline.bench.compare_runs import compare_cases

    same = compare_cases(tmp_path / "gain_cases.csv", tmp_path / "gain_cases.csv")
    assert same["object/all"]["diff"] == 0.0
    # at gain 1 each case scores what the edit stage's lightnet row scores (same seeds and directions)
    _, records = score_rows(compose_cfg("edit", [*common, "bootstrap=10"]), ("lightnet",))
    stage = [r["lightnet/psnr"] for r in records if r["kind"] == "object"]
    assert np.allclose([float(r["lightnet/psnr"]) for r in rows], stage, rtol=0, atol=1e-9)
    # the results page shows the headline rows, one per class
    from pipeline.tracking.results_page import bench_block

    (rows_summary,) = report["summary"].values()
    assert [r["class"] for r in rows_summary] == list(report["classes"])
    assert any("| best gain |" in line for line in bench_block("light_gain", report, "tiny"))
    curve = report["classes"]["all"]["rows"]["lightnet"]["psnr"]
    assert curve[1] == pytest.approx(np.mean(stage))
