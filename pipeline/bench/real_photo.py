"""`python -m pipeline.bench.real_photo`: objects inserted into a real indoor photograph, as a user would.

The photo is scikit-image's `stereo_motorcycle` (the Middlebury 2014 stereo benchmark's Motorcycle, left
view, 741x500 sRGB, a motorcycle in a lab), with its calibration (focal length 994.978 px: a horizontal field
of view of 40.9 degrees) and its measured disparity map. Through the path `invrender insert` runs
(`models.insertion.insert_into`): MaterialNet's G-buffers, then for each LightNet export given
(`--light-net NAME=PATH`, e.g. one per out-of-view branch) a mirror sphere, a glossy and a diffuse vase
(`ops.meshes.vase`, a mesh) resting on the floor. The three pixels come from the predicted normals: in the
lowest third of the image, where the normal points up (view-space y > 0.8), at the candidates nearest to a
quarter, half and three quarters of the width.

Also MaterialNet's depth against the stereo depth (Z = f B / (d + dx) from the disparity, the benchmark's
baseline B and offset dx): over the pixels with a disparity, the RMSE of the log ratio about its mean (the
scale taken out, every depth counted, unlike the NYUv2 protocol's 1-10 m) and the median ratio.
Writes reports/bench/real_photo.png (the photo, then one row per export) and real_photo.json (the pixels,
seconds per insertion, each object's pixel count, the depth check).
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch
from matplotlib.figure import Figure

from pipeline.bench.common import publish
from pipeline.data.formats.photo import linear_to_srgb, srgb8_to_linear
from pipeline.models.insertion import OBJECT_MATERIALS, InsertedObject, insert_into, prepare_view
from pipeline.models.light_net import load_light_export
from pipeline.models.material_net import load_material_export
from pipeline.ops.meshes import vase as vase_mesh

FOCAL_PX, BASELINE_M, DOFFS_PX = 994.978, 0.193001, 31.086  # the down-sampled images' calibration


def photo() -> tuple[np.ndarray, np.ndarray, float]:
    """(linear image (H, W, 3) float32, stereo depth (H, W) metres, NaN without a disparity, fov_x degrees)."""
    from skimage.data import stereo_motorcycle

    left, _, disparity = stereo_motorcycle()
    disparity = disparity.astype(np.float64)
    known = np.isfinite(disparity) & (disparity > 0)  # the benchmark marks pixels without a match inf
    depth = np.where(known, FOCAL_PX * BASELINE_M / (np.where(known, disparity, 0.0) + DOFFS_PX), np.nan)
    fov = math.degrees(2 * math.atan(left.shape[1] / 2 / FOCAL_PX))
    return np.ascontiguousarray(srgb8_to_linear(left), np.float32), depth, fov


def floor_pixels(normal: torch.Tensor, depth: torch.Tensor, count: int = 3) -> list[tuple[int, int]]:
    """`count` pixels (row, col) on the floor: in the lowest third, normal (3, H, W) view-space y > 0.8, a
    valid depth, nearest to evenly spread columns at 85 % of the height."""
    _, H, W = normal.shape
    rows, cols = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    ok = (rows >= 2 * H // 3) & (normal[1] > 0.8) & (depth > 0) & torch.isfinite(depth)
    if not ok.any():
        raise ValueError("no floor found in the lowest third of the photo (no predicted normal points up)")
    r, c = rows[ok].double(), cols[ok].double()
    out = []
    for k in range(count):
        target_c, target_r = (k + 1) * W / (count + 1), 0.85 * H
        i = int(torch.argmin((r - target_r) ** 2 + (c - target_c) ** 2))
        out.append((int(r[i]), int(c[i])))
    return out


def objects_at(pixels: list[tuple[int, int]]) -> list[InsertedObject]:
    """A mirror sphere, a glossy and a diffuse vase at the three pixels."""
    vase = vase_mesh()
    shapes = ("sphere", vase, vase)
    return [
        InsertedObject(shape, r, c, OBJECT_MATERIALS[m], turn=0.0, label=f"object {k + 1}")
        for k, ((r, c), shape, m) in enumerate(zip(pixels, shapes, ("mirror", "glossy", "diffuse"), strict=True))
    ]


def run(material_path: str, lights: dict[str, str], spp: int, seed: int) -> dict:
    im, stereo_depth, fov = photo()
    material = load_material_export(material_path)
    settings = {"photo": "skimage.data.stereo_motorcycle (left)", "fov_x_deg": fov, "spp": spp, "seed": seed}
    report = {"settings": settings, "measured": {"insertions": []}}
    images = {"photo": im}
    for name, path in lights.items():
        net, _ = load_light_export(path)
        net.eval()
        t0 = time.perf_counter()
        view = prepare_view(im, *material, net, fov)
        pixels = floor_pixels(view.pred["normal"][0], view.pred["depth"][0])
        result, changed = insert_into(view, objects_at(pixels), spp, seed)
        seconds = time.perf_counter() - t0
        images[name] = result.numpy()
        report["measured"]["insertions"].append(
            {
                "light_net": name,
                "path": path,
                "pixels": str(pixels),
                "seconds (MaterialNet, LightNet, three objects)": seconds,
                "object_pixels": int(len(changed)),
            }
        )
        report.setdefault("pixels", {})[name] = pixels
        if "depth_pixels_with_disparity" not in report["measured"]:
            pred = view.pred["depth"][0].double()
            valid = torch.from_numpy(np.isfinite(stereo_depth)) & (pred > 0)  # NaN: no disparity there
            truth = torch.from_numpy(np.nan_to_num(stereo_depth))
            log_ratio = (pred[valid] / truth[valid]).log()
            report["measured"].update(
                {
                    "depth_pixels_with_disparity": int(valid.sum()),
                    # the scale a single photo cannot fix taken out: log errors about their mean (every depth)
                    "depth_log_rmse_after_scale": float((log_ratio - log_ratio.mean()).pow(2).mean().sqrt()),
                    "depth_median_ratio_predicted_over_stereo": float(log_ratio.median().exp()),
                    "stereo_depth_median_m": float(truth[valid].median()),
                }
            )
    report["images"] = images
    return report


def plot(report: dict, path) -> None:
    images = report["images"]
    fig = Figure(figsize=(7.5, 2.6 * len(images)))
    for k, (name, image) in enumerate(images.items()):
        ax = fig.add_subplot(len(images), 1, k + 1)
        ax.imshow(linear_to_srgb(np.clip(image, 0, 1)))  # the photo's own 8-bit encoding
        if name != "photo":
            for r, c in report["pixels"][name]:
                ax.plot(c, r, "+", color="yellow", ms=5, mew=0.8)
        title = "the photo" if name == "photo" else f"LightNet {name}: mirror sphere, glossy and diffuse vase"
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--material-net", default="outputs/train_material/model.pt")
    p.add_argument(
        "--light-net",
        action="append",
        help="NAME=PATH of a LightNet export (repeat for several; default trained=outputs/train_lighting/model.pt)",
    )
    p.add_argument("--spp", type=int, default=64)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    lights = dict(x.split("=", 1) for x in (a.light_net or ["trained=outputs/train_lighting/model.pt"]))
    report = run(a.material_net, lights, a.spp, a.seed)
    images = report.pop("images")
    path = publish("real_photo", report, lambda r, out: plot({**r, "images": images}, out))
    print(path)


if __name__ == "__main__":
    main()
