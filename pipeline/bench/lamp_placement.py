"""`python -m pipeline.bench.lamp_placement`: can the photo tell where the room's lamps are?

`bench.visible_light` found the held-out light error to be the placement of the ceiling lamps: knowing
them takes the test views' surface nMSE from the trained branch's 0.88 to 0.35. This bench asks whether
a network learns that placement from the photo. Each view's target is the ceiling of its true box
(`bench.roombox_floor.true_box`, in the canonical frame: columns along view x, rows along view z) cut
into `--grid` x `--grid` cells, each holding the lamps' emitted luminance times the share of the cell
they cover (`ceiling_lamps`). A small CNN (`PlacementNet`) maps the photo (log of its radiance over its
mean, `--size` pixels high) to a distribution over the cells, trained on the training split with the
cross-entropy to the target's distribution (left-right mirrored views as augmentation; the epoch with the
lowest cross-entropy on the validation split kept), and is scored on
the test split against two priors that see no photo: uniform over the ceiling, and the training rooms'
mean placement (each placement's light error minus the mean placement's, paired by view, with a
bootstrap interval over the test views). Scores: the cross-entropy, the predicted share on the cells
that hold a lamp, and the light: every rule blends as tiny's LightNet does with the image's pixel as the
local source, on ground-truth G-buffers (`bench.visible_light`), and each out-of-view direction that leaves the true box
through the ceiling takes its cell's lamp radiance under the placement (the view's true lamp total
spread by the placement's distribution: energy is given, placement is scored) plus the photo's mean;
every other direction the photo's mean. `true lamps` (exact panels) and `true placement` (the target
cells) bound it from below. With `--curve 0,N1,N2`, one network per seed is trained on the training split
plus the first N of `bench.lamp_rooms`' extra rooms (photo-only rooms of the stage's generator and renderer,
cached in `--extra-dir`), each paired with the same seed's network without them: does the photo place the
lamps better with more rooms? Writes reports/bench/lamp_placement.json (or `--name`) and a PNG.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure
from matplotlib.ticker import NullFormatter
from torch import nn
from torch.nn import functional as F
from tqdm import tqdm

from pipeline.bench.blend_floor import KINDS, blended, ground_truth_gbuffers, kind_scores, score_directions, view_rays
from pipeline.bench.common import add_threads_option, apply_threads, publish
from pipeline.bench.lamp_rooms import photo_input
from pipeline.bench.light_energy import EnergyTally
from pipeline.bench.roombox_floor import true_box
from pipeline.bench.visible_light import THRESHOLD, K, box_texels, lamp_radiance, room_lamps

CEILING = 3  # face index of the box's ceiling (ops.roombox.FACES)
SUB = 4  # sub-points per cell side when measuring a lamp's cover


def ceiling_lamps(lamps: dict | None, box, grid: int) -> torch.Tensor:
    """(grid, grid, 3) radiance of the true lamps averaged over each cell of the box's ceiling (rows t
    along the box's z, columns s along its x, as `ops.roombox` lays a ceiling texture out), float64."""
    out = torch.zeros(grid, grid, 3, dtype=torch.float64)
    if lamps is None:
        return out
    rot, lo, hi = (t.double() for t in box)
    n = grid * SUB
    x = lo[0] + (torch.arange(n, dtype=torch.float64) + 0.5) / n * (hi[0] - lo[0])
    z = lo[2] + (torch.arange(n, dtype=torch.float64) + 0.5) / n * (hi[2] - lo[2])
    zz, xx = torch.meshgrid(z, x, indexing="ij")
    q = torch.stack([xx, torch.full_like(xx, float(hi[1])), zz], -1).reshape(-1, 3)
    p = q @ rot.T  # view space
    d = p - lamps["centre"][:, None]  # (L, P, 3)
    a = (d * lamps["u"][:, None]).sum(-1) / (lamps["u"] ** 2).sum(-1)[:, None]
    b = (d * lamps["v"][:, None]).sum(-1) / (lamps["v"] ** 2).sum(-1)[:, None]
    inside = ((a.abs() <= 1) & (b.abs() <= 1)).double()  # (L, P)
    radiance = (inside[..., None] * lamps["emission"][:, None]).sum(0).view(grid, SUB, grid, SUB, 3)
    return radiance.mean((1, 3))


def luminance(rgb: torch.Tensor) -> torch.Tensor:
    return rgb @ torch.tensor([0.2126, 0.7152, 0.0722], dtype=rgb.dtype)


NETS = ("small", "deep")
TEMPERATURES = torch.exp(torch.linspace(math.log(0.25), math.log(16.0), 49))  # the calibration's grid


class PlacementNet(nn.Module):
    """Photo (B, 3, H, W), log radiance over its mean -> logits (B, grid * grid) over the ceiling's cells;
    with `extra` > 0, that many more features per view (B, extra) join the pooled ones before the head.
    `kind`: `small`, three strided convolutions of `width // 2`, `width`, `width` channels; `deep`, six
    batch-normalised ones of `width // 2` (twice), `width` (twice) and `2 width` (twice) channels, four
    of them strided. Either is pooled to 4 x 5 (it keeps where in the photo) before a linear head. The
    logits are divided by the buffer `temperature` (1 until `calibrate` sets it)."""

    def __init__(self, grid: int, width: int = 32, extra: int = 0, kind: str = "small"):
        super().__init__()
        if kind == "small":
            layers = [(width // 2, 2), (width, 2), (width, 2)]
        elif kind == "deep":
            layers = [(width // 2, 1), (width // 2, 2), (width, 2), (width, 2), (2 * width, 2), (2 * width, 1)]
        else:
            raise ValueError(f"--net {kind!r}: one of {', '.join(NETS)}")
        convs, channels = [], 3
        for out, stride in layers:
            convs.append(nn.Conv2d(channels, out, 3, stride, 1))
            if kind == "deep":
                convs.append(nn.BatchNorm2d(out))
            convs.append(nn.ReLU())
            channels = out
        self.features = nn.Sequential(*convs, nn.AdaptiveAvgPool2d((4, 5)))
        self.head = nn.Linear(channels * 20 + extra, grid * grid)
        self.register_buffer("temperature", torch.ones(()))

    def forward(self, x: torch.Tensor, extra: torch.Tensor | None = None) -> torch.Tensor:
        pooled = self.features(x).flatten(1)
        return self.head(pooled if extra is None else torch.cat([pooled, extra], 1)) / self.temperature


def soft_cross_entropy(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean over views of the cross-entropy (nats) of softmax(logits) (N, C) to distributions target (N, C)."""
    return -(target * F.log_softmax(logits, -1)).sum(1).mean()


def calibrated_cross_entropy(logits: torch.Tensor, target: torch.Tensor) -> tuple[float, float]:
    """The lowest mean cross-entropy of softmax(logits / T) to the distributions target over the
    temperatures T of `TEMPERATURES`, and that T: a net that ranks the cells well but is overconfident
    is not charged for the confidence, which one scalar on validation views corrects."""
    scores = torch.stack([soft_cross_entropy(logits / t, target) for t in TEMPERATURES])
    best = int(torch.argmin(scores))
    return float(scores[best]), float(TEMPERATURES[best])


def split_targets(data, source_root: Path, grid: int, height: int):
    """Inputs (N, 3, h, w) and target cell radiance (N, grid, grid, 3) of every view of a dataset."""
    xs, ys = [], []
    for i in tqdm(range(len(data)), desc="targets"):
        item = data[i]
        box = true_box(source_root, item["id"])
        ys.append(ceiling_lamps(room_lamps(source_root, item["id"]), box, grid))
        xs.append(photo_input(item["im"], height))
    return torch.stack(xs), torch.stack(ys)


def room_targets(records: list[dict], grid: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Inputs (N, 3, h, w) float32 and the ceiling lamps' radiance per cell (N, grid, grid, 3) of the
    records of `bench.lamp_rooms`, as `split_targets` reads them for the stage's views."""
    from pipeline.bench.visible_light import lamps_in_view
    from pipeline.ops.roombox import box_from_room

    xs, ys = [], []
    for r in records:
        box = box_from_room(r["room"]["size"], r["world_from_view"])
        ys.append(ceiling_lamps(lamps_in_view(r["room"], r["world_from_view"]), box, grid))
        xs.append(r["x"].float())
    return torch.stack(xs), torch.stack(ys)


def distribution(cells: torch.Tensor) -> torch.Tensor:
    """(N, grid, grid, 3) cell radiance -> (N, grid * grid) share of the lamps' luminance (uniform where none)."""
    w = luminance(cells).flatten(1)
    total = w.sum(1, keepdim=True)
    return torch.where(total > 0, w / total.clamp(min=1e-12), torch.full_like(w, 1 / w.shape[1]))


def mirrored_cells(cells: torch.Tensor, grid: int) -> torch.Tensor:
    """Per-cell values (N, k * grid * grid) of k ceiling maps, each mirrored left-right (view x <-> box x)."""
    return cells.view(len(cells), -1, grid, grid).flip(-1).reshape(len(cells), -1)


def train(
    x,
    target,
    x_val,
    target_val,
    grid: int,
    epochs: int,
    seed: int,
    extra=None,
    extra_val=None,
    width: int = 32,
    patience: int | None = None,
    kind: str = "small",
    calibrate: bool = False,
) -> tuple[PlacementNet, list[float]]:
    """PlacementNet fitted to distributions target (N, grid * grid), mirrored views included; the epoch
    whose validation cross-entropy is lowest is kept (252 rooms overfit long before the last epoch).
    `extra` (N, k * grid * grid), `extra_val`: k more ceiling maps per view as input beside the photo
    (mirrored with it). `width`, `kind`: the net's (`PlacementNet`). `patience`: stop after that many
    epochs without a lower validation cross-entropy (None: every epoch). `calibrate`: each epoch is judged
    at its best temperature (`calibrated_cross_entropy`), which the kept net carries. Returns the net and
    the validation cross-entropy after each epoch run."""
    import copy

    torch.manual_seed(seed)
    net = PlacementNet(grid, width, extra=0 if extra is None else extra.shape[1], kind=kind)
    opt = torch.optim.AdamW(net.parameters(), lr=1e-3, weight_decay=1e-4)
    xs, ts = torch.cat([x, x.flip(-1)]), torch.cat([target, mirrored_cells(target, grid)])
    es = None if extra is None else torch.cat([extra, mirrored_cells(extra, grid)]).float()
    g = torch.Generator().manual_seed(seed)
    best, best_state, curve = math.inf, copy.deepcopy(net.state_dict()), []
    for _ in tqdm(range(epochs), desc="placement net"):
        net.train()
        for idx in torch.randperm(len(xs), generator=g).split(16):
            logits = net(xs[idx], None if es is None else es[idx])
            loss = soft_cross_entropy(logits, ts[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
        net.eval()
        with torch.no_grad():
            logits = net(x_val, None if extra_val is None else extra_val.float())
            if calibrate:
                score, temperature = calibrated_cross_entropy(logits, target_val)
            else:
                score, temperature = float(soft_cross_entropy(logits, target_val)), 1.0
        curve.append(score)
        if curve[-1] < best:
            best, best_state = curve[-1], copy.deepcopy(net.state_dict())
            best_state["temperature"] = torch.tensor(temperature)
        elif patience is not None and len(curve) - 1 - int(np.argmin(curve)) >= patience:
            break
    net.load_state_dict(best_state)
    return net.eval(), curve


def placement_scores(pred: torch.Tensor, target: torch.Tensor) -> dict:
    """Mean cross-entropy (nats) and mean predicted share on the cells holding a lamp, over views."""
    ce = -(target * pred.clamp(min=1e-12).log()).sum(1)
    on_lamps = (pred * (target > 0)).sum(1)
    return {"cross_entropy": float(ce.mean()), "share_on_lamp_cells": float(on_lamps.mean())}


@torch.no_grad()
def light_scores(
    test, source_root: Path, grid: int, placements: dict, extra_names: tuple = (), extra_sources=None, boxes=None
) -> tuple[dict, dict]:
    """Per placement (name -> (N, grid * grid) distributions over the test views, or (N, grid * grid, 3)
    radiance per cell), the surface and free nMSE and class parts of the light with the lamps' radiance
    spread by that placement (module docstring; a radiance placement stands for itself),
    and per kind the test views' summed squared errors and energies (for `paired_differences`).
    `extra_sources(i, batch, gb, r)`, when given, returns more out-of-view sources (name in `extra_names`
    -> (M S, 3)) at the directions r of `view_rays` of test view i, scored alike. `boxes`: per test view
    the box whose ceiling cells the placements refer to (default: the true box)."""
    from torch.utils.data import DataLoader

    from pipeline.data.datasets import collate_views

    names = ["true lamps", "true placement", *placements, *extra_names]
    tallies = {name: {k: EnergyTally() for k in KINDS} for name in names}
    per_view = {k: {"energy": [], **{name: [] for name in names}} for k in KINDS}  # summed squares per view
    loader = DataLoader(test, 1, collate_fn=collate_views)
    for i, batch in enumerate(tqdm(loader, total=len(test), desc="light (test)")):
        view_id = batch["id"][0]
        box = true_box(source_root, view_id) if boxes is None else boxes[i]
        lamps = room_lamps(source_root, view_id)
        cells = ceiling_lamps(lamps, box, grid)
        total = cells.reshape(-1, 3).sum(0)  # the lamps' radiance summed over cells: spread by a placement
        gb = ground_truth_gbuffers(batch)
        image_mean = batch["im"][0].double().clamp(min=0).mean((1, 2))
        for kind in KINDS:
            r = view_rays(batch, gb, kind)
            if r is None:
                continue
            index = box_texels(box, r["origin"], r["direction"], grid)
            ceiling = (index // (grid * grid)) == CEILING
            cell = index % (grid * grid)
            rest = image_mean.expand(len(index), 3)
            out = {}
            if lamps is not None:
                glow, met = lamp_radiance(lamps, r["origin"], r["direction"])
                out["true lamps"] = torch.where(met[:, None], glow, rest)
            else:
                out["true lamps"] = rest
            out["true placement"] = torch.where(ceiling[:, None], cells.reshape(-1, 3)[cell] + rest, rest)
            for name, placed in placements.items():
                if placed.dim() == 3:  # the placement's own radiance per cell
                    spread = placed[i].double()
                else:  # a distribution: the true lamp total spread by it
                    spread = placed[i][:, None].double() * total[None]  # (grid * grid, 3)
                out[name] = torch.where(ceiling[:, None], spread[cell] + rest, rest)
            if extra_sources is not None:
                out.update(extra_sources(i, batch, gb, r))
            per_view[kind]["energy"].append(float((r["truth"] ** 2).sum()))
            for name, o in out.items():
                pred = blended(r["local"], o, r["hit"], r["gap"], K, THRESHOLD)
                texels = score_directions(tallies[name][kind], r, pred)
                per_view[kind][name].append(float(((texels - r["truth"]) ** 2).sum()))
    return {name: kind_scores(by_kind) for name, by_kind in tallies.items()}, per_view


def paired_differences(per_view: dict, reference: str) -> dict:
    """Per probe kind, each placement's pooled nMSE minus the reference's, paired by test view, with a
    95 % bootstrap interval over views: mean(error_a - error_ref) / mean(energy) (`ratio_bootstrap`)."""
    names = [n for n in next(iter(per_view.values())) if n not in ("energy", reference)] if per_view else []
    return paired_pairs(per_view, [(name, reference) for name in names])


def paired_pairs(per_view: dict, pairs: list[tuple[str, str]]) -> dict:
    """`paired_differences` for the given (placement, reference) pairs only."""
    from pipeline.metrics.bootstrap import ratio_bootstrap

    out = {}
    for kind, cols in per_view.items():
        if not cols["energy"]:
            continue
        for name, reference in pairs:
            b = ratio_bootstrap(np.asarray(cols[name]) - np.asarray(cols[reference]), cols["energy"])
            out[f"{kind}: {name} - {reference}"] = {"diff": b["ratio"], "lo": b["lo"], "hi": b["hi"], "views": b["n"]}
    return out


def placement_summary(report: dict, differences_title: str) -> dict:
    """The page's tables of a placement report: each row's light errors and placement scores (from its
    `light` and `placement`), and its paired `differences` under `differences_title`."""
    return {
        "each placement": [
            {
                "placement": name,
                "surface nMSE": row.get("surf", {}).get("nmse"),
                "free nMSE": row.get("free", {}).get("nmse"),
                "cross-entropy (nats)": report["placement"].get(name, {}).get("cross_entropy"),
                "share on lamp cells": report["placement"].get(name, {}).get("share_on_lamp_cells"),
            }
            for name, row in report["light"].items()
        ],
        differences_title: [
            {"difference": name, "nMSE": d["diff"], "lo": d["lo"], "hi": d["hi"]}
            for name, d in report["differences"].items()
        ],
    }


def photo_placement_name(extra: int, seed: int) -> str:
    """The row of a network trained on the training split plus `extra` rooms of `bench.lamp_rooms`."""
    return f"from the photo, seed {seed}" if extra == 0 else f"from the photo, +{extra} rooms, seed {seed}"


def run(
    data_dir="outputs/preprocess",
    grid=8,
    height=60,
    epochs=60,
    seed=0,
    seeds=3,
    curve=(0,),
    extra_dir="outputs/bench/lamp_rooms",
    profile="tiny",
    width=32,
    patience=None,
    net_kind="small",
    calibrate=False,
) -> dict:
    """The bench (module docstring). `curve`: the numbers of extra rooms (`bench.lamp_rooms`, rendered
    into `extra_dir` where missing, from the stage's `profile`) trained on beside the training split, one
    network per number and seed; every row with extra rooms is also paired with the same seed's row
    without them."""
    from pipeline.data.datasets import ShardDataset

    manifest = json.loads((Path(data_dir) / "manifest.json").read_text())
    source_root = Path(manifest["source_root"])
    if not source_root.is_dir():
        raise FileNotFoundError(f"{data_dir}/manifest.json: source_root {source_root} (the room files) is missing")
    if net_kind not in NETS:
        raise ValueError(f"--net {net_kind!r}: one of {', '.join(NETS)}")
    if grid < 1 or height < 8 or epochs < 1 or seeds < 1 or width < 2:
        raise ValueError(
            f"--grid {grid}, --size {height}, --epochs {epochs}, --seeds {seeds}, --width {width}: need grid >= 1, "
            "size >= 8, epochs >= 1, seeds >= 1, width >= 2"
        )
    curve = sorted(set(int(n) for n in curve))
    if not curve or curve[0] < 0:
        raise ValueError(f"--curve {curve}: numbers of extra rooms, each >= 0")
    train_set, test_set = ShardDataset(data_dir, "train", lighting=False), ShardDataset(data_dir, "test", lighting=True)
    val_set = ShardDataset(data_dir, "val", lighting=False)
    x_train, cells_train = split_targets(train_set, source_root, grid, height)
    x_val, cells_val = split_targets(val_set, source_root, grid, height)
    x_test, cells_test = split_targets(test_set, source_root, grid, height)
    t_train, t_val, t_test = distribution(cells_train), distribution(cells_val), distribution(cells_test)
    x_extra, t_extra = x_train[:0], t_train[:0]
    if curve[-1] > 0:
        from pipeline.bench.lamp_rooms import extra_rooms

        x_extra, cells_extra = room_targets(extra_rooms(extra_dir, curve[-1], seed, profile, height), grid)
        t_extra = distribution(cells_extra)
        if x_extra.shape[1:] != x_train.shape[1:]:
            raise ValueError(
                f"{extra_dir}: its photos are {tuple(x_extra.shape[1:])}, the training split's "
                f"{tuple(x_train.shape[1:])}: rendered for another profile or size"
            )
    uniform = torch.full_like(t_test, 1 / t_test.shape[1])
    mean_prior = t_train.mean(0, keepdim=True).expand_as(t_test)
    placements = {"uniform over the ceiling": uniform, "training rooms' mean": mean_prior}
    val_curves, kept, fitted_scores, rooms, temperatures = {}, {}, {}, {}, {}
    for extra in curve:
        for sd in range(seed, seed + seeds):
            name = photo_placement_name(extra, sd)
            x = torch.cat([x_train, x_extra[:extra]])
            t = torch.cat([t_train, t_extra[:extra]])
            net, val_curves[name] = train(
                x, t, x_val, t_val, grid, epochs, sd, width=width, patience=patience, kind=net_kind, calibrate=calibrate
            )
            kept[name] = int(np.argmin(val_curves[name])) + 1
            temperatures[name] = float(net.temperature)
            rooms[name] = len(x)
            with torch.no_grad():
                placements[name] = predicted = F.softmax(net(x_test), -1)
                fitted_scores[name] = placement_scores(F.softmax(net(x_train), -1), t_train)
    report = {
        "data_dir": str(data_dir),
        "grid": grid,
        "input_height": height,
        "epochs": epochs,
        "patience": patience,
        "net": net_kind,
        "net_width": width,
        "calibrated": calibrate,
        "temperature": temperatures,
        "seed": seed,
        "train_views": len(train_set),
        "val_views": len(val_set),
        "test_views": len(test_set),
        "seeds": list(range(seed, seed + seeds)),
        "curve": curve,
        "extra_rooms": {"dir": str(extra_dir), "rooms": len(x_extra), "profile": profile} if curve[-1] else None,
        "training_rooms": rooms,
        "validation_cross_entropy": val_curves,
        "kept_epoch": kept,
        "validation_cross_entropy_of_the_training_mean": placement_scores(
            t_train.mean(0, keepdim=True).expand_as(t_val), t_val
        )["cross_entropy"],
        "placement": {name: placement_scores(p, t_test) for name, p in placements.items()},
        "placement_on_training_views": fitted_scores,
    }
    report["light"], per_view = light_scores(test_set, source_root, grid, placements)
    report["differences"] = paired_differences(per_view, "training rooms' mean")
    report["summary"] = placement_summary(
        report, "nMSE against the training rooms' mean placement, paired by test view (95 % bootstrap)"
    )
    more = [
        (photo_placement_name(extra, sd), photo_placement_name(0, sd))
        for extra in curve
        if extra
        for sd in report["seeds"]
    ]
    if more and curve[0] == 0:
        report["differences_with_more_rooms"] = paired_pairs(per_view, more)
        report["summary"]["nMSE with the extra rooms against without, same seed, paired by test view"] = [
            {"difference": name, "nMSE": d["diff"], "lo": d["lo"], "hi": d["hi"]}
            for name, d in report["differences_with_more_rooms"].items()
        ]
    report["examples"] = {
        "target": t_test[:4].view(-1, grid, grid).tolist(),
        "from the photo": predicted[:4].view(-1, grid, grid).tolist(),
    }
    return report


def light_bars(ax, light: dict, title: str) -> None:
    """Horizontal bars of each row's surface and free nMSE (`light`: row name -> kind -> {"nmse"})."""
    names = list(light)
    y = np.arange(len(names))
    for j, kind in enumerate(KINDS):
        vals = [light[n].get(kind, {}).get("nmse", math.nan) for n in names]
        ax.barh(y + 0.4 * j - 0.2, vals, 0.4, label=f"{kind} nMSE")
    ax.set_yticks(y, names, fontsize=8)
    ax.invert_yaxis()
    ax.legend(fontsize=7)
    ax.set_title(title, fontsize=9)


def curve_rows(report: dict) -> list[dict]:
    """Per network of the learning curve: its training rooms, seed, share on lamp cells and surface nMSE."""
    rows = []
    for extra in report.get("curve", [0]):
        for sd in report["seeds"]:
            name = photo_placement_name(extra, sd)
            if name in report["light"]:
                rows.append(
                    {
                        "rooms": report.get("training_rooms", {}).get(name, report["train_views"]),
                        "seed": sd,
                        "share": report["placement"][name]["share_on_lamp_cells"],
                        "surf": report["light"][name].get("surf", {}).get("nmse", math.nan),
                    }
                )
    return rows


def plot(report: dict, path) -> None:
    rows = curve_rows(report)
    several = len({r["rooms"] for r in rows}) > 1
    fig = Figure(figsize=(11, 8.4 if several else 5.6))
    top = 3 if several else 2
    light_bars(
        fig.add_subplot(top, 1, 1),
        report["light"],
        f"light on {report['test_views']} test views with the lamps' energy placed on the ceiling "
        f"({report['grid']} x {report['grid']} cells)",
    )
    if several:
        for j, (key, label) in enumerate((("share", "share on lamp cells"), ("surf", "surface nMSE"))):
            ax = fig.add_subplot(top, 2, 3 + j)
            ax.plot([r["rooms"] for r in rows], [r[key] for r in rows], "o", alpha=0.6, label="one seed")
            sizes = sorted({r["rooms"] for r in rows})
            ax.plot(sizes, [np.mean([r[key] for r in rows if r["rooms"] == n]) for n in sizes], "-", label="mean")
            prior = "training rooms' mean"
            if key == "share":
                ax.axhline(report["placement"][prior]["share_on_lamp_cells"], color="grey", ls="--", label=prior)
            else:
                ax.axhline(report["light"][prior]["surf"]["nmse"], color="grey", ls="--", label=prior)
                ax.axhline(
                    report["light"]["true placement"]["surf"]["nmse"], color="green", ls=":", label="true placement"
                )
            ax.set_xscale("log")
            ax.set_xticks(sizes, [str(n) for n in sizes], fontsize=8)
            ax.xaxis.set_minor_formatter(NullFormatter())
            ax.set_xlabel("training rooms")
            ax.set_title(f"{label}, test views", fontsize=9)
            ax.legend(fontsize=7)
    ex = report["examples"]
    last = report["seeds"][-1]
    if several:  # the examples are the last network's: the most rooms, the last seed
        last = f"{last}, {max(r['rooms'] for r in rows)} rooms"
    for i in range(min(4, len(ex["target"]))):
        for j, key in enumerate(("target", "from the photo")):
            a = fig.add_subplot(top, 8, 8 * (top - 1) + 1 + 2 * i + j)
            a.imshow(np.array(ex[key][i]), cmap="magma")
            a.set_xticks([])
            a.set_yticks([])
            a.set_title(f"view {i}:\n" + ("true" if j == 0 else f"seed {last}"), fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data-dir", default="outputs/preprocess")
    p.add_argument("--grid", type=int, default=8)
    p.add_argument("--size", type=int, default=60, help="input photo height in pixels")
    p.add_argument("--epochs", type=int, default=60)
    p.add_argument(
        "--patience", type=int, default=None, help="stop after this many epochs without a better validation score"
    )
    p.add_argument("--width", type=int, default=32, help="the placement network's channels")
    p.add_argument("--net", default="small", choices=NETS, help="the placement network (PlacementNet)")
    p.add_argument(
        "--calibrate", action="store_true", help="judge each epoch at its best temperature on validation views"
    )
    p.add_argument("--seed", type=int, default=0, help="the first seed")
    p.add_argument("--seeds", type=int, default=3, help="networks trained, from --seed on")
    p.add_argument(
        "--curve",
        default="0",
        help="comma-separated numbers of extra rooms (bench.lamp_rooms) trained on beside the training split",
    )
    p.add_argument("--extra-dir", default="outputs/bench/lamp_rooms", help="cache of the extra rooms")
    p.add_argument("--profile", default="tiny", help="the synthesize profile the extra rooms are drawn with")
    p.add_argument("--name", default="lamp_placement")
    add_threads_option(p)
    a = p.parse_args(argv)
    try:
        curve = [int(n) for n in a.curve.split(",")]
    except ValueError:
        p.error(f"--curve {a.curve!r}: comma-separated whole numbers")
    apply_threads(a.threads)
    report = run(
        a.data_dir,
        a.grid,
        a.size,
        a.epochs,
        a.seed,
        a.seeds,
        curve,
        a.extra_dir,
        a.profile,
        a.width,
        a.patience,
        a.net,
        a.calibrate,
    )
    print(publish(a.name, report, plot))


if __name__ == "__main__":
    main()
