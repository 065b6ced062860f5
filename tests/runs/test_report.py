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
