"""`python -m pipeline.bench.train_step`: the time of one LightNet training step at `tiny` settings, and
what each saving buys, side by side on the same batches.

Settings, cumulative (`SETTINGS`): the step as it was (the frozen MaterialNet run on every step, the
re-render's single sample chunk recomputed in backward), then MaterialNet's maps computed once per view
(`LightingSystem.material_maps`), then the single chunk kept instead of recomputed (`mc.estimate`),
then the SSRT march as a compiled kernel (`model.light_net.ssrt_compiled`). Every setting trains its
own copy of the same seeded network on the same batches; their steps are interleaved round by round, so
load on the machine falls on all alike. Reported: the median step time per setting (steady state, after
a warm-up pass over the batches that also fills the cache and compiles), its ratio to the first, and
the profiler's top operations of the first and last settings.

Same results at equal steps: the first and last settings, trained the same `--steps` steps from the same
initialisation, are scored on the same test views with the same evaluation draws. The two draw their
random numbers in different orders (the recomputed chunk drew again), so they are equal in
distribution, not bit for bit: after a few dozen steps they are two training trajectories, as two seeds
are, and one pair's per-view differences do not hold that trajectory noise. So the pair trains at
`--pair-seeds` seeds (initialisation and batch order each), and each metric's difference (last minus
first, the mean over the views per seed) gets a t interval over the seeds (`metrics.verdicts.seed_effect`),
each seed's difference beside it. Writes reports/bench/train_step.json and a PNG.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from matplotlib.figure import Figure
from tqdm import tqdm

from pipeline.bench.common import (
    add_threads_option,
    apply_threads,
    gradient_clip,
    optimiser_step,
    publish,
    training_system,
)
from pipeline.metrics.verdicts import seed_effect

SETTINGS = (  # name, (cache MaterialNet's maps, recompute a single chunk, compiled SSRT)
    ("as before", (False, True, False)),
    ("+ MaterialNet once per view", (True, True, False)),
    ("+ one-chunk render kept", (True, None, False)),
    ("+ compiled SSRT", (True, None, True)),
)
SCORES = ("surf_light_nmse", "free_light_nmse", "surf_light_log_l1", "free_light_log_l1", "render_psnr")


def build(setting: tuple, seed: int, overrides: list[str]):
    """A `train_lighting` LightingSystem (tiny, predicted G-buffers) under `setting`, and its optimiser."""
    cache, recompute, compiled = setting
    compiled_override = f"model.light_net.ssrt_compiled={str(compiled).lower()}"
    system, optimizer, cfg = training_system("train_lighting", [compiled_override, *overrides], seed)
    system.cache_gbuffers = cache
    system.train_layer.checkpoint_chunks = recompute
    return system, optimizer, cfg


def step(system, optimizer, batch, cfg) -> float:
    """One optimiser step as the stage takes it (`optimiser_step`, the clip of `cfg`'s trainer); its wall
    time (s)."""
    t0 = time.perf_counter()
    optimiser_step(system, optimizer, batch, 0, gradient_clip(cfg))
    return time.perf_counter() - t0


def self_cpu_times(events) -> dict[str, dict]:
    """Per operation name: its summed self CPU time (us) and call count, from the profiler's raw events
    (`prof.profiler.kineto_results.events()`: start and end in ns, thread ids).

    The profiler's own `key_averages()` first builds a Python object per event (~40 us each; SSRT records
    ~10^5 events a step, so over a minute per profile). The same numbers come from one sweep per thread:
    events sorted by start (the longer first on a tie) nest like brackets, and an event's self time is its
    duration less its direct children's. As in `key_averages()`, an event whose only child has its own name
    (an op re-dispatching to itself) counts as one call, and memory records, hidden events and events that
    end on another thread (asynchronous) are left out."""
    by_thread: dict[int, list[tuple[int, int, str]]] = {}
    for e in events:
        if e.device_type() != torch.autograd.DeviceType.CPU or e.is_async() or e.is_hidden_event():
            continue
        name = e.name()
        if name.startswith("[") or e.start_thread_id() != e.end_thread_id():  # [memory], [OutOfMemory]
            continue
        by_thread.setdefault(e.start_thread_id(), []).append((e.start_ns(), e.end_ns(), name))
    totals: dict[str, dict] = {}
    for spans in by_thread.values():
        spans.sort(key=lambda s: (s[0], -s[1]))
        stack: list[list] = []  # [end_ns, name, self_ns, children, the last child's name] of the open events
        for start, end, name in spans:
            while stack and stack[-1][0] <= start:
                _close(stack.pop(), totals)
            if stack:
                parent = stack[-1]
                parent[2] -= end - start
                parent[3] += 1
                parent[4] = name
            stack.append([end, name, end - start, 0, None])
        while stack:
            _close(stack.pop(), totals)
    return totals


def _close(span: list, totals: dict) -> None:
    row = totals.setdefault(span[1], {"self_us": 0.0, "count": 0})
    row["self_us"] += span[2] / 1e3
    row["count"] += 0 if span[3] == 1 and span[4] == span[1] else 1  # its only child is itself: one call


def top_operations(system, optimizer, cfg, batches, rows: int = 15) -> list[dict]:
    """The profiler's operations with the most self CPU time over a pass of `batches`."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for batch in batches:
            step(system, optimizer, batch, cfg)
    results = getattr(prof.profiler, "kineto_results", None)
    if results is not None:
        totals = self_cpu_times(results.events())
    else:  # a torch without the raw results: its own (slow) averages
        totals = {e.key: {"self_us": e.self_cpu_time_total, "count": e.count} for e in prof.key_averages()}
    total = sum(t["self_us"] for t in totals.values())
    events = sorted(totals.items(), key=lambda kv: kv[1]["self_us"], reverse=True)[:rows]
    return [
        {
            "name": name,
            "self_cpu_ms_per_step": t["self_us"] / 1e3 / len(batches),
            "share": t["self_us"] / max(total, 1),
            "calls_per_step": t["count"] / len(batches),
        }
        for name, t in events
    ]


@torch.no_grad()
def view_scores(systems, views) -> list[dict[str, list[float]]]:
    """Per system, {metric: its per-view scores on `views` (batches), in view order} for `SCORES`."""
    per = []
    for system in systems:
        system.eval()
        rows = []
        for batch in views:
            vs = [{"id": v} for v in batch["id"]]
            system.evaluate_batch(batch, vs)
            rows.extend(vs)
        per.append({m: [r[m] for r in rows if m in r] for m in SCORES})
        system.train()
    return per


def paired_over_seeds(pairs: list[tuple[dict, dict]]) -> dict:
    """Per metric: the first and last settings' means over seeds and views, and last minus first with its t
    interval over the seeds (`seed_effect`: each seed's per-view differences), each seed's mean difference.
    pairs: per seed, (first's, last's) `view_scores`. A metric some view lacks in either is left out."""
    out = {}
    for metric in SCORES:
        diffs, firsts, lasts = [], [], []
        for first, last in pairs:
            a, b = first[metric], last[metric]
            if not a or len(a) != len(b):
                break
            diffs.append([y - x for x, y in zip(a, b, strict=True)])
            firsts.append(statistics.fmean(a))
            lasts.append(statistics.fmean(b))
        else:
            effect = seed_effect(diffs)
            out[metric] = {
                "first": statistics.fmean(firsts),
                "last": statistics.fmean(lasts),
                **effect,
                "per_seed": [statistics.fmean(d) for d in diffs],
            }
    return out


def run(
    batches: int = 6,
    rounds: int = 3,
    steps: int = 60,
    test_views: int = 16,
    seed: int = 0,
    data_dir: str = "outputs/preprocess",
    overrides=(),
    pair_seeds: int = 3,
) -> dict:
    from pipeline.data.datamodules import InteriorVerseDataModule

    if pair_seeds < 1:
        raise ValueError(f"--pair-seeds {pair_seeds}: the same-results check needs at least one seed")
    dm = InteriorVerseDataModule(data_dir, batch_size=4, seed=seed, lighting=True)
    dm.setup("fit")
    dm.setup("test")
    it = iter(dm.train_dataloader())
    train = [next(it) for _ in range(batches)]
    built = [(name, *build(s, seed, list(overrides))) for name, s in SETTINGS]
    for name, system, opt, cfg in built:  # warm-up: caches filled, kernels compiled
        for batch in tqdm(train, desc=f"warm-up: {name}"):
            step(system, opt, batch, cfg)
    times = {name: [] for name, *_ in built}
    for _ in tqdm(range(rounds), desc="timed rounds"):
        for batch in train:
            for name, system, opt, cfg in built:
                times[name].append(step(system, opt, batch, cfg))
    base = statistics.median(times[SETTINGS[0][0]])
    rows = [
        {
            "setting": name,
            "median_step_s": statistics.median(t),
            "speedup": base / statistics.median(t),
            "steps_timed": len(t),
        }
        for name, t in times.items()
    ]
    profiles = {built[i][0]: top_operations(*built[i][1:4], train[:3]) for i in (0, -1)}
    views, n = [], 0
    for batch in dm.plain_loader("test"):
        views.append(batch)
        n += len(batch["im"])
        if n >= test_views:
            break
    # equal results at equal steps: per seed, fresh copies of the first and last settings, same init, same
    # batches; the seeds are the replication units (two float paths diverge like two trajectories)
    pairs = []
    for s in range(seed, seed + pair_seeds):
        pair = [build(SETTINGS[i][1], s, list(overrides)) for i in (0, -1)]
        loader = InteriorVerseDataModule(data_dir, batch_size=4, seed=s, lighting=True)
        loader.setup("fit")
        trained = 0
        bar = tqdm(total=steps, desc=f"paired training, seed {s}")
        while trained < steps:
            for batch in loader.train_dataloader():
                for system, opt, cfg in pair:
                    step(system, opt, batch, cfg)
                trained += 1
                bar.update(1)
                if trained >= steps:
                    break
        bar.close()
        pairs.append(tuple(view_scores([p[0] for p in pair], views)))
    return {
        "settings": rows,
        "profile_top_operations": profiles,
        "paired": {
            "first": SETTINGS[0][0],
            "last": SETTINGS[-1][0],
            "steps": steps,
            "test_views": n,
            "seeds": pair_seeds,
            "scores": paired_over_seeds(pairs),
        },
        "batches": batches,
        "rounds": rounds,
        "batch_size": 4,
        "overrides": list(overrides),
    }


def plot(report: dict, path) -> None:
    rows = report["settings"]
    fig = Figure(figsize=(8, 3.6))
    ax = fig.subplots()
    y = range(len(rows))
    ax.barh(y, [r["median_step_s"] * 1e3 for r in rows], color="tab:blue")
    ax.set_yticks(list(y), [r["setting"] for r in rows], fontsize=8)
    ax.invert_yaxis()
    for i, r in enumerate(rows):
        ax.text(
            r["median_step_s"] * 1e3,
            i,
            f" {r['median_step_s'] * 1e3:.0f} ms ({r['speedup']:.2f}x)",
            va="center",
            fontsize=8,
        )
    ax.set_xlabel("median LightNet training step (ms), tiny settings, batch of 4 views")
    ax.set_xlim(0, max(r["median_step_s"] for r in rows) * 1e3 * 1.35)
    pair = report["paired"]
    psnr = pair["scores"].get("render_psnr")
    if psnr is not None:
        ax.set_title(
            f"same results: after {pair['steps']} steps, {pair['last']} minus {pair['first']} on "
            f"{pair['test_views']} test views,\nre-render {psnr['diff']:+.2f} dB "
            f"[{psnr['lo']:+.2f}, {psnr['hi']:+.2f}] (95 % t interval over {pair.get('seeds', 1)} training seeds)",
            fontsize=8,
        )
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batches", type=int, default=6, help="training batches each setting steps on")
    p.add_argument("--rounds", type=int, default=3, help="timed passes over those batches")
    p.add_argument("--steps", type=int, default=60, help="steps of the paired same-results check")
    p.add_argument("--test-views", type=int, default=16)
    p.add_argument("--pair-seeds", type=int, default=3, help="training seeds of the same-results check (>= 1)")
    p.add_argument("--name", default="train_step", help="the JSON/PNG name under reports/bench")
    p.add_argument("--data-dir", default="outputs/preprocess")
    p.add_argument("--override", action="append", default=[], help="a train_lighting override (repeatable)")
    add_threads_option(p)
    a = p.parse_args(argv)
    apply_threads(a.threads)
    print(
        publish(
            a.name,
            run(
                a.batches,
                a.rounds,
                a.steps,
                a.test_views,
                data_dir=a.data_dir,
                overrides=a.override,
                pair_seeds=a.pair_seeds,
            ),
            plot,
        )
    )


if __name__ == "__main__":
    main()
