"""Shared helpers for benchmarks: timing medians, machine description, quoted figures, JSON output.

A bench JSON keeps what it timed or measured in its own run under `measured` and any figure it did not
measure (a number from a paper or another program) under `quoted`, each as {value, unit, source};
nothing under `measured` is derived from a quoted figure.
"""

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
    """Median wall time (s) of fn() over `repeats` runs after `warmup` untimed runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def device_name(device: str = "cpu") -> str:
    """The device a bench ran on, as the JSON records it: `cpu`, or `cuda (<GPU name>)`."""
    dev = torch.device(device)
    if dev.type == "cuda":
        return f"cuda ({torch.cuda.get_device_name(dev)})"
    return dev.type


def threads(n: int) -> str:
    """`1 thread`, `2 threads`: a thread count for figure labels."""
    return f"{n} thread" + ("s" if n != 1 else "")


def add_threads_option(parser) -> None:
    """`--threads N`: torch's intra-op threads for the run (default: torch's own). 1 keeps OpenMP from
    spin-waiting when other work shares the CPU; the JSON records the count either way."""
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's own)")


def apply_threads(n: int | None) -> None:
    if n is not None:
        torch.set_num_threads(n)


def machine(device: str = "cpu") -> dict:
    """Platform, versions, CPU count, torch's intra-op thread count and the device the bench ran on."""
    return {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "device": device_name(device),
    }


def quoted(value: float, unit: str, source: str) -> dict:
    """A figure the bench did not measure: its value, unit and where it comes from."""
    return {"value": value, "unit": unit, "source": source}


def write_report(name: str, payload: dict, device: str = "cpu", path: Path | None = None) -> Path:
    """reports/bench/<name>.json (or `path`): the payload with the bench's name and the machine."""
    path = Path(path) if path is not None else project_root() / "reports" / "bench" / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"benchmark": name, "machine": machine(device), **payload}, indent=1) + "\n")
    return path


def publish(name: str, report: dict, plot, device: str = "cpu") -> Path:
    """Write reports/bench/<name>.json (with the machine and `device` the bench ran on) and, beside it,
    the figure `plot(report, path)` draws as <name>.png."""
    path = write_report(name, report, device)
    plot(report, path.with_suffix(".png"))
    return path


def edit_object_cases(view_id: str, cases: list) -> list:
    """The object cases of one view's `cases` (as `edit.view_context` reads them), checked to come first:
    the `edit` stage seeds a case by its index in the view's list, so the objects alone keep the seeds it
    gives them only when no edit is listed before them."""
    objects = [c for c in cases if c.kind == "object"]
    if cases[: len(objects)] != objects:
        raise ValueError(f"{view_id}: edits listed before objects; the seeds would differ from `edit`'s")
    return objects
