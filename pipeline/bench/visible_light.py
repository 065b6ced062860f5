"""`python -m pipeline.bench.visible_light`: how much of the light out of view the photo itself holds.

LightNet's out-of-view branch answers the rays SSRT does not land on a pixel (misses, and hits behind a
depth gap). Held out, the trained branch scores about what one constant per probe scores. This bench asks
what an answer built from what the camera saw could score, with no learning and the best geometry:
the photo's pixels splatted onto the room's box (`ops.roombox.observed_textures`: walls, floor and
ceiling by their depth, lamps and windows along their camera rays), each out-of-view direction given the
observed radiance of the texel it leaves the box through, and the texels the camera did not see given a
fill. Every rule blends as tiny's LightNet does (k 10, `out_threshold` 0.9) with the image's own pixel
as the local source (`bench.blend_floor`), on ground-truth G-buffers, so the rows differ only in the
out-of-view source:
- `truth`: each texel's true radiance (the floor of the blend);
- `probe mean`: every out-of-view direction at its probe's true mean radiance (an oracle of energy
  without structure: what the trained branch nearly scores);
- `seen, <box>, unseen at the image mean`: the observed texels, the rest at the photo's mean radiance
  (nothing but the photo);
- `seen, <box>, unseen at the probe mean`: the observed texels, the rest at the probe's true mean (the
  photo's structure with an oracle of the unseen energy);
with `<box>` the room's true box (from the room file) or the one `ops.roombox` estimates from the
ground-truth normals and depth; with `--light-net` the trained network's own out-of-view branch too.
`true lamps` answers a direction that meets one of the room file's ceiling panels (a ray against each
lamp's rectangle; nothing else occludes it) with the lamp's emitted radiance and every other direction
with its probe's true mean over the texels that see no lamp (`the rest at the probe's mean`) or the
photo's mean (`the rest at the image mean`): what a branch that knew where the lamps are, and nothing
else, would score. A ladder of oracles says how finely the light must be placed on the box: `true box, N x N per face`
gives each direction the mean true radiance of all the view's probe directions (both kinds) that leave
the true box through the same texel of an N x N grid per face, N = 1 (each face's mean) up to 32 (fitted
to the probes themselves: an in-sample oracle, the representation's reach, not a prediction).
Scores: the pooled normalised MSE per probe kind and each ray class's part (`light_energy.EnergyTally`).
Writes reports/bench/visible_light.json (or `--name`) and a PNG.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from pipeline.bench.blend_floor import (
    KINDS,
    blended,
    ground_truth_gbuffers,
    kind_scores,
    network_sources,
    network_system,
    plot_class_parts,
    probe_mean_directions,
    score_directions,
    view_rays,
)
from pipeline.bench.common import add_threads_option, apply_threads, publish
from pipeline.bench.light_energy import EnergyTally
from pipeline.bench.roombox_floor import estimated_box, true_box
from pipeline.models.light_net import confidence
from pipeline.ops.roombox import exit_face, observed_textures

K, THRESHOLD = 10.0, 0.9  # tiny's rule (conf/model/light_net/small.yaml, conf/profile/tiny.yaml)
TEXTURE_SIZE = 32  # texels per face side, as the roombox branch's (conf/model/light_net/small.yaml)
BOXES = ("true box", "estimated box")
LADDER = (1, 2, 4, 8, 32)  # texels per face side of the oracle ladder


def box_texels(box, origin: torch.Tensor, direction: torch.Tensor, size: int) -> torch.Tensor:
    """Flat texel index (N,) in [0, 6 size^2) where directions (N, 3) from origins (N, 3), view space,
    leave `box` (rotation (3, 3), lo, hi (3,)) on a size x size grid per face (nearest texel)."""
    rot, lo, hi = (t.double() for t in box)
    q, d = origin.double() @ rot, direction.double() @ rot
    N = len(q)
    face, st, _ = exit_face(q, d, lo.expand(N, 3), hi.expand(N, 3))
    texel = ((st + 1) * (size / 2)).long().clamp(0, size - 1)
    return face * size * size + texel[:, 1] * size + texel[:, 0]


def texel_means(index: torch.Tensor, radiance: torch.Tensor, cells: int) -> torch.Tensor:
    """(cells, 3) mean of radiance (N, 3) over the directions in each cell of index (N,) (0 where none)."""
    total = radiance.new_zeros(cells, 3).index_add_(0, index, radiance)
    count = radiance.new_zeros(cells).index_add_(0, index, torch.ones_like(radiance[:, 0]))
    return total / count.clamp(min=1)[:, None]


def room_lamps(source_root: Path, view_id: str):
    """The view's ceiling panels in view space (`lamps_in_view`) from its room file and camera."""
    scene, view = view_id.split("/")
    room = json.loads((source_root / scene / "scene.json").read_text())
    world_from_view = json.loads((source_root / scene / "cameras.json").read_text())[view]["world_from_view"]
    return lamps_in_view(room, world_from_view)


def lamps_in_view(room: dict, world_from_view):
    """A room's ceiling panels in the view space of a camera with 4x4 `world_from_view`: centre (L, 3),
    half-axes u, v (L, 3), normal (L, 3) and emitted radiance (L, 3), float64, from the room's `lamp`
    shapes (unit rectangles scaled by `to_world`, emitting on the side their normal faces); None without
    lamps."""
    view_from_world = torch.linalg.inv(torch.as_tensor(world_from_view, dtype=torch.float64))
    lamps = [shape for shape in room["shapes"] if shape["role"] == "lamp"]
    if not lamps:
        return None
    m = torch.tensor([lamp["to_world"] for lamp in lamps], dtype=torch.float64)  # (L, 4, 4)
    rot, move = view_from_world[:3, :3], view_from_world[:3, 3]
    centre = m[:, :3, 3] @ rot.T + move
    u, v, n = m[:, :3, 0] @ rot.T, m[:, :3, 1] @ rot.T, m[:, :3, 2] @ rot.T
    emission = torch.tensor([lamp["emission"] for lamp in lamps], dtype=torch.float64)
    return {"centre": centre, "u": u, "v": v, "normal": n, "emission": emission}


def lamp_radiance(lamps: dict, origin: torch.Tensor, direction: torch.Tensor):
    """Radiance (N, 3) of the nearest lamp each ray origin + t direction (N, 3), view space, meets from its
    emitting side, and whether it met one (N,) bool."""
    o, d = origin.double(), direction.double()
    denom = d @ lamps["normal"].T  # (N, L): < 0 when the ray comes at the emitting side
    t = ((lamps["centre"][None] - o[:, None]) * lamps["normal"][None]).sum(-1) / denom.clamp(max=-1e-12)
    point = o[:, None] + t[..., None] * d[:, None] - lamps["centre"][None]
    a = (point * lamps["u"][None]).sum(-1) / (lamps["u"] ** 2).sum(-1)
    b = (point * lamps["v"][None]).sum(-1) / (lamps["v"] ** 2).sum(-1)
    meets = (denom < 0) & (t > 0) & (a.abs() <= 1) & (b.abs() <= 1)
    t = torch.where(meets, t, torch.full_like(t, float("inf")))
    nearest = t.argmin(1)
    met = meets.any(1)
    radiance = torch.where(met[:, None], lamps["emission"][nearest], torch.zeros(len(o), 3, dtype=torch.float64))
    return radiance, met


def observed(batch: dict, gb: dict, box, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """What the camera saw of `box` (rotation (3, 3), lo, hi (3,)): per flat texel of its six size x size
    faces the observed radiance (6 size^2, 3) and the pixel count (6 size^2,) (`observed_textures`)."""
    rot, lo, hi = (t.double() for t in box)
    image = batch["im"].double().clamp(min=0)
    fov = float(batch["fov_x_deg"][0])
    obs, count = observed_textures(
        image, gb["depth"].double(), fov, rot[None], lo[None], hi[None], size, gb["normal"].double()
    )
    return obs[0].permute(0, 2, 3, 1).reshape(-1, 3), count[0].reshape(-1)


def seen_lookup(seen: tuple, box, origin: torch.Tensor, direction: torch.Tensor, size: int):
    """Where directions (N, 3) from origins (N, 3), view space, leave `box`: the observed radiance there
    (N, 3) and whether the camera saw that texel (N,) bool (nearest texel); `seen` is `observed`'s pair."""
    flat = box_texels(box, origin, direction, size)
    return seen[0][flat], seen[1][flat] > 0


def out_sources(batch: dict, r: dict, kind: str, boxes: dict, seen: dict, ladder: dict, lamps=None):
    """Every out-of-view source of the module's rows at the directions of `view_rays`, (M S, 3) float64;
    `seen`: per box what the camera saw of it (`observed`); `ladder`: per grid size, the view's texel
    means on the true box (`texel_means`). Returns the sources, per box whether each direction's texel
    was seen (M S,), and the true lamps' (radiance, met) per direction (None without lamps)."""
    S = r["S"]
    P, T = batch["light"][0].kind(kind).texels()[1].shape[:2]
    truth = r["truth"].repeat_interleave(S, 0)
    probe_mean = probe_mean_directions(batch, kind, r)
    image_mean = batch["im"][0].double().clamp(min=0).mean((1, 2)).expand_as(truth)
    out = {"truth": truth, "probe mean": probe_mean}
    was_seen = {}
    for name, box in boxes.items():
        values, was_seen[name] = seen_lookup(seen[name], box, r["origin"], r["direction"], TEXTURE_SIZE)
        out[f"seen, {name}, unseen at the image mean"] = torch.where(was_seen[name][:, None], values, image_mean)
        out[f"seen, {name}, unseen at the probe mean"] = torch.where(was_seen[name][:, None], values, probe_mean)
    lamp_hits = None
    if lamps is not None:
        glow, met = lamp_hits = lamp_radiance(lamps, r["origin"], r["direction"])
        dark = ~met.view(P, T, S).any(-1)  # texels that see no lamp
        rest = (r["truth"].view(P, T, 3) * dark[..., None]).sum(1) / dark.sum(1).clamp(min=1)[:, None]
        rest = rest.repeat_interleave(T * S, 0)
        out["true lamps, the rest at the probe's mean (oracle)"] = torch.where(met[:, None], glow, rest)
        out["true lamps, the rest at the image mean"] = torch.where(met[:, None], glow, image_mean)
    for size, means in ladder.items():
        out[f"true box, {size} x {size} per face (oracle)"] = means[
            box_texels(boxes["true box"], r["origin"], r["direction"], size)
        ]
    return out, was_seen, lamp_hits


@torch.no_grad()
def run(data_dir="outputs/preprocess", split="test", views=None, light_net=None) -> dict:
    from torch.utils.data import DataLoader, Subset

    from pipeline.data.datasets import ShardDataset, collate_views

    manifest = json.loads((Path(data_dir) / "manifest.json").read_text())
    source_root = Path(manifest["source_root"])
    if not source_root.is_dir():
        raise FileNotFoundError(f"{data_dir}/manifest.json: source_root {source_root} (the room files) is missing")
    data = ShardDataset(data_dir, split, lighting=True)
    count = len(data) if views is None else views
    if not 0 < count <= len(data):
        raise ValueError(f"--views {views}: the {split} split of {data_dir} has {len(data)} views")
    system = None if light_net is None else network_system(light_net)
    tallies: dict[str, dict[str, EnergyTally]] = {}
    seen_counts = {name: [0, 0] for name in BOXES}
    lamp_ratio: list[float] = []
    loader = DataLoader(Subset(data, range(count)), 1, collate_fn=collate_views)
    for batch in tqdm(loader, total=count, desc=f"views ({split})"):
        item_id = batch["id"][0]
        gb = ground_truth_gbuffers(batch)
        normal_item = {"depth": batch["depth"][0], "mask": batch["mask"][0], "normal": batch["normal"][0]}
        normal_item["fov_x_deg"] = float(batch["fov_x_deg"][0])
        boxes = {"true box": true_box(source_root, item_id), "estimated box": estimated_box(normal_item)}
        traced = {kind: view_rays(batch, gb, kind) for kind in KINDS}
        traced = {kind: r for kind, r in traced.items() if r is not None}
        ladder = {}
        for size in LADDER:  # every probe direction of the view, both kinds, binned on the true box
            index = torch.cat(
                [box_texels(boxes["true box"], r["origin"], r["direction"], size) for r in traced.values()]
            )
            radiance = torch.cat([r["truth"].repeat_interleave(r["S"], 0) for r in traced.values()])
            ladder[size] = texel_means(index, radiance, 6 * size * size)
        lamps = room_lamps(source_root, item_id)
        seen = {name: observed(batch, gb, box, TEXTURE_SIZE) for name, box in boxes.items()}  # once per view
        for kind, r in traced.items():
            sources, was_seen, lamp_hits = out_sources(batch, r, kind, boxes, seen, ladder, lamps)
            if lamp_hits is not None:  # the lamps' units against the probes': texels wholly on a lamp
                glow, met = lamp_hits
                full = met.view(r["M"], r["S"]).all(1)
                if full.any():
                    lamp_mean = glow.view(r["M"], r["S"], 3).mean(1)[full].mean(1)
                    lamp_ratio.extend((r["truth"][full].mean(1) / lamp_mean).tolist())
            if system is not None:
                sources["network"] = network_sources(system, batch, gb, r)["out"]
            out_of_view = (~r["hit"]) | (confidence(r["hit"], r["gap"], K) >= THRESHOLD)  # what the branch answers
            for name in BOXES:
                seen_counts[name][0] += int((was_seen[name] & out_of_view).sum())
                seen_counts[name][1] += int(out_of_view.sum())
            for name, out in sources.items():
                tally = tallies.setdefault(name, {k: EnergyTally() for k in KINDS})
                score_directions(tally[kind], r, blended(r["local"], out, r["hit"], r["gap"], K, THRESHOLD))
    rows = [{"source": name, **kind_scores(by_kind)} for name, by_kind in tallies.items()]
    seen_share = {name: c[0] / max(c[1], 1) for name, c in seen_counts.items()}
    return {
        "data_dir": str(data_dir),
        "split": split,
        "views": count,
        "rule": {"k": K, "out_threshold": THRESHOLD, "local": "the image's pixel at the SSRT hit"},
        "texture_size": TEXTURE_SIZE,
        "light_net": None if light_net is None else str(light_net),
        "out_of_view_directions_seen": seen_share,
        "lamp_texels": len(lamp_ratio),
        "lamp_texel_truth_over_emission_median": float(np.median(lamp_ratio)) if lamp_ratio else None,
        "rows": rows,
        "summary": [
            {
                "out-of-view source": r["source"],
                "surface nMSE": r.get("surf", {}).get("nmse"),
                "surface nMSE from misses": r.get("surf", {}).get("classes", {}).get("miss"),
                "free nMSE": r.get("free", {}).get("nmse"),
            }
            for r in rows
        ],
    }


def plot(report: dict, path) -> None:
    rows = report["rows"]

    def part(i, kind, c):
        return rows[i].get(kind, {}).get("classes", {}).get(c, 0.0)

    title = (
        f"out-of-view light from what the photo shows: {report['views']} {report['split']} views, "
        "ground-truth G-buffers, the local source the image's pixel"
    )
    plot_class_parts([r["source"] for r in rows], part, title, path)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data-dir", default="outputs/preprocess")
    p.add_argument("--split", default="test")
    p.add_argument("--views", type=int, default=None, help="the first N views of the split (default: all)")
    p.add_argument("--light-net", default=None, help="a LightNet export: its out-of-view branch as a row too")
    p.add_argument("--name", default="visible_light")
    add_threads_option(p)
    a = p.parse_args(argv)
    apply_threads(a.threads)
    print(publish(a.name, run(a.data_dir, a.split, a.views, a.light_net), plot))


if __name__ == "__main__":
    main()
