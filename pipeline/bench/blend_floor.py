"""`python -m pipeline.bench.blend_floor`: the light error LightNet's blend leaves with perfect sources.

LightNet answers a ray that SSRT lands on a pixel with the local branch, and blends in the out-of-view
branch by the confidence u = tanh(k gap) (gap: metres the ray passes behind the pixel's surface);
`out_threshold` t keeps the local answer alone where u < t. This bench asks what error that rule leaves
when both sources are as good as they can be, so no network is trained:
- the local source is the image's own radiance at the hit pixel (what the local branch is fed and
  fitted towards; it is the radiance leaving the pixel towards the camera, so a glossy pixel is off by
  its view dependence);
- the out-of-view source is the probe texel's true radiance (a perfect branch; within a texel its S
  directions share the texel's mean).
On the ground-truth G-buffers of the first `--views` training views (the overfit bench's rooms), every
probe texel at the evaluation's stratified directions, each rule's texel value (the mean over its S
directions) is scored as the stage scores LightNet: the pooled normalised MSE per probe kind and each ray
class's contribution to it (`light_energy.EnergyTally`; classes labelled by the metric's own rule at
k = 10 for every row, so the rows share their classes). A rule whose surface nMSE is above a target
cannot meet it whatever the two branches learn.
Writes reports/bench/blend_floor.json (or `--name`) and a PNG.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from matplotlib.figure import Figure
from tqdm import tqdm

from pipeline.bench.common import add_threads_option, apply_threads, publish
from pipeline.bench.light_energy import RAY_CLASSES, EnergyTally, class_parts
from pipeline.data.lighting import probe_rays
from pipeline.models.light_net import confidence, trace_views

LABEL_K = 10.0  # the metric's classes: u = tanh(10 gap) at every row (metrics.lighting.ray_classes)
KINDS = ("surf", "free")
# (name, k, out_threshold): the paper (t = 0), tiny (t = 0.9), and sharper confidences
DEFAULT_RULES = (
    ("k 10, t 0 (paper)", 10.0, 0.0),
    ("k 10, t 0.9 (tiny)", 10.0, 0.9),
    ("k 30, t 0", 30.0, 0.0),
    ("k 100, t 0", 100.0, 0.0),
    ("k 1000, t 0", 1000.0, 0.0),
    ("hits local only", 0.0, 0.0),
)


def parse_rule(text: str) -> tuple[str, float, float]:
    """'NAME:K:T' -> (NAME, K, T); a clear error naming the argument otherwise."""
    parts = text.split(":")
    try:
        name, k, t = parts[0], float(parts[1]), float(parts[2])
    except (IndexError, ValueError):
        raise SystemExit(f"--rule {text!r}: expected NAME:K:T, e.g. 'k 30:30:0'") from None
    if k < 0 or not 0.0 <= t <= 1.0:
        raise SystemExit(f"--rule {text!r}: k must be >= 0 and t in [0, 1]")
    return name, k, t


def blended(local: torch.Tensor, out: torch.Tensor, hit: torch.Tensor, gap: torch.Tensor, k: float, t: float):
    """Per direction (N, 3): misses take `out`; hits (1 - u) local + u out where u = tanh(k gap) >= t, else
    `local` alone (LightNet.forward's rule with perfect sources). k = 0 answers every hit locally."""
    u = confidence(hit, gap, k)
    use_out = (~hit) | (u >= t) if t > 0 else torch.ones_like(hit)
    mix = (1 - u).unsqueeze(-1) * local + u.unsqueeze(-1) * out
    return torch.where(use_out.unsqueeze(-1), mix, local)


def ground_truth_gbuffers(batch: dict) -> dict:
    """The ground-truth G-buffers of a collated one-view batch as LightNet reads them: depth (1, H, W)
    (0 where masked), normal and albedo (1, 3, H, W), material (1, 2, H, W)."""
    depth = batch["depth"][:, 0]
    keep = batch["mask"][:, 0].bool() & torch.isfinite(depth)
    gb = {k: batch[k] for k in ("normal", "albedo", "material")}
    return {**gb, "depth": torch.where(keep, depth, torch.zeros_like(depth))}


def view_rays(batch: dict, gb: dict, kind: str):
    """A one-view batch's `kind` probe texels traced on G-buffers gb: the directions' origin, wi (M S, 3),
    the image's radiance at the hit pixel (M S, 3), the texel truth (M, 3), hit and gap (M S,), and each
    texel's class inputs label_hit, label_u (M,)."""
    rays = probe_rays(batch["light"], kind)
    if rays is None:
        return None
    M, S = rays.direction.shape[:2]
    origin = rays.origin.repeat_interleave(S, 0)
    direction = rays.direction.reshape(-1, 3)
    fov = float(batch["fov_x_deg"][0])
    pixel, hit, gap = trace_views(gb, fov, origin, direction, torch.zeros(M * S, dtype=torch.long))
    image = batch["im"][0].clamp(min=0)
    row, col = pixel[:, 0].clamp(min=0), pixel[:, 1].clamp(min=0)
    local = torch.where(hit.unsqueeze(-1), image[:, row, col].T, torch.zeros(M * S, 3))
    gap = gap.double()
    return {
        # the metric's texel classes: most directions hit, their mean confidence at LABEL_K
        "label_hit": hit.view(M, S).float().mean(1) > 0.5,
        "label_u": confidence(hit, gap, LABEL_K).view(M, S).mean(1),
        "pixel": pixel,
        "origin": origin,
        "direction": direction,
        "local": local.double(),
        "truth": rays.radiance.double(),
        "hit": hit,
        "gap": gap,
        "M": M,
        "S": S,
    }


def probe_mean_directions(batch: dict, kind: str, r: dict) -> torch.Tensor:
    """Each direction of `view_rays` at its probe's true mean radiance, (M S, 3) float64 (the rays run
    probe by probe, texel by texel: a mismatch with the view's probes is refused)."""
    P, T = batch["light"][0].kind(kind).texels()[1].shape[:2]
    if P * T != r["M"]:
        raise RuntimeError(f"{kind} probes: {P} x {T} texels against {r['M']} rays (probe_rays' order changed?)")
    return r["truth"].view(P, T, 3).mean(1).repeat_interleave(T * r["S"], 0)


def score_directions(tally: EnergyTally, r: dict, pred: torch.Tensor) -> torch.Tensor:
    """Add a prediction per direction (M S, 3) of `view_rays` to `tally` as texel means against the truth,
    under the metric's texel classes; returns the texel means (M, 3)."""
    texels = pred.view(r["M"], r["S"], 3).mean(1)
    tally.add(texels[None], r["truth"][None], r["label_hit"][None], r["label_u"][None])
    return texels


def kind_scores(by_kind: dict) -> dict:
    """{kind: {"nmse", "classes": {class: its nMSE contribution}}} of the tallies that hold texels."""
    out = {}
    for kind, t in by_kind.items():
        if t.sums:
            s = t.summary()
            out[kind] = {
                "nmse": s["nmse"]["lightnet"],
                "classes": {c: s["classes"][c]["nmse_contribution"] for c in RAY_CLASSES},
            }
    return out


CONTINUE_STEP_M = 0.025  # metres between the points a continued ray is tested at behind an occluder
CONTINUE_REACH_M = 8.0  # how far behind the first crossing a continued ray looks for free space


def continued_local(batch: dict, gb: dict, r: dict, k: float) -> torch.Tensor:
    """The image's radiance where each uncertain hit (u = tanh(k gap) >= 0.5: the ray slipped behind
    what the pixel shows) lands when the march goes on behind the occluder, (M S, 3) float64, NaN where
    it does not land on a confident pixel (it leaves the image or finds no free space within reach).

    From the point of the ray level with the hit pixel's surface, the ray is walked in CONTINUE_STEP_M
    steps to the first point in front of the depth map again (or off it), and traced from there with the
    same hit rule; its radiance is taken only where that second hit is confident (u < 0.5). This is what
    a march with a thickness for what it passes behind would answer, given the image's own pixels."""
    from pipeline.ops.camera import backproject, project

    out = torch.full_like(r["local"], float("nan"))
    u = confidence(r["hit"], r["gap"], k)
    sel = torch.nonzero(r["hit"] & (u >= 0.5)).squeeze(-1)
    if not sel.numel():
        return out
    depth = gb["depth"][0]
    H, W = depth.shape
    fov = float(batch["fov_x_deg"][0])
    pixel = r["pixel"][sel]
    points = backproject(depth[None], fov)[0]  # (H, W, 3)
    o, d = r["origin"][sel].to(points.dtype), r["direction"][sel].to(points.dtype)
    t0 = ((points[pixel[:, 0], pixel[:, 1]] - o) * d).sum(-1)  # the ray level with the hit's surface
    steps = torch.arange(1, int(CONTINUE_REACH_M / CONTINUE_STEP_M) + 1, dtype=o.dtype) * CONTINUE_STEP_M
    t = t0[:, None] + steps[None]  # (n, K)
    xy, z = project(o[:, None] + t[..., None] * d[:, None], fov, H, W)
    col, row = xy[..., 0].floor().long(), xy[..., 1].floor().long()
    inside = (col >= 0) & (col < W) & (row >= 0) & (row < H) & (z > 0)
    surface = depth[row.clamp(0, H - 1), col.clamp(0, W - 1)]
    free = ~inside | (surface <= 0) | ~torch.isfinite(surface) | (z < surface)
    found = free.any(1)
    first = free.float().argmax(1)
    start = o + (t.gather(1, first[:, None])[:, 0])[:, None] * d
    ok = torch.nonzero(found).squeeze(-1)
    pixel2, hit2, gap2 = trace_views(gb, fov, start[ok], d[ok], torch.zeros(len(ok), dtype=torch.long))
    good = hit2 & (confidence(hit2, gap2.to(o.dtype), k) < 0.5)
    image = batch["im"][0].clamp(min=0)
    rows = sel[ok[good]]
    out[rows] = image[:, pixel2[good, 0], pixel2[good, 1]].T.double()
    return out


def network_sources(system, batch: dict, gb: dict, r: dict) -> dict:
    """The trained LightNet's two sources at the directions of `view_rays`: `local` (its SSRT answer,
    0 on misses) and `out` (its out-of-view branch on every direction), (M S, 3) float64."""
    from pipeline.systems.lighting import QUERY_CHUNK

    net = system.net
    fov = system.fov(batch)
    ctx = net.encode(batch["im"], gb["depth"], fov, normal=gb["normal"])
    b = torch.zeros(len(r["direction"]), dtype=torch.long)
    out, mode = {}, net.mode
    try:
        for name, m in (("local", "ssrt_only"), ("out", "out_of_view_only")):
            net.mode = m
            gen = system.eval_generator()
            out[name] = torch.cat(
                [
                    net(
                        ctx,
                        gb,
                        fov,
                        r["origin"][i : i + QUERY_CHUNK],
                        r["direction"][i : i + QUERY_CHUNK],
                        b[i : i + QUERY_CHUNK],
                        gen,
                    )["radiance"]
                    for i in range(0, len(b), QUERY_CHUNK)
                ]
            ).double()
    finally:
        net.mode = mode
    return out


SOURCE_PAIRS = (("image", "truth"), ("network", "truth"), ("image", "network"), ("network", "network"))


@torch.no_grad()
def run(
    data_dir="outputs/preprocess", views=8, rules=DEFAULT_RULES, light_net=None, material=None, continue_behind=False
) -> dict:
    """Every rule with perfect sources on ground-truth G-buffers; with `light_net` (an export path) the
    trained network's sources swapped in one at a time, at its own k and out_threshold, on the G-buffers
    it was trained on (the frozen MaterialNet's export at `material`, else the ground truth).
    continue_behind: rows where the uncertain hits that land on a confident pixel when marched on behind
    their occluder take that pixel's radiance (`continued_local`), beside the same rows without: on
    ground-truth G-buffers with one constant per probe (its true mean) as the out-of-view source (about
    what a trained branch scores held out), with `light_net` with the network's own sources."""
    from torch.utils.data import DataLoader, Subset

    from pipeline.data.datasets import ShardDataset, collate_views

    train = ShardDataset(data_dir, "train", lighting=True)
    if views > len(train):
        raise ValueError(f"--views {views}: the training split of {data_dir} has {len(train)} views")
    system = None
    # each row: name, k, out_threshold, local source, out-of-view source, uncertain hits continued
    if light_net is None:
        table = [(name, k, t, "image", "truth", False) for name, k, t in rules]
        if continue_behind:
            table += [
                ("k 10, t 0.9, out probe mean", 10.0, 0.9, "image", "probe mean", False),
                ("k 10, t 0.9, out probe mean, uncertain hits continued", 10.0, 0.9, "image", "probe mean", True),
            ]
    else:
        system = network_system(light_net, material)
        k, t = system.net.k, system.net.out_threshold
        table = [(f"local {a}, out {b}", k, t, a, b, False) for a, b in SOURCE_PAIRS]
        if continue_behind:
            table.append(("local network, out network, uncertain hits continued", k, t, "network", "network", True))
    tallies = {name: {kind: EnergyTally() for kind in KINDS} for name, *_ in table}
    continued_share = [0, 0]
    for batch in tqdm(DataLoader(Subset(train, range(views)), 1, collate_fn=collate_views), total=views, desc="views"):
        gb = ground_truth_gbuffers(batch) if system is None else system.gbuffers(batch)
        for kind in KINDS:
            r = view_rays(batch, gb, kind)
            if r is None:
                continue
            local = {"image": r["local"]}
            out = {
                "truth": r["truth"].repeat_interleave(r["S"], 0),
                "probe mean": probe_mean_directions(batch, kind, r),
            }
            if system is not None:
                net = network_sources(system, batch, gb, r)
                local["network"], out["network"] = net["local"], net["out"]
            continued = continued_local(batch, gb, r, LABEL_K) if continue_behind else None
            if continued is not None:
                uncertain = r["hit"] & (confidence(r["hit"], r["gap"], LABEL_K) >= 0.5)
                continued_share[0] += int(torch.isfinite(continued[:, 0]).sum())
                continued_share[1] += int(uncertain.sum())
            for name, k, t, a, b, cont in table:
                pred = blended(local[a], out[b], r["hit"], r["gap"], k, t)
                if cont:
                    pred = torch.where(torch.isfinite(continued[:, :1]), continued, pred)
                score_directions(tallies[name][kind], r, pred)
    rows = []
    for name, k, t, *_ in table:
        row = {"rule": name, "k": k, "out_threshold": t}
        for kind in KINDS:
            if tallies[name][kind].sums:
                s = tallies[name][kind].summary()
                row[kind] = {"nmse": s["nmse"]["lightnet"], "classes": class_parts(s)}
        rows.append(row)
    return {
        "data_dir": str(data_dir),
        "views": views,
        "label_k": LABEL_K,
        "light_net": None if light_net is None else str(light_net),
        "material": None if material is None else str(material),
        "uncertain_hits_continued_to_a_confident_pixel": (
            continued_share[0] / continued_share[1] if continue_behind and continued_share[1] else None
        ),
        "rules": rows,
        "summary": summarise(rows),
    }


def network_system(light_net, material=None):
    """A `LightingSystem` in eval mode holding the LightNet export at light_net, on the frozen MaterialNet
    export's G-buffers at `material` (None: the ground-truth G-buffers)."""
    from pipeline.bench.light_net import system_from_export
    from pipeline.models.export import LIGHT_FORMAT, read_export
    from pipeline.models.material_net import load_material_export

    maps = None if material is None else load_material_export(material)[1]
    return system_from_export(light_net, read_export(light_net, LIGHT_FORMAT), maps)


def summarise(rows: list[dict]) -> list[dict]:
    """One line per rule: surface and free nMSE and the uncertain class's share of the surface one."""
    return [
        {
            "rule": r["rule"],
            "surface nMSE": r.get("surf", {}).get("nmse"),
            "surface nMSE from uncertain hits": r.get("surf", {})
            .get("classes", {})
            .get("uncertain", {})
            .get("nmse_contribution"),
            "surface nMSE from hits": r.get("surf", {}).get("classes", {}).get("hit", {}).get("nmse_contribution"),
            "free nMSE": r.get("free", {}).get("nmse"),
        }
        for r in rows
    ]


def plot_class_parts(labels: list[str], part, title: str, path, target: float | None = None) -> None:
    """One horizontal bar per row and probe kind, stacked by ray class: part(i, kind, cls) is row i's
    class's contribution to its nMSE (0 where none); `target` a dashed line."""
    fig = Figure(figsize=(10, 1.6 + 0.32 * len(labels)))
    y = np.arange(len(labels))
    for j, kind in enumerate(KINDS):
        ax = fig.add_subplot(1, 2, j + 1)
        left = np.zeros(len(labels))
        for c in RAY_CLASSES:
            v = np.array([part(i, kind, c) for i in range(len(labels))])
            ax.barh(y, v, 0.6, left=left, label=c)
            left += v
        if target is not None:
            ax.axvline(target, color="k", lw=0.8, ls="--")
        ax.set_yticks(y, labels if j == 0 else [""] * len(labels), fontsize=7)
        ax.invert_yaxis()
        ax.set_xlabel(f"{kind} nMSE (class parts)")
        ax.set_title(f"{kind} probes", fontsize=9)
    handles, names = fig.axes[0].get_legend_handles_labels()
    fig.legend(handles, names, loc="lower center", ncol=len(RAY_CLASSES), fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    fig.savefig(path, dpi=120)


def plot(report: dict, path) -> None:
    rows = report["rules"]
    what = (
        "perfect sources, ground-truth G-buffers"
        if report.get("light_net") is None
        else "the network's sources swapped"
    )

    def part(i, kind, c):
        return rows[i].get(kind, {}).get("classes", {}).get(c, {}).get("nmse_contribution", 0.0)

    title = f"LightNet's blend with {what}, {report['views']} training views (dashed: 0.10)"
    plot_class_parts([r["rule"] for r in rows], part, title, path, target=0.10)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data-dir", default="outputs/preprocess")
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--rule", action="append", default=None, help="NAME:K:T (repeatable; default: the built-in set)")
    p.add_argument("--light-net", default=None, help="a LightNet export: swap its sources in (rules ignored)")
    p.add_argument("--material", default=None, help="the MaterialNet export whose G-buffers the LightNet trained on")
    p.add_argument(
        "--continue-behind", action="store_true", help="rows with uncertain hits marched on behind their occluder"
    )
    p.add_argument("--name", default="blend_floor")
    add_threads_option(p)
    a = p.parse_args(argv)
    apply_threads(a.threads)
    rules = tuple(parse_rule(r) for r in a.rule) if a.rule else DEFAULT_RULES
    print(publish(a.name, run(a.data_dir, a.views, rules, a.light_net, a.material, a.continue_behind), plot))


if __name__ == "__main__":
    main()
