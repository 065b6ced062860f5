"""Stages `finetune` and `evaluate` end to end on the micro profile with stand-ins."""

import csv
import json
import statistics

import mlflow
import numpy as np
import pytest

from tests.conftest import compose_cfg

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("finetune_and_evaluate")]  # one worker runs the module fixture


@pytest.fixture(scope="module")
def evaluated(micro_shards, micro_ood_shards, micro_exports, tmp_path_factory):
    from stages import evaluate, finetune, train_material

    tmp = tmp_path_factory.mktemp("bench_stages")
    common = [
        "profile=micro",
        f"paths.outputs={tmp}/outputs",
        f"paths.reports={tmp}/reports",
        f"data_dir={micro_shards}",
        "progress=false",
    ]
    train_material.run(compose_cfg("train_material", [*common, "system_metrics=false"]))
    ft = finetune.run(compose_cfg("finetune", [*common, "trainer.max_epochs=1", "finetune.batch_size=2"]))
    ood = [f"ood_data_dir={micro_ood_shards}", f"light_path={micro_exports / 'light.pt'}", "bootstrap=200"]
    ev = evaluate.run(compose_cfg("evaluate", [*common, *ood]))
    return tmp, ft, ev


def test_finetune_builds_standins_and_exports_a_model(evaluated):
    tmp, ft, _ = evaluated
    out = tmp / "outputs" / "finetune"
    assert (out / "model.pt").is_file() and (out / "standins" / "iiw" / "SOURCE.txt").is_file()
    assert ft["global_step"] >= 1 and np.isfinite(ft["loss_iiw_ranking"]) and np.isfinite(ft["loss_nyu_depth"])
    sources = json.loads((tmp / "reports" / "finetune" / "sources.json").read_text())
    assert sources == {"iiw": "standin-iiw", "nyuv2": "standin-nyuv2", "synthetic": "synthetic"}


def test_evaluate_reports_both_models_with_their_sources(evaluated):
    tmp, _, ev = evaluated
    report = tmp / "reports" / "evaluate"
    for model in ("trained", "finetuned"):
        for key in ("iiw/whdr_gamma", "nyu/normal_deg", "nyu/depth_si", "synthetic/albedo_mse"):
            assert np.isfinite(ev[f"{model}/{key}"])
        for bench in ("iiw", "nyu", "synthetic"):  # every per-image score counted: none is non-finite here
            assert ev[f"{model}/{bench}/nonfinite"] == 0
        for bench in ("iiw", "nyuv2"):
            assert (report / f"{model}_{bench}.csv").read_text().count("\n") >= 2
        # the synthetic test split scored once per model: its one per-view CSV holds the means reported
        assert not (report / f"{model}_synthetic.csv").exists()
        synthetic = _csv_means(report / f"{model}_synthetic_views.csv")
        for metric in ("albedo_mse", "normal_angle_deg", "depth_log_mse"):
            assert ev[f"{model}/synthetic/{metric}"] == pytest.approx(synthetic[f"model/{metric}"], rel=1e-9)
        assert (report / f"{model}_nyuv2_cases.png").stat().st_size > 5_000
    for model in ("trained", "finetuned", "lightnet"):  # in and out of distribution, by the same code
        for entry in ("synthetic", "synthetic_ood"):
            rows = (report / f"{model}_{entry}_views.csv").read_text().splitlines()
            assert len(rows) >= 3 and rows[0].startswith("id,")
    for entry in ("synthetic", "synthetic_ood"):
        for model in ("trained", "finetuned"):
            for gate in ("mean_material/metallic_mse", "mean_material/roughness_mse", "mean_albedo/albedo_mse"):
                lo, ratio, hi = (ev[f"{model}/{entry}/gate/{gate}{s}"] for s in ("_lo", "", "_hi"))
                assert 0 < lo <= hi and ratio > 0
        psnr = ev[f"lightnet/{entry}/render_psnr"] - ev[f"lightnet/{entry}/scaled_constant/render_psnr"]
        assert ev[f"lightnet/{entry}/minus_scaled_constant/render_psnr"] == pytest.approx(psnr, abs=1e-6)
        assert np.isfinite(ev[f"lightnet/{entry}/surf_light_nmse"])
    table = (report / "table.md").read_text()
    assert "standin-nyuv2" in table and "not comparable" in table and "published" in table
    for model in ("trained", "finetuned"):  # each row: the means of the per-image scores the stage wrote
        nyu, iiw = (_csv_means(report / f"{model}_{bench}.csv") for bench in ("nyuv2", "iiw"))
        row = f"| ours: {model} | {nyu['normal_deg']:.2f}° | {nyu['depth_si']:.3f} | {iiw['whdr_gamma']:.1f} |"
        assert row in table, (row, table)
    assert "| Zhu et al. 2022 (paper) | 21.86° | 0.155 | 15.5 | published (NYUv2 / IIW) |" in table
    runs = mlflow.search_runs(experiment_names=["invrender"], filter_string="tags.stage = 'evaluate'")
    assert (runs["tags.data_source"] == "standin-iiw+standin-nyuv2+synthetic").any()


def _csv_means(path) -> dict[str, float]:
    """Mean of every score column of a per-image CSV (all finite here: the caller checks `nonfinite`)."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    return {k: statistics.fmean(float(r[k]) for r in rows) for k in rows[0] if k not in ("id", "index")}


def test_whdr_command_line(evaluated, capsys):
    from PIL import Image

    from pipeline.cli import main
    from pipeline.data import iiw

    tmp = evaluated[0]
    root = tmp / "outputs" / "finetune" / "standins" / "iiw"
    image_id = iiw.list_ids(root)[0]
    gray = root.parent / "gray.png"
    Image.fromarray(np.full((8, 8, 3), 128, np.uint8)).save(gray)
    assert main(["whdr", str(gray), str(root / f"{image_id}.json")]) == 0
    value = float(capsys.readouterr().out)
    # a flat reflectance says "equal" everywhere: it disagrees with exactly the usable "darker" judgements
    judgements = iiw.read_judgements(root, image_id)
    opaque = {p["id"] for p in judgements["intrinsic_points"] if p["opaque"]}
    usable = [
        c
        for c in judgements["intrinsic_comparisons"]
        if c["darker"] in ("1", "2", "E") and (c["darker_score"] or 0) > 0 and {c["point1"], c["point2"]} <= opaque
    ]
    darker = sum(c["darker_score"] for c in usable if c["darker"] != "E")
    assert value == pytest.approx(darker / sum(c["darker_score"] for c in usable), rel=1e-9)
    assert main(["whdr", str(gray), str(root / "missing.json")]) == 2
    assert "missing.json" in capsys.readouterr().err


def test_evaluate_refuses_standins_built_with_other_settings(evaluated, micro_shards):
    """evaluate reads finetune's stand-ins and never rebuilds them (they are finetune's DVC output)."""
    from stages import evaluate

    tmp = evaluated[0]
    done = tmp / "outputs" / "finetune" / "standins" / "done.json"
    before = done.read_text()
    common = ["profile=micro", f"paths.outputs={tmp}/outputs", f"paths.reports={tmp}/reports_other"]
    with pytest.raises(ValueError, match="points differ"):
        evaluate.run(compose_cfg("evaluate", [*common, f"data_dir={micro_shards}", "standin.points=41"]))
    assert done.read_text() == before


def test_finetune_out_is_byte_identical_on_a_rerun(evaluated, micro_shards, tmp_path):
    """finetune again from the same trained model and seed, in other folders and another MLflow run: every
    file of its DVC out (model.pt, the stand-ins) has the same bytes, so `dvc.lock` does not change; its
    checkpoint lies beside the out."""
    import hashlib

    from stages import finetune

    tmp = evaluated[0]
    common = ["profile=micro", f"paths.outputs={tmp_path}/outputs", f"paths.reports={tmp_path}/reports"]
    model = f"model_path={tmp}/outputs/train_material/model.pt"
    overrides = [f"data_dir={micro_shards}", "progress=false", "trainer.max_epochs=1", "finetune.batch_size=2", model]
    finetune.run(compose_cfg("finetune", [*common, *overrides]))

    def digest(root):
        return {
            str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in root.rglob("*") if p.is_file()
        }

    first, again = digest(tmp / "outputs" / "finetune"), digest(tmp_path / "outputs" / "finetune")
    # every file the re-run wrote is the first run's (whose folder other tests here add files to)
    assert again == {k: first.get(k) for k in again}
    assert {"model.pt", "standins/done.json", "standins/nyuv2/splits.mat"} <= set(again)
    assert (tmp_path / "outputs" / "checkpoints" / "finetune" / "last.ckpt").is_file()
