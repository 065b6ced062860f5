"""The room around an inserted object, scored: the shadow and bounce light that differential rendering
(`models.shadows`) adds to the photo, against the change Mitsuba's render shows there.

`synthesize` stores, for every object case, its surroundings (the room's pixels within a few bounding
radii of it) and Mitsuba's render there with the object minus without it (`ring_delta`, paired renders).
The reference is the photo plus that change; a row's prediction is the photo plus its own change: none for
the plain composite (`no_shadows`, what insertion without differential rendering leaves), or the
difference `models.shadows` renders under the row's light on a proxy of the room, clamped so that no pixel
goes below black (as `invrender insert` composites it). The stage places each object where it truly is
(its own pixels are scored so), so the proxy's geometry (depth, normals) is the ground truth's, where the
object truly stands, and its materials are the predicted ones. Both share the photo, so only the change is
judged. Scores, PSNR after the stage's tone map:
- `psnr` on the ring: the pixels the object changes in Mitsuba's render (its luminance change beyond
  `SIGNIFICANT` standard errors and `FLOOR` of the photo's luminance there); NaN where it changes none;
- `psnr_surround` on every pixel of the surroundings (a row that darkens pixels the object leaves alone is
  penalised there).
Every row's change is rendered at the same pixels (the true surroundings) with the same sample directions
(one seed per case), so rows are paired.
"""

from __future__ import annotations

import numpy as np
import torch

from pipeline.metrics.bootstrap import paired_bootstrap
from pipeline.metrics.image import psnr_tonemapped
from pipeline.models.insertion import cast_shape, render_case
from pipeline.models.shadows import facing_camera, occlusion_light

RING_ROWS = ("lightnet", "scaled_constant", "nearest_probe")  # lights differential rendering is scored under
NO_SHADOWS = "no_shadows"  # the composite without differential rendering: the photo left as it is
SIGNIFICANT = 3.0  # standard errors of Mitsuba's change for a pixel to count as changed
FLOOR = 0.01  # ... and at least this share of the photo's luminance there
LUMINANCE = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)


def ring_row(row: str) -> str:
    """The name a row's ring scores are recorded under (`ring_<row>`)."""
    return f"ring_{row}"


def changed_pixels(delta: torch.Tensor, stderr: torch.Tensor, base: torch.Tensor) -> torch.Tensor:
    """(K,) bool: the pixels whose luminance Mitsuba's change delta (K, 3), with standard errors stderr
    (K, 3), moves by more than `SIGNIFICANT` standard errors and by more than `FLOOR` of the luminance of
    base (K, 3), the photo there (HDR radiance)."""
    change = (delta.double() @ LUMINANCE).abs()
    se = ((stderr.double() ** 2) @ (LUMINANCE**2)).sqrt()
    return (change > SIGNIFICANT * se) & (change > FLOOR * (base.double() @ LUMINANCE).abs())


def view_spheres(spheres: list, world_from_view: np.ndarray) -> torch.Tensor:
    """(S, 4) float64 view-space spheres (centre metres, radius) of an object's world-space sphere list."""
    s = np.asarray(spheres, np.float64)
    centres = (s[:, :3] - world_from_view[:3, 3]) @ world_from_view[:3, :3]
    return torch.from_numpy(np.concatenate([centres, s[:, 3:]], 1))


def view_shape(description: dict, world_from_view: np.ndarray):
    """An object case's shape in view space, as `models.insertion.cast_shape` takes it: its triangles
    (vertices (V, 3) float64 metres, faces (F, 3) long) when its description has a `mesh`, else its
    spheres (`view_spheres`)."""
    mesh = description.get("mesh")
    if mesh is None:
        return view_spheres(description["spheres"], world_from_view)
    vertices = (np.asarray(mesh["vertices"], np.float64) - world_from_view[:3, 3]) @ world_from_view[:3, :3]
    return torch.from_numpy(vertices), torch.as_tensor(np.asarray(mesh["faces"], np.int64))


def ring_change(
    layer,
    gbuffer: dict,
    fov_x: float,
    pixels: torch.Tensor,
    light,
    shape,
    radiance: torch.Tensor,
    seed: int,
    guide=None,
) -> torch.Tensor:
    """(K, 3) the object's change to the room at `pixels` (K,): differential rendering (`models.shadows`)
    of the G-buffers `gbuffer` (normals facing the camera) under `light`, the object `shape` (view space)
    sending radiance (3,), the mean of its rendered pixels, where it blocks a sample ray."""
    if not len(pixels):
        return torch.zeros(0, 3)
    blocked = occlusion_light(light, [shape], radiance.reshape(1, 3), cast_shape)
    return render_case(layer, facing_camera(gbuffer, fov_x), fov_x, pixels, blocked, seed, guide)


def ring_scores(photo: torch.Tensor, case, changes: dict[str, torch.Tensor], scale: float) -> dict[str, dict]:
    """{ring_<row>: {psnr, psnr_surround}} for `no_shadows` and every row of `changes` ({row: (K, 3)
    change at case.ring_pixel}), against the photo (H, W, 3) plus Mitsuba's change (`case.ring_delta`);
    NaN where there is nothing to score (no surroundings, or no changed pixel for `psnr`)."""
    base = photo.double().reshape(-1, 3)[case.ring_pixel]
    target = base + case.ring_delta.double()
    changed = changed_pixels(case.ring_delta, case.ring_stderr, base)
    s = torch.full((len(base),), float(scale), dtype=torch.float64)
    out = {}
    for row, change in {NO_SHADOWS: torch.zeros_like(base), **changes}.items():
        pred = (base + change.double()).clamp(min=0)
        out[ring_row(row)] = {
            "psnr": float(psnr_tonemapped(pred[changed], target[changed], s[changed])) if changed.any() else np.nan,
            "psnr_surround": float(psnr_tonemapped(pred, target, s)) if len(base) else np.nan,
        }
    return out


RING_SCORES = ("psnr", "psnr_surround")


def summarise_ring(records: list[dict], rows: tuple, resamples: int, seed: int) -> dict[str, float]:
    """The ring's summary over the object cases of `records` (the stage's per-case records, with
    `ring_<row>/<score>`), per material class and all: `insert/<group>/ring/cases` (cases with a ring,
    i.e. changed pixels), each row's mean score (`no_shadows` and `rows`, cases where it is finite), and
    paired bootstrap intervals (whole views resampled) with a verdict (+1 above 0, -1 below, 0 neither) of
    every row minus `no_shadows` and of `lightnet` minus every other row."""
    objects = [r for r in records if r["kind"] == "object" and ring_row(NO_SHADOWS) + "/psnr" in r]
    groups: dict[str, list[dict]] = {}
    for r in objects:
        groups.setdefault(r["label"], []).append(r)
        groups.setdefault("all", []).append(r)
    names = (NO_SHADOWS, *rows)
    pairs = [(row, NO_SHADOWS) for row in rows] + [("lightnet", row) for row in rows if row != "lightnet"]
    metrics: dict[str, float] = {}
    for group, rs in sorted(groups.items()):
        key = f"insert/{group}/ring"
        metrics[f"{key}/cases"] = float(sum(np.isfinite(r[f"{ring_row(NO_SHADOWS)}/psnr"]) for r in rs))
        for score in RING_SCORES:
            for name in names:
                values = [r[f"{ring_row(name)}/{score}"] for r in rs]
                values = [v for v in values if np.isfinite(v)]
                if values:
                    metrics[f"{key}/{name}/{score}"] = float(np.mean(values))
            for a, b in pairs:
                kept = [
                    r
                    for r in rs
                    if np.isfinite(r[f"{ring_row(a)}/{score}"]) and np.isfinite(r[f"{ring_row(b)}/{score}"])
                ]
                if not kept:
                    continue
                diff = [r[f"{ring_row(a)}/{score}"] - r[f"{ring_row(b)}/{score}"] for r in kept]
                ci = paired_bootstrap(diff, resamples, seed, groups=[r["view"] for r in kept])
                name = f"{key}/{a}_minus_{b}/{score}"
                metrics[f"{name}_diff"] = ci["diff"]
                if np.isfinite(ci["lo"]):
                    metrics[f"{name}_lo"], metrics[f"{name}_hi"] = ci["lo"], ci["hi"]
                    metrics[f"{name}_verdict"] = 1.0 if ci["lo"] > 0 else (-1.0 if ci["hi"] < 0 else 0.0)
                else:  # one view: no interval, and no verdict either way
                    metrics[f"{name}_verdict"] = 0.0
    return metrics
