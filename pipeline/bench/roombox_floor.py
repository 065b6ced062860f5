"""`python -m pipeline.bench.roombox_floor`: how well can a room's box hold its light, and how well is the box found?

The floor test of the `roombox` out-of-view branch. For each of `--views` training views, free HDR
textures on the six faces of a box (one radiance per texel, an opacity per texel and a free 16x32 distant
map behind it, in the box's frame) are fitted with Adam to every texel of the view's ground-truth probes
(surface and free), minimising their normalised MSE. Nothing is decoded from the image: the fit gives the
error the representation itself cannot go below, for the room's true box (`gt`, from the room file) and
for the box `ops.roombox` estimates from the ground-truth normals and depth (`predicted`).
The errors are reported per ray class (SSRT against the ground-truth depth: `miss` rays are the ones only
the out-of-view branch answers) as the pooled normalised MSE sum (L^ - L)^2 / sum L^2 (`metrics.lighting`).

It also measures the box estimate on `--layout-views` views: the rotation's angle from the true one
(degrees) and each face's distance error (metres), unseen faces (behind the camera) apart.
Writes reports/bench/roombox_floor.json (or `--name`) and a PNG.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure
from torch.nn import functional as F
from tqdm import tqdm

from pipeline.bench.common import add_threads_option, apply_threads, publish
from pipeline.data.lighting import probe_rays
from pipeline.metrics.lighting import normalised_mse, ray_classes
from pipeline.models.light_net import confidence, trace_views
from pipeline.models.light_net.roombox import box_radiance
from pipeline.ops.camera import backproject_views
from pipeline.ops.roombox import FACES, box_from_room, extents_from_points, rotation_from_normals

LAYOUTS = ("gt", "predicted")
FAR_SIZE = (16, 32)  # the free distant map's rows x cols (equirectangular in the box's frame)


def true_box(source_root: Path, view_id: str):
    """(rotation (3, 3), lo, hi (3,)) of a view `scene/view` from its room file and camera, float64."""
    scene, view = view_id.split("/")
    room = json.loads((source_root / scene / "scene.json").read_text())
    camera = json.loads((source_root / scene / "cameras.json").read_text())[view]
    return box_from_room(room["size"], camera["world_from_view"])


def estimated_box(item: dict):
    """The box `ops.roombox` finds from a view's ground-truth normals and depth (as the branch would)."""
    depth = item["depth"][0][None]
    valid = item["mask"][0].bool()[None] & (depth > 0)
    points = backproject_views(torch.where(valid, depth, torch.zeros_like(depth)), float(item["fov_x_deg"]))
    rot = rotation_from_normals(item["normal"][None], valid)
    lo, hi = extents_from_points(points, valid, rot, item["normal"][None])
    return rot[0].double(), lo[0].double(), hi[0].double()


def rotation_error_deg(a: torch.Tensor, b: torch.Tensor) -> float:
    """Angle (degrees) of the rotation a^T b."""
    c = ((torch.trace(a.T @ b) - 1) / 2).clamp(-1, 1)
    return math.degrees(math.acos(float(c)))


def far_lookup(far: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Bilinear values (N, 3) of an equirectangular map far (1, 3, R, C) at unit directions d (N, 3) (y up)."""
    theta = torch.acos(d[:, 1].clamp(-1, 1))  # from +y
    phi = torch.atan2(d[:, 0], -d[:, 2])
    grid = torch.stack([phi / math.pi, theta / math.pi * 2 - 1], -1).view(1, -1, 1, 2).to(far.dtype)
    return F.grid_sample(far, grid, mode="bilinear", padding_mode="border", align_corners=False)[0, :, :, 0].T


def fit_view(item: dict, box, texture_size: int, steps: int, lr: float) -> dict:
    """Fit free textures on `box` to one view's probes; nMSE per kind and ray class, and the fit's curve."""
    rot, lo, hi = (t.float() for t in box)
    lights = [item["light"]]
    rays = {k: probe_rays(lights, k) for k in ("surf", "free")}
    rays = {k: r for k, r in rays.items() if r is not None}
    depth = torch.where(item["mask"][0].bool(), item["depth"][0], torch.zeros_like(item["depth"][0]))[None]
    gb = {"depth": depth, "normal": item["normal"][None]}
    fov = float(item["fov_x_deg"])
    classes, flat = {}, {}
    for kind, r in rays.items():
        M, S = r.direction.shape[:2]
        o = r.origin.repeat_interleave(S, 0)
        d = r.direction.reshape(-1, 3)
        b = torch.zeros(len(d), dtype=torch.long)
        pixel, hit, gap = trace_views(gb, fov, o, d, b)
        u = confidence(hit, gap.float(), 10.0)
        classes[kind] = ray_classes(hit.view(M, S).float().mean(1) > 0.5, u.view(M, S).mean(1))
        flat[kind] = (o, d, b, M, S)
    T = texture_size
    raw = torch.zeros(1, 6, 4, T, T)
    raw[:, :, 3] = 3.0
    scale = item["im"].clamp(min=0).mean()
    raw[:, :, :3] = math.log(float(scale))
    raw.requires_grad_(True)
    far = torch.full((1, 3, *FAR_SIZE), math.log(float(scale)), requires_grad=True)
    opt = torch.optim.Adam([raw, far], lr=lr)

    def predict(kind):
        o, d, b, M, S = flat[kind]
        room = {
            "rotation": rot[None],
            "lo": lo[None],
            "hi": hi[None],
            "textures": torch.cat([torch.exp(raw[:, :, :3]), torch.sigmoid(raw[:, :, 3:])], 2),
        }
        behind = torch.exp(far_lookup(far, d @ rot))
        return box_radiance(room, b, o, d, behind).view(M, S, 3).mean(1)

    curve = []
    for step in range(steps + 1):
        loss = sum(normalised_mse(predict(k), r.radiance) for k, r in rays.items())
        if step % max(1, steps // 10) == 0:
            curve.append({"step": step, "loss": float(loss.detach())})
        if step == steps:
            break
        opt.zero_grad()
        loss.backward()
        opt.step()
    out = {"curve": curve}
    with torch.no_grad():
        for kind, r in rays.items():
            pred = predict(kind)
            out[kind] = {"nmse": float(normalised_mse(pred, r.radiance))}
            for name, sel in classes[kind].items():
                out[kind][f"ray_fraction_{name}"] = float(sel.float().mean())
                if sel.any():
                    out[kind][f"nmse_{name}"] = float(normalised_mse(pred[sel], r.radiance[sel]))
        miss = [(predict(k)[classes[k]["miss"]], r.radiance[classes[k]["miss"]]) for k, r in rays.items()]
        p, t = torch.cat([m[0] for m in miss]), torch.cat([m[1] for m in miss])
        out["miss_nmse"] = float(normalised_mse(p, t)) if len(t) else None
    return out


def layout_errors(dataset, source_root: Path, count: int) -> dict:
    """The estimated box against the true one on the first `count` views: rotation angle (degrees) and,
    per face, |estimated - true| distance (metres)."""
    angles, faces = [], {f: [] for f in FACES}
    for i in tqdm(range(min(count, len(dataset))), desc="layout"):
        item = dataset[i]
        rot_t, lo_t, hi_t = true_box(source_root, item["id"])
        rot_e, lo_e, hi_e = estimated_box(item)
        angles.append(rotation_error_deg(rot_t, rot_e))
        if angles[-1] > 10:  # a different labelling of the axes: faces are not comparable
            continue
        for k, f in enumerate(FACES):
            axis, side = divmod(k, 2)
            true = (hi_t if side else lo_t)[axis]
            est = (hi_e if side else lo_e)[axis]
            faces[f].append(abs(float(est - true)))
    summary = {
        "views": len(angles),
        "rotation_deg_median": float(np.median(angles)),
        "rotation_deg_p90": float(np.percentile(angles, 90)),
        "rotation_over_10deg": int(sum(a > 10 for a in angles)),
        "face_error_m_median": {f: float(np.median(v)) if v else None for f, v in faces.items()},
        "face_error_m_p90": {f: float(np.percentile(v, 90)) if v else None for f, v in faces.items()},
    }
    return summary


def run(data_dir="outputs/preprocess", views=(0, 1, 2, 3), texture_size=32, steps=600, lr=0.05, layout_views=64):
    from pipeline.data.datasets import ShardDataset

    manifest = json.loads((Path(data_dir) / "manifest.json").read_text())
    source_root = Path(manifest["source_root"])
    if not source_root.is_dir():
        raise FileNotFoundError(f"{data_dir}/manifest.json: source_root {source_root} (the room files) is missing")
    train = ShardDataset(data_dir, "train", lighting=True)
    report = {
        "data_dir": str(data_dir),
        "texture_size": texture_size,
        "far_size": list(FAR_SIZE),
        "steps": steps,
        "lr": lr,
        "views": [],
        "layout": layout_errors(train, source_root, layout_views),
    }
    for i in views:
        item = train[i]
        row = {"index": i, "id": item["id"]}
        boxes = {"gt": true_box(source_root, item["id"]), "predicted": estimated_box(item)}
        for layout in LAYOUTS:
            row[layout] = fit_view(item, boxes[layout], texture_size, steps, lr)
            print(item["id"], layout, row[layout]["miss_nmse"], row[layout]["surf"]["nmse"])
        report["views"].append(row)
    report["summary"] = summarise(report)
    return report


def summarise(report: dict) -> dict:
    """The headline: per layout the median and largest miss-ray nMSE over the fitted views, the box
    estimate's rotation error and per-face median distance error, and one row per view."""
    out = {}
    for layout in LAYOUTS:
        vals = [v[layout]["miss_nmse"] for v in report["views"] if v[layout]["miss_nmse"] is not None]
        out[f"{layout}_box_miss_nmse_median"] = float(np.median(vals)) if vals else None
        out[f"{layout}_box_miss_nmse_max"] = float(np.max(vals)) if vals else None
    lay = report["layout"]
    out["layout_views"] = lay["views"]
    out["rotation_error_deg_median"] = lay["rotation_deg_median"]
    out["rotation_error_deg_p90"] = lay["rotation_deg_p90"]
    out["face_error_m_median"] = {f: v for f, v in lay["face_error_m_median"].items() if v is not None}
    out["views"] = [
        {
            "view": v["id"],
            "gt box: miss nMSE": v["gt"]["miss_nmse"],
            "gt box: surface nMSE": v["gt"]["surf"]["nmse"],
            "predicted box: miss nMSE": v["predicted"]["miss_nmse"],
            "predicted box: surface nMSE": v["predicted"]["surf"]["nmse"],
        }
        for v in report["views"]
    ]
    return out


def plot(report: dict, path) -> None:
    fig = Figure(figsize=(9, 3.4))
    ax = fig.add_subplot(1, 2, 1)
    x = np.arange(len(report["views"]))
    for j, layout in enumerate(LAYOUTS):
        ax.bar(x + 0.4 * j, [v[layout]["miss_nmse"] or 0 for v in report["views"]], 0.4, label=f"{layout} box")
    ax.axhline(0.05, color="k", lw=0.8, ls="--", label="0.05")
    ax.set_xticks(x + 0.2, [v["id"] for v in report["views"]], rotation=30, fontsize=7)
    ax.set_ylabel("miss-ray nMSE after the fit")
    ax.set_title("free box textures fitted to one room's probes", fontsize=9)
    ax.legend(fontsize=7)
    ax = fig.add_subplot(1, 2, 2)
    lay = report["layout"]
    med = [lay["face_error_m_median"][f] or 0 for f in FACES]
    p90 = [lay["face_error_m_p90"][f] or 0 for f in FACES]
    ax.bar(np.arange(6) - 0.2, med, 0.4, label="median")
    ax.bar(np.arange(6) + 0.2, p90, 0.4, label="90th percentile")
    ax.set_xticks(np.arange(6), FACES, fontsize=7)
    ax.set_ylabel("|estimated - true| face distance (m)")
    ax.set_title(
        f"box estimate, {lay['views']} views: rotation {lay['rotation_deg_median']:.1f} deg median", fontsize=9
    )
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data-dir", default="outputs/preprocess")
    p.add_argument("--views", type=int, nargs="+", default=[0, 1, 2, 3])
    p.add_argument("--texture-size", type=int, default=32)
    p.add_argument("--steps", type=int, default=600)
    p.add_argument("--lr", type=float, default=0.05)
    p.add_argument("--layout-views", type=int, default=64)
    p.add_argument("--name", default="roombox_floor")
    add_threads_option(p)
    a = p.parse_args(argv)
    apply_threads(a.threads)
    report = run(a.data_dir, a.views, a.texture_size, a.steps, a.lr, a.layout_views)
    print(publish(a.name, report, plot))


if __name__ == "__main__":
    main()
