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


BENCH_FILES = {"iiw": "iiw", "nyu": "nyuv2", "synthetic": "synthetic_views"}  # metrics prefix -> CSV name


def test_evaluate_publishes_every_interval_the_results_page_prints(evaluated):
    """The page computes no interval: each mean's, the fine-tuned minus trained differences paired by image
    and LightNet minus every other predictor paired by view are the stage's, and agree with its CSVs."""
    tmp, _, ev = evaluated
    report = tmp / "reports" / "evaluate"

    def within(key: str, images: int) -> bool:  # an interval from two images on; none from one (no spread)
        if images < 2:
            return f"{key}_lo" not in ev and f"{key}_hi" not in ev
        return ev[f"{key}_lo"] <= ev[key] <= ev[f"{key}_hi"]

    images = {b: (report / f"trained_{f}.csv").read_text().count("\n") - 1 for b, f in BENCH_FILES.items()}
    assert max(images.values()) >= 2  # the micro data hold an interval to check
    for model in ("trained", "finetuned"):
        for key in ("iiw/whdr_gamma", "nyu/normal_deg", "synthetic/albedo_mse"):
            assert within(f"{model}/{key}", images[key.split("/")[0]])
    for bench in ("nyu", "iiw"):
        before, after = (_csv_means(report / f"{m}_{BENCH_FILES[bench]}.csv") for m in ("trained", "finetuned"))
        for metric in before:
            key = f"finetuned_minus_trained/{bench}/{metric}"
            assert ev[key] == pytest.approx(after[metric] - before[metric], abs=1e-9)
            assert ev[f"{key}_n"] == images[bench] and within(key, images[bench])
    for entry in ("synthetic", "synthetic_ood"):
        means = _csv_means(report / f"lightnet_{entry}_views.csv", nan_ok=True)
        others = {k.split("/")[0] for k in means if k.endswith("/surf_light_nmse") and not k.startswith("model/")}
        assert {"constant", "scaled_constant", "probe_mean_oracle"} <= others
        for who in others:
            key = f"lightnet/{entry}/minus_{who}/surf_light_nmse"
            assert ev[key] == pytest.approx(means["model/surf_light_nmse"] - means[f"{who}/surf_light_nmse"], abs=1e-6)
            assert ev[f"{key}_lo"] <= ev[key] <= ev[f"{key}_hi"] and ev[f"{key}_n"] >= 2


def test_paired_intervals_pair_by_image_or_not_at_all():
    from pipeline.runs.evaluate import mean_intervals, paired_intervals

    before = [{"index": i, "err": float(i), "miss": float("nan") if i == 0 else 1.0} for i in range(6)]
    after = [{**r, "err": r["err"] - 2.0} for r in before]
    d = paired_intervals(before, after, 100, 0)
    assert d["err"] == pytest.approx(-2.0) and d["err_lo"] == pytest.approx(-2.0) and d["err_n"] == 6
    assert d["miss_n"] == 5  # a non-finite image is left out of that column only
    assert paired_intervals(before, after[::-1], 100, 0) == {}  # other images in another order: no pairing
    m = mean_intervals(before, 100, 0)
    assert m["err_lo"] < 2.5 < m["err_hi"] and "index_lo" not in m


def _csv_means(path, nan_ok: bool = False) -> dict[str, float]:
    """Mean of every score column of a per-image CSV (all finite unless `nan_ok`: the caller checks
    `nonfinite`); with `nan_ok`, over the finite values."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    keys = [k for k in rows[0] if k not in ("id", "index")]
    if not nan_ok:
        return {k: statistics.fmean(float(r[k]) for r in rows) for k in keys}
    return {k: float(np.nanmean([float(r[k]) for r in rows])) for k in keys}


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
