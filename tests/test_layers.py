"""The layer rules of docs/design.md, section 2, checked by machine: import-linter's contracts and no cycles."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_import_contracts_hold():
    lint = Path(sys.executable).parent / "lint-imports"  # import-linter's console script, beside python
    out = subprocess.run([str(lint), "--no-cache"], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    assert "0 broken" in out.stdout


def test_no_import_cycles():
    import grimp

    graph = grimp.build_graph("pipeline", cache_dir=None)
    modules = sorted(graph.modules)
    state: dict[str, int] = {}  # 1 on the DFS stack, 2 done

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for n in sorted(graph.find_modules_directly_imported_by(m)):
            if state.get(n) == 1:
                raise AssertionError("import cycle: " + " -> ".join([*path[path.index(n) :], n]))
            if n not in state:
                visit(n, [*path, n])
        state[m] = 2

    for m in modules:
        if m not in state:
            visit(m, [m])


def test_every_run_module_is_a_dvc_stage_and_back():
    import yaml

    stages = set(yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"])
    runs = {p.stem for p in (ROOT / "pipeline" / "runs").glob("*.py")} - {"__init__"}
    assert runs == stages
    for name in stages:
        assert (ROOT / "stages" / f"{name}.py").is_file() and (ROOT / "conf" / f"{name}.yaml").is_file(), name
        assert f"from pipeline.runs.{name} import run" in (ROOT / "stages" / f"{name}.py").read_text()


def test_lightning_modules_live_in_systems():
    offenders = [
        str(p.relative_to(ROOT))
        for p in (ROOT / "pipeline").rglob("*.py")
        if "systems" not in p.parts and "(L.LightningModule)" in p.read_text()
    ]
    assert offenders == []
