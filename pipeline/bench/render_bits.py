"""`python -m pipeline.bench.render_bits`: does the generator render the same bits on another machine?

`synthesize` renders with Mitsuba's llvm variant. Dr.Jit compiles its kernels for the host CPU (vector width
and instruction set) and Embree picks its ray-tracing kernels at run time, so two machines can write
different floats from the same seed and config, and DVC then sees new data and retrains everything.

`--name NAME` renders one micro room (scene 1 of the `micro` profile, with its insertion and editing cases)
in a fresh process, exactly as `synthesize` renders a scene, and writes for this machine
reports/bench/render_bits_<NAME>.json (the CPU, Dr.Jit's LLVM target and vector width, a SHA-256 per file)
and reports/bench/render_bits_<NAME>.npz (every array the scene wrote). `--llvm-target CPU:WIDTH` (e.g.
`haswell:8`) overrides Dr.Jit's target first.

`--compare A B` reads two such runs (made on two machines) and writes reports/bench/render_bits.json and a
PNG: per array, the fraction of values that differ, their distance in float32 units in the last place
(ULP) and their relative difference.
"""

from __future__ import annotations

import argparse
import ctypes
import hashlib
import os
import tempfile
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from pipeline.bench.common import bench_dir, compose, publish, write_report

SCENE = 1  # a test-split room of the micro profile: it has insertion and editing cases
SEED = 0


# ----------------------------------------------------------------------------------------------------
# Dr.Jit's LLVM target (exported by libdrjit-core as C++ functions: no Python binding in Dr.Jit 1.5)


def _drjit_core():
    import drjit as dr

    return ctypes.CDLL(str(Path(dr.__file__).parent / "libdrjit-core.so"))


def llvm_target() -> dict | None:
    """{cpu, features, vector_width} the LLVM backend compiles for, or None where Dr.Jit does not say."""
    try:
        lib = _drjit_core()
        cpu, feats = lib._Z19jit_llvm_target_cpuv, lib._Z24jit_llvm_target_featuresv
        width = lib._Z21jit_llvm_vector_widthv
    except (OSError, AttributeError):
        return None
    cpu.restype = feats.restype = ctypes.c_char_p
    width.restype = ctypes.c_uint32
    features = feats()
    return {
        "cpu": (cpu() or b"").decode(),
        "features": features.decode() if features else None,
        "vector_width": int(width()),
    }


def set_llvm_target(spec: str) -> None:
    """`CPU:WIDTH` (e.g. `haswell:8`): Dr.Jit's LLVM backend compiles for that CPU and vector width."""
    cpu, _, width = spec.partition(":")
    if not cpu or not width.isdigit() or int(width) not in (1, 2, 4, 8, 16, 32):
        raise ValueError(f"--llvm-target={spec!r}: give CPU:WIDTH with WIDTH a power of two up to 32, e.g. haswell:8")
    try:
        fn = _drjit_core()._Z19jit_llvm_set_targetPKcS0_j
    except AttributeError as e:
        raise RuntimeError("--llvm-target: this Dr.Jit does not export jit_llvm_set_target") from e
    fn.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
    fn(cpu.encode(), b"", int(width))  # no extra features: the CPU's own (never NULL: Dr.Jit searches it)


def host_cpu() -> dict:
    """The CPU's model name and whether it has AVX2, FMA and AVX-512 (from /proc/cpuinfo where present)."""
    info = Path("/proc/cpuinfo")
    text = info.read_text() if info.exists() else ""
    model = next((ln.split(":", 1)[1].strip() for ln in text.splitlines() if ln.startswith("model name")), None)
    flags = next((ln.split(":", 1)[1].split() for ln in text.splitlines() if ln.startswith("flags")), [])
    return {"model": model, **{f: f in flags for f in ("avx2", "fma", "avx512f")}}


# ----------------------------------------------------------------------------------------------------
# One scene, rendered as `synthesize` renders it


def scene_arrays(folder: Path) -> dict[str, np.ndarray]:
    """Every numeric array under `folder`: EXR images as `<file>` (H, W, C) and NPZ members as
    `<file>:<member>`, keyed by the path relative to `folder`."""
    from pipeline.data.formats.exr import read_exr

    out = {}
    for path in sorted(folder.rglob("*")):
        rel = path.relative_to(folder).as_posix()
        if path.suffix == ".exr":
            out[rel] = np.asarray(read_exr(path))
        elif path.suffix == ".npz":
            with np.load(path) as z:
                out.update({f"{rel}:{k}": z[k] for k in z.files if np.issubdtype(z[k].dtype, np.number)})
    return out


def _render(synth: dict, target: str | None, out: str) -> dict:
    """In a fresh process: set the variant (and target), render scene SCENE into `out`."""
    from pipeline.data.synth import generate as g
    from pipeline.data.synth import mitsuba_backend as mb

    cfg = g.SynthConfig.from_dict(synth)
    variant = mb.choose_variant(cfg.variant)
    mb.init_mitsuba(variant)
    if target:
        if not variant.startswith("llvm"):
            raise RuntimeError(f"--llvm-target needs the llvm variant; this machine renders with {variant}")
        set_llvm_target(target)
    jit = llvm_target() if variant.startswith("llvm") else None
    g.render_scene(SCENE, SEED, cfg, out, variant, os.cpu_count() or 1, with_cases=True)
    return {"variant": variant, "llvm_target": jit}


def render(
    profile: str = "micro", target: str | None = None, variant: str = "auto", overrides=()
) -> tuple[dict, dict[str, np.ndarray]]:
    """(report, arrays) of one scene rendered on this machine: variant, LLVM target, host CPU and a
    SHA-256 (first 16 hex digits) per file; `arrays` as `scene_arrays` reads them."""
    from omegaconf import OmegaConf

    synth = OmegaConf.to_container(
        compose("synthesize", [f"profile={profile}", f"synth.variant={variant}", *overrides]).synth, resolve=True
    )
    with tempfile.TemporaryDirectory() as tmp:
        with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as pool:  # a target is per process
            run = pool.submit(_render, synth, target, tmp).result()
        files = {
            p.relative_to(tmp).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()[:16]
            for p in sorted(Path(tmp).rglob("*"))
            if p.is_file()
        }
        arrays = scene_arrays(Path(tmp))
    total = hashlib.sha256("".join(f"{k}{v}" for k, v in files.items()).encode()).hexdigest()[:16]
    report = {
        "scene": SCENE,
        "seed": SEED,
        "profile": profile,
        "overrides": list(overrides),
        "denoise": bool(synth["denoise"]),
        "override": target,
        "host": host_cpu(),
        **run,
    }
    summary = {"files": len(files), "arrays": len(arrays)}
    if run["llvm_target"]:
        summary["LLVM vector width"] = run["llvm_target"]["vector_width"]
    return {**report, "summary": summary, "total_sha256": total, "files": files}, arrays


# ----------------------------------------------------------------------------------------------------
# Two machines compared


def ulp_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| in float32 units in the last place, for finite values (across zero too: the smallest positive
    float and its negative are 2 apart; +0 and -0 are 0 apart)."""
    ia = np.asarray(a, np.float32).view(np.int32).astype(np.int64)
    ib = np.asarray(b, np.float32).view(np.int32).astype(np.int64)
    # map the sign-magnitude bit patterns onto a line where adjacent floats differ by one
    ia = np.where(ia < 0, np.int64(-(2**31)) - ia, ia)
    ib = np.where(ib < 0, np.int64(-(2**31)) - ib, ib)
    return np.abs(ia - ib)


def compare_arrays(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict:
    """Per array key present in both: values, the fraction that differ, median and max ULP distance and
    max relative difference of those that do. Keys in only one run and shape mismatches are listed."""
    rows, mismatched, pooled, values = {}, [], [], 0
    for key in sorted(set(a) & set(b)):
        x, y = np.asarray(a[key]), np.asarray(b[key])
        if x.shape != y.shape:
            mismatched.append({"array": key, "shapes": [list(x.shape), list(y.shape)]})
            continue
        differ = ~((x == y) | (np.isnan(x) & np.isnan(y)))
        row = {"values": int(x.size), "differing_fraction": float(differ.mean()) if x.size else 0.0}
        values += x.size
        if differ.any():
            ulps = ulp_distance(x[differ], y[differ])
            pooled.append(ulps)
            rel = np.abs(x[differ].astype(np.float64) - y[differ]) / np.maximum(np.abs(x[differ]), 1e-30)
            row.update(median_ulp=float(np.median(ulps)), max_ulp=int(ulps.max()), max_relative=float(np.nanmax(rel)))
        rows[key] = row
    ulps = np.concatenate(pooled) if pooled else np.zeros(0, np.int64)
    summary = {
        "arrays compared": len(rows),
        "arrays with differing values": sum(r["differing_fraction"] > 0 for r in rows.values()),
        "values differing (%)": 100 * ulps.size / max(values, 1),
        "median ULP distance of differing values": float(np.median(ulps)) if ulps.size else 0.0,
        "99th-percentile ULP distance": float(np.percentile(ulps, 99)) if ulps.size else 0.0,
        "largest relative difference": max((r.get("max_relative", 0.0) for r in rows.values()), default=0.0),
    }
    return {
        "summary": summary,
        "arrays": rows,
        "identical": not mismatched and set(a) == set(b) and all(r["differing_fraction"] == 0 for r in rows.values()),
        "only_in_first": sorted(set(a) - set(b)),
        "only_in_second": sorted(set(b) - set(a)),
        "shape_mismatch": mismatched,
    }


def load_run(name: str) -> tuple[dict, dict[str, np.ndarray]]:
    """A run written by `--name NAME`: its JSON and arrays (clear errors naming the missing file)."""
    import json

    path = bench_dir() / f"render_bits_{name}.json"
    arrays = path.with_suffix(".npz")
    for p in (path, arrays):
        if not p.exists():
            raise FileNotFoundError(
                f"{p}: no such run; make it with `python -m pipeline.bench.render_bits --name {name}`"
            )
    with np.load(arrays) as z:
        return json.loads(path.read_text()), {k: z[k] for k in z.files}


def compare(first: str, second: str) -> dict:
    (ra, a), (rb, b) = load_run(first), load_run(second)
    describe = ("host", "variant", "llvm_target", "override", "denoise", "total_sha256")
    arrays = compare_arrays(a, b)
    files = set(ra["files"]) | set(rb["files"])  # a file only one run wrote differs too
    differing = sorted(k for k in files if ra["files"].get(k) != rb["files"].get(k))
    arrays["summary"] = {"files differing": len(differing), "files": len(files), **arrays["summary"]}
    return {
        "runs": {first: {k: ra.get(k) for k in describe}, second: {k: rb.get(k) for k in describe}},
        "files_differing": differing,
        **arrays,
    }


def plot(report: dict, path: Path) -> None:
    rows = report["arrays"]
    keys = [k for k, r in rows.items() if r["differing_fraction"] > 0] or list(rows)[:1]
    fig = Figure(figsize=(9, 0.28 * len(keys) + 1.6))
    ax = fig.subplots()
    y = np.arange(len(keys))
    ax.barh(y, [100 * rows[k]["differing_fraction"] for k in keys], color="tab:blue")
    for i, k in enumerate(keys):
        r = rows[k]
        if "max_ulp" in r:
            ax.text(1, i, f"median {r['median_ulp']:.0f} ULP, max {r['max_ulp']} ULP", va="center", fontsize=7)
    ax.set_yticks(y, [k.split("/", 1)[-1] for k in keys], fontsize=7)  # the scene is always SCENE
    ax.invert_yaxis()
    ax.set_xlim(0, 100)
    ax.set_xlabel("values that differ (%)")
    first, second = report["runs"]
    ax.set_title(f"scene {SCENE} of the micro profile rendered on two machines: {first} against {second}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--name", help="render here and write reports/bench/render_bits_<NAME>.json and .npz")
    p.add_argument("--llvm-target", help="CPU:WIDTH for Dr.Jit's LLVM backend (e.g. haswell:8)")
    p.add_argument("--profile", default="micro")
    p.add_argument("--variant", default="auto", help="Mitsuba variant: auto (as synthesize), llvm_ad_rgb or scalar_rgb")
    p.add_argument("--override", action="append", default=[], help="a synthesize config override (repeatable)")
    p.add_argument("--compare", nargs=2, metavar=("A", "B"), help="compare two named runs")
    p.add_argument("--report", default="render_bits", help="the comparison's name under reports/bench/")
    args = p.parse_args(argv)
    if bool(args.name) == bool(args.compare):
        p.error("give --name NAME (render here) or --compare A B")
    if args.name:
        if not args.name.replace("-", "").replace("_", "").isalnum():
            p.error(f"--name={args.name!r}: letters, digits, '-' and '_' only")
        report, arrays = render(args.profile, args.llvm_target, args.variant, args.override)
        path = write_report(f"render_bits_{args.name}", report)
        np.savez_compressed(path.with_suffix(".npz"), **arrays)
        print(f"{path}: {report['total_sha256']} ({report['variant']}, {report['llvm_target']})")
    else:
        report = compare(*args.compare)
        path = publish(args.report, report, plot)
        print(f"{path}: identical={report['identical']}, files differing: {len(report['files_differing'])}")


if __name__ == "__main__":
    main()
