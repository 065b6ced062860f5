"""The device bench (`bench.device_step`) and its data copier (`bench.shard_subset`) on the micro data, on
the CPU: every part runs and records its numbers, a failing part is recorded without hiding the others,
and a subset of the shards holds exactly the views it names."""

import json

import numpy as np
import pytest
import torch

from pipeline.bench import device_step, shard_subset
from pipeline.data.datasets import ShardDataset, read_manifest


def test_a_shard_subset_holds_the_first_views_with_their_probes(micro_shards, tmp_path):
    manifest = read_manifest(micro_shards)
    n = len(manifest["splits"]["train"]["views"])
    shard_subset.write_subset(micro_shards, tmp_path / "sub", {"train": n - 1, "test": 1})
    sub, full = ShardDataset(tmp_path / "sub", "train"), ShardDataset(micro_shards, "train")
    assert len(sub) == n - 1 and sub.ids == full.ids[: n - 1]
    for i in (0, n - 2):
        a, b = sub[i], full[i]
        for key in ("im", "depth", "normal", "mask"):
            assert torch.equal(a[key], b[key])
        for kind in ("surf", "free"):
            pa, pb = getattr(a["light"], kind), getattr(b["light"], kind)
            for field, value in vars(pa).items():
                if value is not None:
                    assert np.array_equal(np.asarray(value), np.asarray(getattr(pb, field))), (kind, field)
    written = json.loads((tmp_path / "sub" / "manifest.json").read_text())
    assert set(written["splits"]) == {"train", "test"} and written["height"] == manifest["height"]
    with pytest.raises(ValueError, match="train=10000"):
        shard_subset.write_subset(micro_shards, tmp_path / "bad", {"train": 10_000})
    with pytest.raises(ValueError, match="no split 'nope'"):
        shard_subset.write_subset(micro_shards, tmp_path / "bad", {"nope": 1})
    with pytest.raises(ValueError, match="SPLIT=COUNT"):
        shard_subset.parse_counts(["train:3"])


def test_the_device_bench_runs_every_part_on_the_cpu(micro_shards, monkeypatch, tmp_path):
    written = {}
    monkeypatch.setattr(
        device_step, "publish", lambda name, report, plot, device: written.update(report) or tmp_path / "x.json"
    )
    device_step.main(
        [
            "--device", "cpu", "--profiles", "micro", "--data-dir", str(micro_shards), "--warmup", "0",
            "--steps", "1", "--cpu-steps", "1", "--learn-steps", "2", "--learn-batches", "1", "--operation-steps", "1",
        ]
    )  # fmt: skip
    cases = {c["stage"]: c for c in written["cases"]}
    assert set(cases) == {"train_material", "train_lighting"}
    for case in cases.values():
        assert not [k for k in device_step.PARTS if "error" in case[k]], case
        assert case["timing"]["device_median_s"] > 0 and case["cpu_timing"]["speedup"] > 0
        ops = case["operations"]
        assert ops["aten_operations_per_step"] > 0 and ops["synchronising_per_step"] >= ops["host_reads_per_step"]
        assert case["learning"]["finite"] and case["learning"]["steps"] == 2
    material, light = cases["train_material"], cases["train_lighting"]
    assert all(v == 0.0 for v in material["agreement"].values())  # the same device: the same numbers
    assert light["agreement"]["surf"]["radiance_relative_l2"] == 0.0
    assert 0 < light["learning"]["surf_light_nmse_before"] < 10
    # the sites name project functions: the SSRT march synchronises on every live-ray count
    assert any(site.startswith("ops/ssrt.py") for site in light["operations"]["synchronising_sites_one_step"])
    device_step.plot({**written, "device": "cpu"}, tmp_path / "d.png")
    assert (tmp_path / "d.png").stat().st_size > 5_000


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_a_device_the_machine_lacks_is_refused_at_once(capsys):
    with pytest.raises(SystemExit):
        device_step.main(["--device", "cuda"])
    assert "--device cuda: not available here" in capsys.readouterr().err


def test_a_failing_part_is_recorded_and_the_others_still_run():
    record = {}
    device_step.part(record, "broken", lambda: 1 / 0)
    device_step.part(record, "fine", lambda: {"x": 1})
    assert record["broken"]["error"].startswith("ZeroDivisionError") and "Traceback" in record["broken"]["traceback"]
    assert record["fine"] == {"x": 1}


def test_the_results_page_shows_failed_and_unreached_cases():
    from pipeline.tracking.results_page import device_rows

    data = {
        "settings": {"profiles": ["tiny", "paper"], "stages": ["train_lighting"]},
        "cases": [
            {
                "profile": "tiny",
                "stage": "train_lighting",
                "setup": {"parameters": 10, "batch_size": 4},
                "timing": {"device_median_s": 0.5},
                "cpu_timing": {"cpu_median_s": 1.0, "speedup": 2.0},
                "agreement": {"error": "RuntimeError: boom", "traceback": "..."},
            }
        ],
    }
    tiny, paper = device_rows(data)
    assert tiny["device step (ms)"] == 500 and tiny["CPU step (ms)"] == 1000 and tiny["CPU / device"] == 2.0
    assert tiny["failed or not run"] == "agreement" and tiny["largest CPU/device relative L2"] is None
    assert paper["profile"] == "paper" and paper["failed or not run"].startswith("not reached")
