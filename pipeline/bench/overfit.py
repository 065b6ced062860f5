"""`python -m pipeline.bench.overfit`: can LightNet memorise its own training rooms?

Before a network is tuned to generalise it must fit the few rooms it is trained on; if it cannot, what
blocks it is in the model, the loss or the optimiser, not in the data. For each room count in `--rooms`
(the first n views of the training split) and each variant (`--variant NAME:override;override`, Hydra
overrides of `train_lighting`), this trains LightNet with the stage's training step on those rooms alone
(ground-truth G-buffers, so MaterialNet's errors do not count; a constant learning rate unless the
variant sets `+bench.schedule=cosine`, the stage's cosine decay to zero over the run's steps; no validation)
until the training loss plateaus: its mean over the last `--window` steps improved by less than
`--min-gain` (relative) over the `--window` steps before (checked at evaluations; a negative value
never stops), or `--max-steps`.

Every `--eval-every` steps, on the same rooms at the evaluation's settings (every probe texel, stratified
directions; re-render at the evaluation spp on the stride grid), it records per probe kind (surface,
free): the pooled normalised MSE, its energy and placement parts and each ray class's share of it
(`bench.light_energy`'s split), each class's predicted over true energy, and the re-render PSNR (dB).
With `--network material` the same for MaterialNet (`train_material`'s step and schedule-free optimiser on
the rooms alone): every map's error on those rooms over the error of the rooms' own mean (the mean
baselines of the metallic gate, fitted on the same rooms), metallic first.
With the NeRF branch, each light run also ends with its `walls`: on the miss rays of the rooms' probes,
where the volume puts its compositing weight against the true distance to the room's wall (from the room
file): the weight-averaged distance's relative error, the share of the weight within 20 % of the wall,
the volume's opacity and the far field's share. A variant with the override `+bench.room_embedding=true`
replaces the branch's image feature by a free vector per room (started at the room's image feature):
whether the image encoder is what keeps the NeRF from memorising; `+bench.room_textures=true` does the
same for the room-box branch's decoded textures (a free texture table per room), and
`+bench.true_layout=true` gives the room-box branch each room's true box. `+bench.head_rates=fan_in`
gives the weight of each hypernetwork head's last layer the stage's rate over its fan-in (its bias keeps
the rate): Adam moves every weight by about the rate per step, so a generated parameter, a sum over the
head's fan-in, moves by the rate times that fan-in's mean activation instead of by about the rate.
Writes reports/bench/overfit.json (or `--name`) and a PNG of those curves against steps.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from matplotlib.figure import Figure
from omegaconf import OmegaConf
from tqdm import tqdm

from pipeline.bench.common import (
    add_threads_option,
    apply_threads,
    gradient_clip,
    optimiser_step,
    publish,
    training_system,
)
from pipeline.bench.light_energy import class_parts, tally_batches

KINDS = ("surf", "free")
NETWORKS = ("light", "material")


def parse_variant(text: str) -> tuple[str, list[str]]:
    """'name:a=1;b=2' -> ('name', ['a=1', 'b=2']); 'name' alone: no overrides."""
    name, _, rest = text.partition(":")
    if not name:
        raise ValueError(f"--variant {text!r}: give a name before ':'")
    return name, [o for o in rest.split(";") if o.strip()]


MATERIAL_MAPS = ("metallic_mse", "roughness_mse", "albedo_mse")  # each against mean_material / mean_albedo


@torch.no_grad()
def evaluate_material(system, plain) -> dict:
    """Each map's mean error over the rooms and over the rooms' own mean baseline (their ratio)."""
    from pipeline.metrics.synthetic import material_metrics
    from pipeline.systems.material_baselines import MaterialBaselines

    system.eval()
    baselines = MaterialBaselines.fit(plain)
    sums: dict[str, float] = {}
    for batch in plain:
        per = material_metrics(system.net(batch["im"]), batch)
        per.update(baselines.metrics(batch))
        for k, v in per.items():
            v = v[torch.isfinite(v)]
            sums[k] = sums.get(k, 0.0) + float(v.sum())
    system.train()
    out = {}
    for metric in MATERIAL_MAPS:
        base = "mean_albedo" if metric == "albedo_mse" else "mean_material"
        out[metric] = {
            "model": sums[metric],
            "mean_baseline": sums[f"{base}/{metric}"],
            "ratio": sums[metric] / max(sums[f"{base}/{metric}"], 1e-12),
        }
    return out


def rooms_batches(data_dir: str, rooms: int, batch_size: int, lighting: bool = True):
    """The first `rooms` training views as a shuffling loader (seeded) and as plain batches."""
    from torch.utils.data import DataLoader, Subset

    from pipeline.data.datasets import ShardDataset, collate_views

    train = ShardDataset(data_dir, "train", lighting=lighting)
    if rooms > len(train):
        raise ValueError(f"--rooms {rooms}: the training split of {data_dir} has {len(train)} views")
    subset = Subset(train, range(rooms))
    bs = min(batch_size, rooms)
    loader = DataLoader(
        subset, bs, shuffle=True, generator=torch.Generator().manual_seed(0), collate_fn=collate_views, drop_last=True
    )
    plain = list(DataLoader(subset, 4, shuffle=False, collate_fn=collate_views))
    return loader, plain


@torch.no_grad()
def evaluate(system, plain) -> dict:
    """Light-error split per kind and the mean re-render PSNR (dB) over the rooms."""
    system.eval()
    out = {}
    for kind, t in tally_batches(system, plain).items():
        if not t.sums:
            continue
        s = t.summary()
        out[kind] = {
            "nmse": s["nmse"]["lightnet"],
            "oracle_nmse": s["nmse"]["probe_mean_oracle"],
            "energy_part": s["lightnet_energy_part"],
            "placement_part": s["lightnet_placement_part"],
            "classes": class_parts(s),
        }
    psnr = [system.evaluate_batch(b)["render_psnr"] for b in plain]
    out["render_psnr"] = sum(psnr) / len(psnr)
    system.train()
    return out


def image_keys(images) -> list[float]:
    """One key per image (N, 3, H, W): its sum, which tells the bench's fixed training rooms apart."""
    return [float(x.double().sum()) for x in images]


def room_index(keys: list[float], images) -> list[int]:
    """The positions in `keys` of images (B, 3, H, W) (`image_keys`)."""
    return [keys.index(k) for k in image_keys(images)]


@torch.no_grad()
def wall_agreement(system, plain, source_root: Path) -> dict | None:
    """Where the NeRF branch's volume puts its weight on the miss rays of the rooms' probe texels (one
    direction per texel, its centre) against the true distance t_wall to the room's box: the median of
    |E_w[t] - t_wall| / t_wall (E_w the compositing-weight average, rays with opacity >= 0.05), the mean
    share of the weight within 20 % of t_wall, the mean opacity and the mean far-field share (the
    transmittance left). None for a branch that is not a NeRF."""
    from pipeline.bench.roombox_floor import true_box
    from pipeline.data.lighting import probe_rays
    from pipeline.models.light_net import trace_views
    from pipeline.models.light_net.branches import OutOfViewBranch
    from pipeline.ops.roombox import exit_face

    net = system.net
    if not isinstance(net.out_of_view, OutOfViewBranch):
        return None
    system.eval()
    rel, near, opacity, left = [], [], [], []
    for batch in plain:
        fov = system.fov(batch)
        gb = system.gbuffers(batch)
        ctx = net.encode(batch["im"], gb["depth"], fov, normal=gb["normal"])
        boxes = [true_box(source_root, v) for v in batch["id"]]
        for kind in KINDS:
            rays = probe_rays(batch["light"], kind, strata=1)
            if rays is None:
                continue
            o, d, b = rays.origin, rays.direction[:, 0], rays.image
            _, hit, _ = trace_views(gb, fov, o, d, b)
            o, d, b = o[~hit], d[~hit], b[~hit]
            if not len(b):
                continue
            out = net.out_of_view.query(
                ctx["feature"],
                ctx["params"],
                ctx["unit"],
                ctx.get("bounds"),
                b,
                o,
                d,
                depth_max=ctx.get("depth_max"),
                details=True,
            )
            rot = torch.stack([boxes[i][0] for i in b.tolist()]).float()
            lo = torch.stack([boxes[i][1] for i in b.tolist()]).float()
            hi = torch.stack([boxes[i][2] for i in b.tolist()]).float()
            q, dq = (o.unsqueeze(1) @ rot)[:, 0], (d.unsqueeze(1) @ rot)[:, 0]
            _, _, t_wall = exit_face(q, dq, lo, hi)
            w, t = out["weights"], out["t"]
            mass = w.sum(1)
            mean_t = (w * t).sum(1) / mass.clamp(min=1e-9)
            ok = mass >= 0.05
            rel.append(((mean_t - t_wall).abs() / t_wall.clamp(min=1e-3))[ok])
            within = ((t - t_wall[:, None]).abs() <= 0.2 * t_wall[:, None]).to(w.dtype)
            near.append((w * within).sum(1) / mass.clamp(min=1e-9))
            opacity.append(mass)
            left.append(out["left"])
    system.train()
    if not rel:
        return None
    rel, near, opacity, left = (torch.cat(x) for x in (rel, near, opacity, left))
    return {
        "miss_rays": int(len(opacity)),
        "depth_relative_error_median": float(rel.median()) if len(rel) else None,
        "weight_within_20pc_of_wall": float(near.mean()),
        "opacity_mean": float(opacity.mean()),
        "far_field_share_mean": float(left.mean()),
    }


def use_room_embedding(system, optimizer, plain) -> None:
    """Suspect 5: the out-of-view branch's image feature replaced by a free vector per training room,
    each started at its room's image feature and trained with the branch (a param group of the stage's
    optimiser). Rooms are told apart by their images' sums (the bench's rooms are fixed)."""
    branch = system.net.out_of_view
    images = torch.cat([b["im"] for b in plain])
    keys = image_keys(images)
    if len(set(keys)) != len(keys):
        raise ValueError("+bench.room_embedding: two training rooms have the same image sum")
    with torch.no_grad():
        start, _ = branch.encode(images)
    table = torch.nn.Parameter(start.clone())
    branch.register_parameter("room_table", table)
    optimizer.add_param_group({"params": [table]})

    def encode(im, normalise=True):
        index = torch.tensor(room_index(keys, im))
        feature = table[index]
        return feature, branch.hyper(feature)

    branch.encode = encode


HEAD_RATES = ("fan_in",)


def use_head_rates(system, optimizer, rule: str) -> dict:
    """Suspect 1, per group: each hypernetwork head's last Linear weight (the NeRF branch's `hyper`) moved
    to a param group of its own at the stage's rate over its fan-in (`rule` fan_in); every other parameter
    keeps its group. Returns {group name: rate} for the report."""
    from pipeline.models.light_net.hyper import HyperMLP

    if rule not in HEAD_RATES:
        raise ValueError(f"+bench.head_rates={rule!r}: choose one of {list(HEAD_RATES)}")
    hyper = getattr(system.net.out_of_view, "hyper", None)
    if not isinstance(hyper, HyperMLP):
        raise ValueError("+bench.head_rates: the out-of-view branch has no hypernetwork (kind: nerf only)")
    heads = [*hyper.heads, *(hyper.bias_heads if hyper.split_bias else [])]
    lasts = [h[-1] if isinstance(h, torch.nn.Sequential) else h for h in heads]
    moved = {id(last.weight) for last in lasts}
    base = optimizer.param_groups[0]
    rates = {}
    for group in optimizer.param_groups:
        group["params"] = [q for q in group["params"] if id(q) not in moved]
    for k, last in enumerate(lasts):
        rate = base["lr"] / last.in_features
        optimizer.add_param_group({"params": [last.weight], "lr": rate})
        rates[f"head {k} weight ({last.in_features} in)"] = rate
    return rates


def use_true_layout(system, plain, data_dir) -> None:
    """The room-box branch given each training room's true box (from its room file, `layout: gt`) instead
    of the one it estimates from the depth and normals: whether the box estimate limits memorising."""
    from pipeline.bench.roombox_floor import true_box

    branch = system.net.out_of_view
    ids = [v for b in plain for v in b["id"]]
    keys = image_keys(torch.cat([b["im"] for b in plain]))
    boxes = [true_box(source_root(data_dir), v) for v in ids]
    encode = branch.encode

    def with_box(im, unit, depth, fov_x, normal=None, normalise=True, box=None):
        index = room_index(keys, im)
        box = tuple(torch.stack([boxes[i][k] for i in index]).to(im.dtype) for k in range(3))
        return encode(im, unit, depth, fov_x, normal, normalise, box)

    branch.encode = with_box


TABLE_LR = 0.05  # the free texture table's learning rate (bench.roombox_floor's)


def use_room_textures(system, optimizer, plain) -> None:
    """The room-box branch's face textures replaced by a free table per training room (log radiance and
    opacity logit per texel, started at the room's textures), trained with the stage's optimiser (the
    table at `TABLE_LR`) and loss: whether the texture decoder or the supervision limits memorising."""
    branch = system.net.out_of_view
    images = torch.cat([b["im"] for b in plain])
    keys = image_keys(images)
    if len(set(keys)) != len(keys):
        raise ValueError("+bench.room_textures: two training rooms have the same image sum")
    encode = branch.encode
    with torch.no_grad():
        rooms = []
        for b in plain:
            gb = system.gbuffers(b)
            rooms.append(system.net.encode(b["im"], gb["depth"], system.fov(b), normal=gb["normal"])["room"])
        tex = torch.cat([r["textures"] for r in rooms])
        start = torch.cat([tex[:, :, :3].clamp(min=1e-6).log(), torch.logit(tex[:, :, 3:].clamp(1e-4, 1 - 1e-4))], 2)
    table = torch.nn.Parameter(start)
    branch.register_parameter("room_table", table)
    # log radiance moves by several units from one image mean to a lamp: at the stage's 1e-3 a free
    # table would need thousands of steps, so it gets the rate the floor test fits textures with
    optimizer.add_param_group({"params": [table], "lr": TABLE_LR})

    def free(im, unit, *args, **kwargs):
        room = encode(im, unit, *args, **kwargs)
        index = torch.tensor(room_index(keys, im))
        t = table[index]
        return {**room, "textures": torch.cat([torch.exp(t[:, :, :3].clamp(max=12.0)), torch.sigmoid(t[:, :, 3:])], 2)}

    branch.encode = free


def plateaued(losses: list[float], window: int, min_gain: float) -> bool:
    """Whether the mean loss of the last `window` steps is less than `min_gain` (relative) below the mean
    of the `window` steps before (False until there are 2 windows; a negative min_gain never stops)."""
    if len(losses) < 2 * window or min_gain < 0:
        return False
    recent = sum(losses[-window:]) / window
    before = sum(losses[-2 * window : -window]) / window
    return before - recent < min_gain * abs(before)


def train_to_plateau(
    system,
    optimizer,
    loader,
    plain,
    max_steps,
    eval_every,
    window,
    min_gain,
    label,
    score=evaluate,
    clip=0.0,
    scheduler=None,
) -> dict:
    """Steps of the stage's optimiser (`optimiser_step`, gradients clipped at `clip` as the stage clips them)
    until `max_steps` or a plateau of the loss; `score` on `plain` every `eval_every` steps and at the end.
    `scheduler` (None: a constant rate) is stepped after every optimiser step."""
    losses, curve = [], []
    step, t0, stop = 0, time.perf_counter(), "max_steps"
    system.train()
    bar = tqdm(total=max_steps, desc=label)
    while step < max_steps:
        for batch in loader:
            if step % eval_every == 0:
                curve.append({"step": step, "seconds": time.perf_counter() - t0, **score(system, plain)})
            losses.append(optimiser_step(system, optimizer, batch, step, clip))
            if scheduler is not None:
                scheduler.step()
            step += 1
            bar.update(1)
            if step % eval_every == 0 and plateaued(losses, window, min_gain):
                stop = "plateau"
                break
            if step >= max_steps:
                break
        if stop == "plateau":
            break
    bar.close()
    curve.append({"step": step, "seconds": time.perf_counter() - t0, **score(system, plain)})
    return {"steps": step, "stopped_by": stop, "seconds": time.perf_counter() - t0, "loss": losses, "curve": curve}


SCHEDULES = ("constant", "cosine")


def step_schedule(optimizer, kind, max_steps: int):
    """The learning-rate schedule of a run (`+bench.schedule`): None for `constant` (or unset); for `cosine`
    the stage's cosine decay to zero (conf/optim/adamw.yaml, there over its epochs) over the run's
    `max_steps`, every parameter group from its own rate."""
    if kind in (None, "constant"):
        return None
    if kind not in SCHEDULES:
        raise ValueError(f"+bench.schedule={kind!r}: choose one of {SCHEDULES}")
    return torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=max_steps)


def source_root(data_dir) -> Path:
    """Where the shards' views were rendered (their manifest's `source_root`: the room files)."""
    return Path(json.loads((Path(data_dir) / "manifest.json").read_text())["source_root"])


def run(
    rooms=(1, 8, 64),
    variants=(("default", []),),
    data_dir="outputs/preprocess",
    max_steps=600,
    eval_every=50,
    window=50,
    min_gain=0.02,
    seed=0,
    network: str = "light",
    on_run=None,
) -> dict:
    """Every variant on every room count (module docstring); on_run(report) after each run (the JSON
    written so far, so a long bench that stops keeps the runs it finished)."""
    if network not in NETWORKS:
        raise ValueError(f"--network {network!r}: choose one of {NETWORKS}")
    report = {
        "network": network,
        "rooms": list(rooms),
        "max_steps": max_steps,
        "eval_every": eval_every,
        "window": window,
        "min_gain": min_gain,
        "seed": seed,
        "runs": [],
    }
    if network == "light":
        report["gbuffers"] = "ground_truth"
    for name, overrides in variants:
        for n in rooms:
            extra = {}
            if network == "light":
                system, optimizer, cfg = training_system("train_lighting", ["gbuffers=ground_truth", *overrides], seed)
                loader, plain = rooms_batches(data_dir, n, int(cfg.batch_size))
                score = evaluate
                if OmegaConf.select(cfg, "bench.room_embedding"):
                    use_room_embedding(system, optimizer, plain)
                if OmegaConf.select(cfg, "bench.true_layout"):
                    use_true_layout(system, plain, data_dir)
                if OmegaConf.select(cfg, "bench.room_textures"):
                    use_room_textures(system, optimizer, plain)
                if OmegaConf.select(cfg, "bench.head_rates"):
                    extra["head_rates"] = use_head_rates(system, optimizer, str(cfg.bench.head_rates))
            else:
                system, optimizer, cfg = training_system("train_material", overrides, seed)
                loader, plain = rooms_batches(data_dir, n, int(cfg.batch_size), lighting=False)
                score = evaluate_material
            clip = gradient_clip(cfg)  # the stage's: a bench without it measures another optimiser
            scheduler = step_schedule(optimizer, OmegaConf.select(cfg, "bench.schedule"), max_steps)
            extra["schedule"] = OmegaConf.select(cfg, "bench.schedule") or "constant"
            label = f"{name}, {n} rooms"
            row = train_to_plateau(
                system, optimizer, loader, plain, max_steps, eval_every, window, min_gain, label, score, clip, scheduler
            )
            if network == "light":
                row["walls"] = wall_agreement(system, plain, source_root(data_dir))
            report["runs"].append({"variant": name, "overrides": overrides, "rooms": n, "clip": clip, **extra, **row})
            if on_run is not None:
                on_run(report)
    return report


def plot(report: dict, path) -> None:
    """Per run (variant x rooms), against training steps: surface and free nMSE, their energy parts, the
    miss class's share, and the re-render PSNR (dB); for MaterialNet each map's error over its mean
    baseline's."""
    if report.get("network") == "material":
        return plot_material(report, path)
    panels = [
        ("surface probes: nMSE", lambda c: c["surf"]["nmse"]),
        ("surface: energy part", lambda c: c["surf"]["energy_part"]),
        ("free points: nMSE", lambda c: c.get("free", {}).get("nmse", float("nan"))),
        (
            "surface: predicted/true energy on misses",
            lambda c: c["surf"]["classes"]["miss"]["predicted_over_true_energy"] or float("nan"),
        ),
        ("re-render PSNR on GT G-buffers (dB)", lambda c: c["render_psnr"]),
        ("training loss", None),
    ]
    fig = Figure(figsize=(13, 7.5))
    axes = fig.subplots(2, 3).ravel()
    for ax, (title, get) in zip(axes, panels, strict=True):
        for r in report["runs"]:
            label = f"{r['variant']}, {r['rooms']} rooms"
            if get is None:
                loss = torch.tensor(r["loss"])
                k = max(1, min(25, len(loss) // 4))
                smooth = torch.nn.functional.avg_pool1d(loss[None, None], k, 1)[0, 0] if len(loss) >= k else loss
                ax.plot(range(k - 1, k - 1 + len(smooth)), smooth.tolist(), label=label)
                ax.set_yscale("log")
            else:
                ax.plot([c["step"] for c in r["curve"]], [get(c) for c in r["curve"]], marker=".", label=label)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("training step")
    axes[0].axhline(0.3, color="k", lw=0.6, ls="--")
    axes[1].axhline(0.01, color="k", lw=0.6, ls="--")
    axes[3].axhline(1.0, color="k", lw=0.6, ls="--")
    axes[0].legend(fontsize=6)
    fig.suptitle("LightNet memorising its training rooms (evaluated on those rooms; dashed: targets)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def plot_material(report: dict, path) -> None:
    fig = Figure(figsize=(13, 3.8))
    axes = fig.subplots(1, len(MATERIAL_MAPS) + 1)
    for ax, metric in zip(axes, MATERIAL_MAPS, strict=False):
        for r in report["runs"]:
            ax.plot(
                [c["step"] for c in r["curve"]],
                [c[metric]["ratio"] for c in r["curve"]],
                marker=".",
                label=f"{r['variant']}, {r['rooms']} rooms",
            )
        ax.axhline(0.2 if metric == "metallic_mse" else 1.0, color="k", lw=0.6, ls="--")
        ax.set_yscale("log")
        ax.set_title(f"{metric}: model / the rooms' mean (log)", fontsize=9)
        ax.set_xlabel("training step")
    ax = axes[-1]
    for r in report["runs"]:
        ax.plot(r["loss"], lw=0.5)
    ax.set_yscale("log")
    ax.set_title("training loss", fontsize=9)
    ax.set_xlabel("training step")
    axes[0].legend(fontsize=6)
    fig.suptitle("MaterialNet memorising its training rooms (dashed: metallic target 0.2, else the mean)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--network", default="light", choices=NETWORKS)
    p.add_argument("--rooms", type=int, nargs="+", default=[1, 8, 64])
    p.add_argument("--variant", action="append", default=None, help="NAME:override;override (repeatable)")
    p.add_argument("--data-dir", default="outputs/preprocess")
    p.add_argument("--max-steps", type=int, default=600)
    p.add_argument("--eval-every", type=int, default=50)
    p.add_argument("--window", type=int, default=50)
    p.add_argument("--min-gain", type=float, default=0.02)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--name", default="overfit", help="the JSON/PNG name under reports/bench")
    add_threads_option(p)
    a = p.parse_args(argv)
    apply_threads(a.threads)
    variants = [parse_variant(v) for v in (a.variant or ["default"])]
    report = run(
        a.rooms,
        variants,
        a.data_dir,
        a.max_steps,
        a.eval_every,
        a.window,
        a.min_gain,
        a.seed,
        a.network,
        on_run=lambda partial: publish(a.name, partial, plot),
    )
    print(publish(a.name, report, plot))


if __name__ == "__main__":
    main()
