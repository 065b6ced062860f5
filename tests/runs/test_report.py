"""Stage `report`: docs/results.md is what it renders from the committed reports: it cannot drift from
them, a changed number in a report changes it, and a corrupt report is refused naming the file."""

import json
import shutil
from pathlib import Path

import pytest

from pipeline.runs.report import results_markdown
from pipeline.tracking.results_page import num
from tests.conftest import ROOT

REPORTS = ROOT / "reports"


def render(reports: Path) -> str:
    """The page as the stage renders it: with the claims of conf/claims/ (the report's own config)."""
    import yaml

    claims = yaml.safe_load((ROOT / "conf" / "claims" / "paper.yaml").read_text())
    return results_markdown(reports, reports / "ablate", "tiny", claims)


def test_committed_results_page_is_what_the_reports_render():
    committed = (ROOT / "docs" / "results.md").read_text()
    assert render(REPORTS) == committed, (
        "docs/results.md differs from what the reports render: run `dvc repro report` "
        "(or `python -m stages.report`) and commit the result"
    )


def test_a_changed_report_number_changes_the_page(tmp_path):
    reports = tmp_path / "reports"
    shutil.copytree(REPORTS, reports)
    path = reports / "edit" / "metrics.json"
    metrics = json.loads(path.read_text())
    before = render(reports)
    written = metrics["insert/mirror/lightnet/psnr"]
    assert f"| lightnet | {num(written)} |" in before  # mirror insertion PSNR as the edit stage wrote it
    metrics["insert/mirror/lightnet/psnr"] = written + 1.5
    path.write_text(json.dumps(metrics))
    after = render(reports)
    assert after != before and f"| lightnet | {num(metrics['insert/mirror/lightnet/psnr'])} |" in after


def test_corrupt_or_missing_reports(tmp_path):
    reports = tmp_path / "reports"
    shutil.copytree(REPORTS, reports)
    (reports / "train_material" / "metrics.json").write_text("{not json")
    with pytest.raises(ValueError, match="train_material/metrics.json"):
        render(reports)
    (reports / "train_material" / "metrics.json").unlink()
    assert "No `" in render(reports)  # the section says which file is missing instead of printing numbers
    (reports / "evaluate" / "trained_iiw.csv").write_text("id,whdr_gamma\n1000,nan-ish\n")
    with pytest.raises(ValueError, match="trained_iiw.csv: row 2"):
        render(reports)


def test_the_ring_table_shows_each_row_and_its_paired_differences(tmp_path):
    reports = tmp_path / "reports"
    shutil.copytree(REPORTS, reports)
    path = reports / "edit" / "metrics.json"
    metrics = {k: v for k, v in json.loads(path.read_text()).items() if "/ring/" not in k}
    path.write_text(json.dumps(metrics))
    assert "The room around each inserted object" not in render(reports)  # a stage run without the ring
    ring = {"insert/all/ring/cases": 40.0, "scoring_spp/ring": 128.0}
    for k, who in enumerate(("no_shadows", "lightnet", "scaled_constant", "nearest_probe")):
        ring[f"insert/all/ring/{who}/psnr"] = 30.0 + k
        ring[f"insert/all/ring/{who}/psnr_surround"] = 40.0 + k
    p = "insert/all/ring/lightnet_minus_no_shadows/psnr"
    ring.update({f"{p}_diff": 1.25, f"{p}_lo": 0.5, f"{p}_hi": 2.0, f"{p}_verdict": 1.0})
    path.write_text(json.dumps({**metrics, **ring}))
    page = render(reports)
    assert "The room around each inserted object" in page and "at 128 samples per pixel" in page
    ring_table = page.split("The room around each inserted object")[1]
    row = next(line for line in ring_table.splitlines() if line.startswith("| lightnet |"))
    assert row.split("|")[-3:-1] == [f" {num(31.0)} ", f" {num(41.0)} "]  # ring all, surroundings all
    assert "| ring all | lightnet - no_shadows | +1.25 |" in page
