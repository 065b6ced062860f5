"""Shared helpers for benchmarks: timing medians, machine description, JSON output."""

from __future__ import annotations

import json
import os
import platform
import statistics
import time
from pathlib import Path

import torch

from pipeline.tracking import project_root


def median_seconds(fn, repeats: int = 3, warmup: int = 1) -> float:
    """Median wall time of fn() over `repeats` runs after `warmup` untimed runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def machine() -> dict:
    return {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu",
    }


def write_report(name: str, payload: dict) -> Path:
    path = project_root() / "reports" / "bench" / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"benchmark": name, "machine": machine(), **payload}, indent=1) + "\n")
    return path


def publish(name: str, report: dict, plot) -> Path:
    """Write reports/bench/<name>.json and, beside it, the figure `plot(report, path)` draws as <name>.png."""
    path = write_report(name, report)
    plot(report, path.with_suffix(".png"))
    return path
