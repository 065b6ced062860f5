"""`python -m pipeline.bench.device_step`: each profile's training steps on an accelerator beside the CPU,
in one run: does the step run there, does it compute what the CPU computes, how long it takes, and does
it learn.

For each profile (`--profiles`, default tiny and paper) and training stage (`train_material`,
`train_lighting`), the stage's system is built as the stage builds it (`common.training_system`, the
profile's own batch size, optimiser and gradient clip), once on the CPU and once moved to `--device`,
from the same seeded initialisation. The data are `--data-dir`'s shards at whatever size they were
written (a profile's networks take any size; the paper's 320x240 needs its own synthesize run). A
LightNet needs a frozen MaterialNet: the profile's own, untrained (its weights do not matter to the
step's cost or to whether it runs), exported to a temporary file.

Reported per case (`--parts`), in this order (the device's parts first, so that a run stopped at its
time limit keeps them), each on its own so that one failure does not hide the others:
- `operations`: what one step issues from the host: operations, aten operations (kernel launches on a
  GPU) and host reads of a device value (each a synchronisation), counted by the profiler.
- `timing`: the median synchronised step time on the device (`--steps` timed after `--warmup`) and its
  peak memory.
- `learning`: `--learn-steps` steps on the device over `--learn-batches` fixed batches with the stage's
  optimiser and clip: the mean loss of the first and last tenth, and (LightNet) the surface probes' nMSE
  on those batches before and after.
- `agreement`: the same weights on the same views, CPU against device: MaterialNet's maps (relative L2
  difference per map) and LightNet's radiance at every probe texel and its light errors (deterministic:
  SSRT, the branches' queries). The re-render is not compared: its random draws differ between devices.
- `cpu_timing`: the median step on the same host's CPU (`--cpu-steps` after one untimed), and the ratio.
Writes reports/bench/<--name>.json and a PNG.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import tempfile
import time
import traceback
from pathlib import Path

import torch
from matplotlib.figure import Figure

from pipeline.bench.common import (
    add_threads_option,
    apply_threads,
    gradient_clip,
    optimiser_step,
    publish,
    training_system,
)

STAGES = ("train_material", "train_lighting")
PARTS = ("setup", "operations", "timing", "learning", "agreement", "cpu_timing")


def move(batch, device: str):
    """The batch on `device` as Lightning moves it (tensors, and objects with a `.to`, in any nesting)."""
    from lightning.fabric.utilities.apply_func import move_data_to_device

    return move_data_to_device(batch, torch.device(device))


def synchronise(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def material_export(profile: str, directory: Path, data_dir: str) -> Path:
    """An untrained MaterialNet export of `profile` (seeded), sized for `data_dir`'s views."""
    from pipeline.data.datasets import read_manifest
    from pipeline.models.export import save_material_export

    system, _, _ = training_system("train_material", [f"profile={profile}", f"data_dir={data_dir}"], 0)
    manifest = read_manifest(data_dir)
    path = directory / f"material_{profile}.pt"
    return save_material_export(
        path, system.hparams["model"], system.net, (manifest["height"], manifest["width"]), depth_scale=1.0
    )


def build_case(profile: str, stage: str, data_dir: str, material: Path | None, seed: int, extra: list[str]):
    overrides = [f"profile={profile}", f"data_dir={data_dir}", *extra]
    if stage == "train_lighting":
        overrides.append(f"material_path={material}")
    return training_system(stage, overrides, seed)


def batches(cfg, stage: str, data_dir: str, count: int, seed: int, split: str = "fit") -> list[dict]:
    """`count` batches of the stage's batch size from the training split (or the test split)."""
    from pipeline.data.datamodules import InteriorVerseDataModule

    dm = InteriorVerseDataModule(
        data_dir, batch_size=int(cfg.batch_size), seed=seed, lighting=stage == "train_lighting"
    )
    dm.setup(split)
    loader = dm.train_dataloader() if split == "fit" else dm.plain_loader("test")
    out = []
    while len(out) < count:
        before = len(out)
        for batch in loader:
            out.append(batch)
            if len(out) >= count:
                break
        if len(out) == before:
            raise ValueError(f"{data_dir}: its {split} split gives no batch of size {cfg.batch_size}")
    return out


def relative_difference(a: torch.Tensor, b: torch.Tensor) -> float:
    """||a - b|| / ||b|| in float64 (both on the CPU)."""
    a, b = a.detach().double().cpu(), b.detach().double().cpu()
    return float((a - b).norm() / b.norm().clamp_min(1e-30))


@torch.no_grad()
def light_predictions(system, batch: dict) -> dict[str, tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    """Per probe kind (surf, free): LightNet's (prediction, target, scale) at every texel of the batch's
    probes, as `evaluate_batch` queries them (without its re-render, whose draws differ between devices)."""
    from pipeline.data.lighting import probe_rays

    fov = system.fov(batch)
    gb = system.gbuffers(batch)
    ctx = system.net.encode(batch["im"], gb["depth"], fov, normal=gb["normal"])
    out = {}
    for kind in ("surf", "free"):
        rays = probe_rays(batch["light"], kind)
        if rays is not None:
            rays = rays.to(system.device)
            pred = system.query(ctx, gb, fov, rays, system.eval_generator())["radiance"]
            out[kind] = (pred, rays.radiance, ctx["scale"][rays.image])
    return out


@torch.no_grad()
def agreement(stage: str, cpu_system, dev_system, batch: dict, device: str) -> dict:
    """CPU against device on `batch` with equal weights (evaluation mode): per MaterialNet map, or per
    LightNet probe kind, the relative L2 difference of the outputs and each side's light errors."""
    from pipeline.metrics.lighting import light_errors

    cpu_system.eval()
    dev_system.eval()
    try:
        if stage == "train_material":
            ref = cpu_system.net(batch["im"])
            got = dev_system.net(move(batch, device)["im"])
            return {f"{k}_relative_l2": relative_difference(got[k], ref[k]) for k in ref}
        ref = light_predictions(cpu_system, batch)
        got = light_predictions(dev_system, move(batch, device))
        return {
            kind: {
                "radiance_relative_l2": relative_difference(got[kind][0], ref[kind][0]),
                "cpu": light_errors(*ref[kind]),
                "device": light_errors(*(t.cpu() for t in got[kind])),
            }
            for kind in ref
        }
    finally:
        cpu_system.train()
        dev_system.train()


def timed_steps(system, optimizer, cfg, moved: list[dict], device: str, warmup: int, steps: int) -> list[float]:
    """Wall times (s) of `steps` synchronised optimiser steps after `warmup` untimed ones, cycling the
    batches `moved` (already on `device`)."""
    clip = gradient_clip(cfg)
    times = []
    for i in range(warmup + steps):
        batch = moved[i % len(moved)]
        synchronise(device)
        t0 = time.perf_counter()
        optimiser_step(system, optimizer, batch, i, clip)
        synchronise(device)
        if i >= warmup:
            times.append(time.perf_counter() - t0)
    return times


# operations whose result size or value the host must read from the device before it can go on: each
# waits for everything queued before it on a GPU (on a CPU they cost nothing special)
SYNCING = (
    "aten::_local_scalar_dense",  # .item(), float(t), bool(t), int(t)
    "aten::nonzero",  # boolean-mask indexing, torch.where(condition)
    "aten::masked_select",
    "aten::_unique2",
    "aten::unique_consecutive",
    "aten::unique_dim",
)


def operations(system, optimizer, cfg, moved: list[dict], device: str, steps: int = 3, sites: int = 12) -> dict:
    """What an optimiser step issues from the host, the mean over `steps` steps after one untimed step
    (the profiler's CPU events, `train_step.self_cpu_times`): every operation, the aten operations among
    them (each at least one kernel launch on a GPU), the host reads of a device value
    (`aten::_local_scalar_dense`, `.item()`) and every operation that synchronises (`SYNCING`: each waits
    for the device), per name. Counts, not times: the same on any device up to compiled regions; they
    vary from step to step with the rays drawn (the SSRT march runs until its last ray ends). Then one
    more step profiled with Python stacks: the `sites` project source lines that issue the most
    synchronising operations (the innermost frame under pipeline/), per step."""
    from collections import Counter

    from torch.profiler import ProfilerActivity, profile

    from pipeline.bench.train_step import self_cpu_times

    clip = gradient_clip(cfg)
    optimiser_step(system, optimizer, moved[0], 0, clip)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for i in range(1, steps + 1):
            optimiser_step(system, optimizer, moved[i % len(moved)], i, clip)
        synchronise(device)
    totals = self_cpu_times(prof.profiler.kineto_results.events())
    aten = [v["count"] for k, v in totals.items() if k.startswith("aten::")]
    syncing = {k: totals[k]["count"] / steps for k in SYNCING if k in totals}
    with profile(activities=[ProfilerActivity.CPU], with_stack=True) as traced:
        optimiser_step(system, optimizer, moved[0], steps + 1, clip)
        synchronise(device)
    where = Counter()
    for event in traced.events():
        if event.name in SYNCING:
            # with stacks, each Python call is an event of its own ("path.py(line): name"): the innermost
            # ancestor in the project's code is the site
            owner = event.cpu_parent
            while owner is not None and not ("pipeline/" in owner.name and ".py(" in owner.name):
                owner = owner.cpu_parent
            if owner is not None and "pipeline/bench/" in owner.name:
                owner = None
            where[owner.name.split("pipeline/", 1)[1] if owner else "(outside pipeline/)"] += 1
    return {
        "steps": steps,
        "operations_per_step": sum(v["count"] for v in totals.values()) / steps,
        "aten_operations_per_step": sum(aten) / steps,
        "host_reads_per_step": totals.get("aten::_local_scalar_dense", {}).get("count", 0) / steps,
        "synchronising_per_step": sum(syncing.values()),
        "synchronising_by_operation": syncing,
        "synchronising_sites_one_step": dict(where.most_common(sites)),
    }


def light_nmse(system, moved: list[dict]) -> float | None:
    """The surface probes' nMSE pooled over `moved` batches (evaluation mode), or None for a MaterialNet."""
    from pipeline.metrics.lighting import light_errors

    if "light" not in moved[0]:
        return None
    system.eval()
    try:
        parts = [light_predictions(system, b).get("surf") for b in moved]
    finally:
        system.train()
    parts = [p for p in parts if p is not None]
    if not parts:
        return None
    return light_errors(*(torch.cat([p[i] for p in parts]) for i in range(3)))["light_nmse"]


def learning(system, optimizer, cfg, moved: list[dict], steps: int) -> dict:
    """`steps` optimiser steps over the fixed batches `moved` (on the system's device): the loss's first and
    last tenth."""
    clip = gradient_clip(cfg)
    before = light_nmse(system, moved)
    losses = [optimiser_step(system, optimizer, moved[i % len(moved)], i, clip) for i in range(steps)]
    tenth = max(steps // 10, 1)
    return {
        "steps": steps,
        "batches": len(moved),
        "loss_first_tenth": statistics.fmean(losses[:tenth]),
        "loss_last_tenth": statistics.fmean(losses[-tenth:]),
        "finite": all(map(lambda x: x == x and abs(x) != float("inf"), losses)),
        "surf_light_nmse_before": before,
        "surf_light_nmse_after": light_nmse(system, moved),
        "losses": losses,
    }


def part(record: dict, name: str, fn) -> None:
    """record[name] = fn(), or the error and its traceback: every part of a case is tried."""
    try:
        record[name] = fn()
    except Exception as exc:  # a bench of what runs where: a failure is a result, recorded and shown
        record[name] = {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
        print(f"  {name}: {type(exc).__name__}: {exc}")


def run_case(profile, stage, args, material) -> dict:
    record: dict = {"profile": profile, "stage": stage}
    state: dict = {}

    def setup():
        cpu = build_case(profile, stage, args.data_dir, material, args.seed, args.override)
        state["cpu"] = cpu
        system, _, cfg = cpu
        dev_system = copy.deepcopy(system).to(args.device)
        from hydra.utils import instantiate

        state["dev"] = (dev_system, instantiate(cfg.optim.optimizer)(dev_system.net.parameters()), cfg)
        state["train"] = batches(cfg, stage, args.data_dir, max(args.learn_batches, 2), args.seed)
        state["test"] = batches(cfg, stage, args.data_dir, 1, args.seed, split="test")[0]
        state["moved"] = [move(b, args.device) for b in state["train"]]  # once, for every device part
        return {
            "batch_size": int(cfg.batch_size),
            "image": list(state["train"][0]["im"].shape[-2:]),
            "parameters": sum(p.numel() for p in system.net.parameters()),
            "gradient_clip": gradient_clip(cfg),
        }

    part(record, "setup", setup)
    if "dev" not in state:
        return record
    # the device's parts first, the CPU's last: a run stopped at its time limit keeps what only the
    # device can measure (a large profile's CPU side takes minutes)
    if "operations" in args.parts:
        part(record, "operations", lambda: operations(*state["dev"], state["moved"], args.device, args.operation_steps))

    def timing():
        if args.device.startswith("cuda"):
            torch.cuda.reset_peak_memory_stats()
        dev = timed_steps(*state["dev"], state["moved"], args.device, args.warmup, args.steps)
        out = {"device_median_s": statistics.median(dev), "device_steps": len(dev)}
        if args.device.startswith("cuda"):
            out["device_peak_memory_gib"] = torch.cuda.max_memory_allocated() / 2**30
        return out

    if "timing" in args.parts:
        part(record, "timing", timing)

    def learn():
        from hydra.utils import instantiate

        system, _, cfg = build_case(profile, stage, args.data_dir, material, args.seed, args.override)
        system = system.to(args.device)
        optimizer = instantiate(cfg.optim.optimizer)(system.net.parameters())
        return learning(system, optimizer, cfg, state["moved"], args.learn_steps)

    if "learning" in args.parts:
        part(record, "learning", learn)
    if "agreement" in args.parts:
        # the device's copy has trained by now: compare the CPU's untouched system with a fresh copy of it
        cpu_system = state["cpu"][0]
        part(
            record,
            "agreement",
            lambda: agreement(stage, cpu_system, copy.deepcopy(cpu_system).to(args.device), state["test"], args.device),
        )

    def cpu_timing():
        cpu = timed_steps(*state["cpu"], state["train"], "cpu", 1, args.cpu_steps)
        out = {"cpu_median_s": statistics.median(cpu), "cpu_steps": len(cpu)}
        device = record.get("timing", {}).get("device_median_s")
        if device:
            out["speedup"] = out["cpu_median_s"] / device
        return out

    if "cpu_timing" in args.parts and args.cpu_steps > 0:
        part(record, "cpu_timing", cpu_timing)
    return record


def plot(report: dict, path) -> None:
    """Up to three panels, each drawn only where the run measured it: median step times (device and the
    same host's CPU), the operations and host reads a step, and the memorising runs' losses."""
    cases = report["cases"]
    timed = [c for c in cases if isinstance(c.get("timing"), dict) and "device_median_s" in c["timing"]]
    counted = [
        c for c in cases if isinstance(c.get("operations"), dict) and "aten_operations_per_step" in c["operations"]
    ]
    learnt = [c for c in cases if isinstance(c.get("learning"), dict) and "losses" in c["learning"]]
    panels = [p for p, rows in (("time", timed), ("operations", counted), ("learning", learnt)) if rows]
    if not panels:
        panels = ["time"]
    fig = Figure(figsize=(4.6 * len(panels), 3.8))
    axes = dict(zip(panels, fig.subplots(1, len(panels), squeeze=False)[0], strict=True))

    def label(c):
        return f"{c['profile']}\n{c['stage']}"

    if "time" in axes:
        ax = axes["time"]
        y = range(len(timed))
        ax.barh(
            [i + 0.2 for i in y], [c["timing"]["device_median_s"] * 1e3 for c in timed], 0.4, label=report["device"]
        )
        cpu = [c.get("cpu_timing", c["timing"]).get("cpu_median_s", 0) * 1e3 for c in timed]
        ax.barh([i - 0.2 for i in y], cpu, 0.4, label="cpu (same host)")
        ax.set_yticks(list(y), [label(c) for c in timed], fontsize=7)
        ax.set_xscale("log")
        ax.set_xlabel("median training step (ms, log)")
        ax.legend(fontsize=7)
        if not timed:
            ax.set_title("no step timed", fontsize=8)
    if "operations" in axes:
        ax = axes["operations"]
        y = range(len(counted))
        ops = [c["operations"] for c in counted]
        ax.barh([i + 0.2 for i in y], [o["aten_operations_per_step"] for o in ops], 0.4, label="aten operations")
        waits = [o.get("synchronising_per_step", o["host_reads_per_step"]) for o in ops]
        ax.barh([i - 0.2 for i in y], waits, 0.4, label="synchronising operations")
        for i, o in enumerate(ops):
            ax.text(
                o["aten_operations_per_step"],
                i + 0.2,
                f" {o['aten_operations_per_step']:,.0f}",
                va="center",
                fontsize=6,
            )
            ax.text(waits[i], i - 0.2, f" {waits[i]:,.0f}", va="center", fontsize=6)
        ax.set_yticks(list(y), [label(c) for c in counted], fontsize=7)
        ax.set_xscale("log")
        ax.set_xlabel("per training step (log; profiled on " + report["device"] + ")")
        ax.legend(fontsize=7)
    if "learning" in axes:
        ax = axes["learning"]
        for c in learnt:
            ax.plot(c["learning"]["losses"], lw=0.8, label=f"{c['profile']} {c['stage']}")
        ax.set_yscale("log")
        ax.set_xlabel(f"step on {report['device']} (fixed batches)")
        ax.set_ylabel("training loss")
        ax.legend(fontsize=6)
    fig.suptitle(f"training steps on {report['device']}: " + ", ".join(panels), fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--profiles", nargs="+", default=["tiny", "paper"])
    p.add_argument("--stages", nargs="+", default=list(STAGES), choices=STAGES)
    p.add_argument("--data-dir", default="outputs/preprocess")
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--steps", type=int, default=20, help="timed steps on the device")
    p.add_argument("--operation-steps", type=int, default=3, help="profiled steps of `operations`")
    p.add_argument("--cpu-steps", type=int, default=2, help="timed steps on the CPU (0: none)")
    p.add_argument("--learn-steps", type=int, default=200)
    p.add_argument("--learn-batches", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--parts", nargs="+", default=list(PARTS[1:]), choices=PARTS[1:], help="what to measure")
    p.add_argument("--name", default="device_step")
    p.add_argument("--override", action="append", default=[], help="an override for every stage (repeatable)")
    add_threads_option(p)
    a = p.parse_args(argv)
    try:
        torch.empty(0, device=a.device)
    except (RuntimeError, AssertionError) as exc:  # no such device here: say so before building anything
        p.error(f"--device {a.device}: not available here ({exc})")
    apply_threads(a.threads)
    data_dir = str(Path(a.data_dir).resolve())
    a.data_dir = data_dir
    cases = []
    with tempfile.TemporaryDirectory() as tmp:
        for profile in a.profiles:
            material = None
            if "train_lighting" in a.stages:
                material = material_export(profile, Path(tmp), data_dir)
            for stage in a.stages:
                print(f"{profile} {stage}", flush=True)
                cases.append(run_case(profile, stage, a, material))
                # written after every case: a run stopped at its time limit keeps what it measured
                report = {"device": a.device, "data_dir": a.data_dir, "cases": cases, "settings": vars(a)}
                path = publish(a.name, report, plot, a.device)
                summarise(cases[-1])
    print(path)


def summarise(c: dict) -> None:
    """One line per case: each part's outcome and the times."""
    status = {k: v["error"] if isinstance(v, dict) and "error" in v else "ok" for k, v in c.items() if k in PARTS}
    times = {}
    for name in ("timing", "cpu_timing"):
        if isinstance(c.get(name), dict):
            times.update({k: round(v, 4) for k, v in c[name].items() if isinstance(v, float)})
    print(c["profile"], c["stage"], status, times, flush=True)


if __name__ == "__main__":
    main()
