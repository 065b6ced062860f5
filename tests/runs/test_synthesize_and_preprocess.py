"""End-to-end smoke of `synthesize` and `preprocess` on the micro profile: files, reports, MLflow runs."""

import json

import mlflow
import pytest

from tests.conftest import compose_cfg

pytestmark = pytest.mark.slow


def test_synthesize_stage_reports_and_tracks(micro_stage_paths):
    reports = micro_stage_paths["reports"] / "synthesize"
    metrics = json.loads((reports / "metrics.json").read_text())
    timings = json.loads((reports / "timings.json").read_text())
    assert {**metrics, **timings} == pytest.approx(micro_stage_paths["metrics"])
    assert "wall_seconds" in timings and not any("seconds" in k for k in metrics)  # dvc.lock holds no timing
    assert metrics["scenes"] == 3 and metrics["views"] == 6 and metrics["split_train_scenes"] == 1
    assert metrics["surface_probes"] > 0 and metrics["free_probes"] == 12
    assert (reports / "samples.png").stat().st_size > 10_000
    runs = mlflow.search_runs(
        experiment_names=["invrender"], filter_string="tags.stage = 'synthesize' and attributes.status = 'FINISHED'"
    )  # another worker's may be mid-run
    assert len(runs) >= 1
    row = runs.iloc[0]
    assert row["tags.profile"] == "micro" and row["tags.mitsuba_variant"] in ("llvm_ad_rgb", "scalar_rgb")
    assert row["params.synth.spp"] == "16" and row["metrics.views"] == 6


def test_preprocess_stage_reports_and_tracks(micro_stage_paths, tmp_path):
    from stages import preprocess

    cfg_args = [
        "profile=micro",
        f"paths.outputs={tmp_path}/outputs",
        f"paths.reports={tmp_path}/reports",
        "progress=false",
        f"data.interiorverse.generated_root={micro_stage_paths['outputs']}/synthesize",
        f"ood.root={micro_stage_paths['outputs']}/synthesize_ood",
    ]
    cfg = compose_cfg("preprocess", cfg_args)
    metrics = preprocess.run(cfg)
    assert metrics["views_kept"] == 6 and metrics["views_rejected"] == 0 and metrics["lighting_available"] == 1
    # the out-of-distribution set: its test split only (micro: 2 rooms, 2 views each)
    assert metrics["ood/test_views"] == 4 and metrics["ood/views_rejected"] == 0 and "ood/train_views" not in metrics
    ood = json.loads((tmp_path / "outputs" / "preprocess_ood" / "manifest.json").read_text())
    assert list(ood["splits"]) == ["test"] and ood["source"] == "synthetic_ood" and ood["lighting"]
    from pipeline.data import interiorverse as iv

    main_rooms = {
        n
        for split in ("train", "val", "test")
        for n in iv.read_split(micro_stage_paths["outputs"] / "synthesize", split, allow_empty=True)
    }
    ood_rooms = set(iv.read_split(micro_stage_paths["outputs"] / "synthesize_ood", "test"))
    assert ood_rooms and all(n.startswith("ood_") for n in ood_rooms) and not ood_rooms & main_rooms  # ids never shared
    with pytest.raises(FileNotFoundError, match="ood.root=null"):  # a missing set is named, never skipped
        preprocess.run(compose_cfg("preprocess", [*cfg_args[:-1], f"ood.root={tmp_path}/nowhere"]))
    rejected = json.loads((tmp_path / "reports" / "preprocess" / "rejected.json").read_text())
    assert rejected["source"] == "synthetic" and rejected["rejected"] == []
    manifest = json.loads((tmp_path / "outputs" / "preprocess" / "manifest.json").read_text())
    assert manifest["source"] == "synthetic" and manifest["height"] == 48
    runs = mlflow.search_runs(experiment_names=["invrender"], filter_string="tags.stage = 'preprocess'")
    assert (runs["tags.data_source"] == "synthetic").any() and (runs["metrics.views_kept"] == 6).any()


def _tree_digest(root) -> dict[str, str]:
    import hashlib

    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in root.rglob("*") if p.is_file()
    }


def test_synthesize_output_is_byte_identical_on_a_rerun(micro_stage_paths, tmp_path):
    """The DVC out holds no timings: the same seed gives the same bytes (and hash), so a re-run of
    `synthesize` re-runs nothing after it."""
    from stages import synthesize

    cfg = compose_cfg(
        "synthesize",
        # the main set only: it is what this compares (the OOD set's rooms would double the render)
        [
            "profile=micro",
            f"paths.outputs={tmp_path}/outputs",
            f"paths.reports={tmp_path}/reports",
            "progress=false",
            "ood.scenes=0",
        ],
    )
    metrics = synthesize.run(cfg)
    assert metrics["wall_seconds"] > 0  # timings are reported ...
    first = _tree_digest(micro_stage_paths["outputs"] / "synthesize")
    again = _tree_digest(tmp_path / "outputs" / "synthesize")
    assert again == first  # ... but not written into the dataset
    record = json.loads((tmp_path / "outputs" / "synthesize" / "dataset.json").read_text())
    assert "wall_seconds" not in record and all("seconds" not in s for s in record["scenes"])
