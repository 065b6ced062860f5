import pytest

from pipeline.cli import main

pytestmark = pytest.mark.slow


def test_validate_and_sheet(micro_root, tmp_path, capsys):
    assert main(["validate", str(micro_root)]) == 0
    assert '"rejected_views": 0' in capsys.readouterr().out
    assert main(["sheet", str(micro_root), "--out", str(tmp_path / "s.png"), "--views", "1"]) == 0
    assert (tmp_path / "s.png").stat().st_size > 1000


def test_validate_reports_bad_root(tmp_path, capsys):
    assert main(["validate", str(tmp_path)]) == 2
    assert "train.txt: split file not found" in capsys.readouterr().err
