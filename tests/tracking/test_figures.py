"""Figures are drawn on matplotlib's object API: no pyplot state, no global backend switch, PNGs of the
size their figsize and dpi give."""

import subprocess
import sys

import numpy as np
from PIL import Image

from tests.conftest import ROOT


def test_figure_modules_leave_pyplot_unloaded():
    code = (
        "import sys, pipeline.tracking.figures, pipeline.data.synth.figures\nprint('matplotlib.pyplot' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "False"


def test_insertion_grid_and_pareto_figure_write_pngs(tmp_path):
    from pipeline.tracking.figures import insertion_grid, pareto_figure

    rng = np.random.default_rng(0)
    H, W = 24, 32
    panels = []
    for i in range(2):
        photo = rng.gamma(1.0, 0.5, (H, W, 3))
        panels.append(
            {
                "label": f"obj{i}",
                "photo": photo,
                "gt": photo * 1.05,
                "rows": {"lightnet": photo * 0.9, "constant_light": photo * 0.5},
                "psnr": {"lightnet": 25.0, "constant_light": 18.0},
                "pixels": np.array([5 * W + 6, 9 * W + 12]),
                "scale": float(photo.mean()),
            }
        )
    grid = np.asarray(Image.open(insertion_grid(panels, tmp_path / "figs" / "insertion.png", title="insert")))
    assert grid.shape[:2] == (int(1.6 * 2 * 90), int(1.55 * 5 * 90))  # figsize times dpi 90
    assert grid[..., :3].std() > 10  # drawn, not blank
    points = [
        {"label": f"setting_{i}", "seconds": s, "train_minutes": m, "insertion_psnr": a, "render_psnr": b}
        for i, (s, m, a, b) in enumerate([(0.5, 10, 20, 22), (0.6, 12, 20.1, 22.05), (5.0, 40, 21, 23)])
    ]
    pareto = np.asarray(Image.open(pareto_figure(points, tmp_path / "pareto.png", title="pareto")))
    assert pareto.shape[:2] == (810, 1080)
