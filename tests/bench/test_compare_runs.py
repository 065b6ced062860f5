"""bench.compare_runs pairs two runs' per-case and per-view scores and refuses runs that scored other cases."""

import csv
import json

import pytest

from pipeline.bench import compare_runs

HEADER = ["view", "case", "kind", "label", "lightnet/psnr"]


def _cases(path, shift=0.0, drop=None, noise=()):
    rows = []
    for v in range(12):
        for c, label in enumerate(("mirror", "diffuse")):
            if (v, c) == drop:
                continue
            jitter = noise[v % len(noise)] if noise else 0.0
            rows.append([f"scene_{v:04d}/000", f"object{c}", "object", label, 15 + v + c + shift * (c == 0) + jitter])
    rows.append(["scene_0000/000", "edit0", "edit", "metal", 20.0])
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(HEADER)
        w.writerows(rows)
    return path


def test_a_shift_on_mirrors_only_is_found_and_nothing_else(tmp_path):
    old = _cases(tmp_path / "old.csv")
    new = _cases(tmp_path / "new.csv", shift=2.0, noise=(0.3, -0.3, 0.1, -0.1))
    out = tmp_path / "c.json"
    compare_runs.main(["--cases", str(old), str(new), "--out", str(out)])
    groups = json.loads(out.read_text())["cases"]["groups"]
    assert groups["object/mirror"]["verdict"] == "higher"
    assert groups["object/mirror"]["diff"] == pytest.approx(2.0, abs=0.1)
    assert groups["object/diffuse"]["lo"] <= 0 <= groups["object/diffuse"]["hi"]
    assert groups["object/all"]["diff"] == pytest.approx(1.0, abs=0.1)
    assert groups["edit/metal"]["n"] == 1 and groups["edit/metal"]["verdict"] == "no interval"


def test_runs_of_other_cases_and_bad_numbers_are_refused(tmp_path):
    old = _cases(tmp_path / "old.csv")
    with pytest.raises(ValueError, match="same cases"):
        compare_runs.compare_cases(old, _cases(tmp_path / "new.csv", drop=(3, 1)))
    bad = tmp_path / "bad.csv"
    text = old.read_text().splitlines()
    text[1] = text[1].rsplit(",", 1)[0] + ",nan"
    bad.write_text("\n".join(text) + "\n")
    with pytest.raises(ValueError, match="lightnet/psnr is nan"):
        compare_runs.compare_cases(old, bad)
    with pytest.raises(FileNotFoundError, match="missing.csv"):
        compare_runs.compare_cases(old, tmp_path / "missing.csv")


def test_material_views_are_paired_by_view_on_each_map(tmp_path):
    header = ["id", "model/normal_angle_deg", "model/albedo_mse", "mean_albedo/albedo_mse"]

    def views(path, shift):
        with open(path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(header)
            w.writerows([[f"scene_{v:04d}/000", 20 + v + shift + 0.1 * (v % 3), 0.01, 0.04] for v in range(10)])
        return path

    out = tmp_path / "m.json"
    compare_runs.main(
        ["--material", str(views(tmp_path / "a.csv", 0)), str(views(tmp_path / "b.csv", -1)), "--out", str(out)]
    )
    metrics = json.loads(out.read_text())["material"]["metrics"]
    assert set(metrics) == {"normal_angle_deg", "albedo_mse"}  # the model's maps only, not the baselines'
    assert (
        metrics["normal_angle_deg"]["diff"] == pytest.approx(-1.0) and metrics["normal_angle_deg"]["verdict"] == "lower"
    )
    assert metrics["albedo_mse"]["verdict"] == "none"
