"""`python -m pipeline.bench.probe_resolution`: how sharp must the light be for an inserted mirror?

LightNet learns the light from probes: texel averages of the true incident radiance, full spheres of
16 x 32 texels at free points on `tiny`. What a network fitted exactly to such targets could show is
bounded by their resolution, wherever its inductive bias comes from. For every object insertion case of
the `edit` stage's test views, this renders with Mitsuba the true incident radiance at the object's own
centre (in the room without the object; every texel the mean of a k x k stratified grid of directions
inside it, as the training probes are), at the probes' resolution and finer ones, and renders the object
under each map as a distant environment (the `edit` stage's `nearest_probe` lookup and per-case seeds)
against Mitsuba's render of the case. The centre maps are rendered at `--spp` samples per pixel (default:
the `edit` stage's `scoring.spp`) with the stage's scoring layer, each map guiding its own samples as the
stage's nearest-probe row is guided, and so are LightNet's rows compared with them (`*_fine`), so that
rows compared here differ in their light, not their sample count; the stage's own rows keep their
`scoring.row_spp`. Whether a count is converged for a sharp map is `bench.scoring_convergence`'s question
(the stage's nearest-probe row needs 1024).

- `centre_<rows>x<cols>` at the training probes' size: the ceiling the supervision sets, for a LightNet
  that reproduced its training targets exactly at the object's centre (no error of position either);
- the finer maps: what resolution a given insertion PSNR needs (the oracle row, Mitsuba's radiance for
  every sample ray from every shading point, is the limit);
- `lightnet_fine`, `nearest_probe_fine`: LightNet's light and the nearest ground-truth probe's, rendered
  like the maps (the `edit` stage's `lightnet` and `nearest_probe` rows at its own spp are re-rendered
  too, and checked equal case by case to that stage's, so the seeds and directions are the stage's);
- `lightnet_true_out` and `lightnet_true_in`: which of LightNet's two sources costs the insertion. A ray
  is out of view where LightNet's SSRT confidence weight u >= 0.5 (its out-of-view branch carries it);
  `lightnet_true_out` is LightNet with those rays given the centre map at the first (training) size, as
  if the out-of-view branch had learnt its training target exactly; `lightnet_true_in` gives it to the
  other rays. Same seeds and directions as `lightnet_fine`.
Per material class and over all objects: the mean PSNR (dB) of each row, and paired bootstrap intervals
(resampling views) of each centre map minus LightNet and minus the nearest probe. With `--edit-cases`
(the `edit` stage's cases.csv) the oracle row's PSNR joins per case.
Needs the trained exports and `synthesize`'s cases (`dvc repro train_lighting`). Writes
reports/bench/probe_resolution.json (or `--out`), a PNG of PSNR against map width per class, and a
second PNG of mirror crops under each map.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure
from tqdm import tqdm

from pipeline.bench.common import edit_object_cases, write_report
from pipeline.data.synth import mitsuba_backend as mb
from pipeline.data.synth.scene import Room
from pipeline.metrics.bootstrap import paired_bootstrap
from pipeline.metrics.insertion import case_scores
from pipeline.models.insertion import composite_gbuffer, composite_image, render_case
from pipeline.ops.envmap import sphere_lookup, stratified_square, texel_directions

CLASSES = ("mirror", "glossy", "diffuse")
DEFAULT_SIZES = ("16x32", "32x64", "64x128")
EDIT_ROWS = ("lightnet", "nearest_probe")
SPLIT_ROWS = ("lightnet_true_out", "lightnet_true_in")
FINE_ROWS = ("lightnet_fine", *SPLIT_ROWS, "nearest_probe_fine")  # rendered at the fine spp, like the maps


def parse_sizes(texts) -> list[tuple[int, int]]:
    """['16x32', ...] -> [(16, 32), ...]: full-sphere maps of rows x cols texels, cols = 2 rows."""
    sizes = []
    for text in texts:
        rows, sep, cols = str(text).partition("x")
        try:
            r, c = int(rows), int(cols)
        except ValueError:
            r = c = 0
        if not sep or r < 2 or c != 2 * r:
            raise ValueError(f"--sizes {text!r}: give ROWSxCOLS with COLS = 2 ROWS >= 4 (e.g. 16x32)")
        sizes.append((r, c))
    if not sizes:
        raise ValueError("--sizes: give at least one map size")
    return sorted(set(sizes))


def row_name(size: tuple[int, int]) -> str:
    return f"centre_{size[0]}x{size[1]}"


def sphere_map(
    scene, position_view: np.ndarray, world_from_view: np.ndarray, size: tuple[int, int], strata: int, seed: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The true incident radiance at one view-space point (3,) metres as a full-sphere map laid out as the
    free-point probes are (`ops.envmap.sphere_directions`): (1, rows, cols, 3) texel means of a strata x
    strata stratified grid of directions each (one path per direction), and their standard errors."""
    from pipeline.data.synth.views import stratified_stderr

    rows, cols = size
    k, texels = int(strata), rows * cols
    gen = torch.Generator().manual_seed(int(seed))
    row = torch.arange(rows).repeat_interleave(cols)
    col = torch.arange(cols).repeat(rows)
    u = stratified_square(k, texels, gen)
    d_view = texel_directions(row, col, u, rows, cols).numpy().reshape(-1, 3)
    rot, origin = world_from_view[:3, :3], world_from_view[:3, 3]
    o = np.repeat((np.asarray(position_view, np.float64) @ rot.T + origin)[None], len(d_view), axis=0)
    L, _ = mb.radiance(scene, o, d_view @ rot.T, 1, seed=int(seed))
    L = L.reshape(rows, cols, k * k, 3)
    se = stratified_stderr(L.reshape(rows, cols, k, k, 3))
    return torch.from_numpy(L.mean(2)).float()[None], torch.from_numpy(se).float()[None]


def split_light(net, ctx: dict, scene: dict, fov_x: float, generator, truth: torch.Tensor, tally: dict) -> dict:
    """Radiance callbacks of LightNet (as `models.insertion.light_net_radiance` with its `generator`) and of
    LightNet with the rays it holds out of view (u >= 0.5), or the others, given the map `truth`
    (1, rows, cols, 3): {"lightnet", "lightnet_true_out", "lightnet_true_in"}. `tally` counts the
    `lightnet` callback's rays: {"rays", "out"}."""

    def make(part: str):
        def radiance(idx, origin, wi, image):
            out = net(ctx, scene, fov_x, origin, wi, image, generator)
            if part == "lightnet":
                tally["rays"] = tally.get("rays", 0) + len(wi)
                tally["out"] = tally.get("out", 0) + int((out["u"] >= 0.5).sum())
                return out["radiance"]
            true = sphere_lookup(truth, torch.zeros(len(wi), dtype=torch.long), wi).to(out["radiance"].dtype)
            outside = (out["u"] >= 0.5).unsqueeze(-1)
            return torch.where(outside if part == "lightnet_true_out" else ~outside, true, out["radiance"])

        return radiance

    return {part: make(part) for part in ("lightnet", *SPLIT_ROWS)}


def _edit_oracle(path: Path | None) -> dict[tuple[str, str], float]:
    """{(view, case): oracle PSNR} from the `edit` stage's cases.csv, or {} without one."""
    if path is None:
        return {}
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise FileNotFoundError(f"--edit-cases {path}: cannot read it ({exc})") from exc
    if rows and "oracle/psnr" not in rows[0]:
        raise ValueError(f"--edit-cases {path}: no 'oracle/psnr' column (is it the edit stage's cases.csv?)")
    return {(r["view"], r["case"]): float(r["oracle/psnr"]) for r in rows if r.get("kind") == "object"}


def summarise(records: list[dict], rows: list[str], resamples: int, seed: int) -> dict:
    """Per class and over all objects: mean PSNR per row, and paired bootstrap intervals (views) of the
    split rows and the `centre_*` rows minus `lightnet_fine`, and of the `centre_*` rows minus
    `nearest_probe_fine` (rows rendered at the same spp). records: {view, label, <row>: psnr}."""
    out = {}
    pairs = [(row, "lightnet_fine") for row in rows if row in SPLIT_ROWS or row.startswith("centre_")]
    pairs += [(row, "nearest_probe_fine") for row in rows if row.startswith("centre_")]
    for label in (*CLASSES, "all"):
        rs = [r for r in records if label == "all" or r["label"] == label]
        if not rs:
            continue
        present = [row for row in rows if all(row in r for r in rs)]
        entry = {"cases": len(rs), "views": len({r["view"] for r in rs})}
        entry["psnr"] = {row: float(np.mean([r[row] for r in rs])) for row in present}
        groups = [r["view"] for r in rs]
        entry["differences"] = {
            f"{row}_minus_{base}": paired_bootstrap([r[row] - r[base] for r in rs], resamples, seed, groups=groups)
            for row, base in pairs
            if row in present and base in present
        }
        out[label] = entry
    return out


def headline(classes: dict, rows: list[str]) -> list[dict]:
    """One row per class: the mean PSNR (dB) of every row (the results page's table)."""
    return [{"class": label, "cases": e["cases"], **{f"{r} (dB)": e["psnr"][r] for r in rows if r in e["psnr"]}}
            for label, e in classes.items()]  # fmt: skip


def headline_differences(classes: dict) -> list[dict]:
    """One row per class and paired difference against `lightnet_fine` (dB, 95 % interval over views)."""
    rows = []
    for label, e in classes.items():
        for name, d in e["differences"].items():
            if name.endswith("_minus_lightnet_fine"):
                rows.append({"class": label, "row minus lightnet_fine": name.removesuffix("_minus_lightnet_fine"),
                             "dB": d["diff"], "lo": d["lo"], "hi": d["hi"]})  # fmt: skip
    return rows


def _distant(radiance: torch.Tensor):
    """A full-sphere map (1, rows, cols, 3) as a distant light: the render layer's radiance callback."""

    def light(idx, origin, wi, batch_index):
        return sphere_lookup(radiance, torch.zeros_like(batch_index), wi)

    return light


def _lightnet_renders(ctx, v, shading, case, case_seed, generator, fine_layer, truth, tallies) -> dict:
    """The `lightnet` row at the stage's spp (advancing the view's generator as the `edit` stage does),
    then at the fine layer's spp LightNet alone and with either ray class given `truth`, each from the
    generator state the `lightnet` row started from; the generator is left where the `lightnet` row ended."""
    split = split_light(v.net, v.ctx_pred, v.pred, v.fov, generator, truth, tallies.setdefault(case.label, {}))
    before = generator.get_state()
    out = {"lightnet": render_case(ctx["layers"]["lightnet"], shading, v.fov, case.pixel, split["lightnet"], case_seed)}
    after = generator.get_state()
    for name, part in zip(("lightnet_fine", *SPLIT_ROWS), ("lightnet", *SPLIT_ROWS), strict=True):
        generator.set_state(before)
        out[name] = render_case(fine_layer, shading, v.fov, case.pixel, split[part], case_seed)
    generator.set_state(after)
    return out


def run(
    overrides: list[str],
    sizes: list[tuple[int, int]],
    strata: int,
    edit_cases: Path | None,
    figure_cases: int,
    spp: int | None = None,
    max_views: int | None = None,
    progress: bool = True,
) -> tuple[dict, list[dict]]:
    """Scores every object case of the test views of the `edit` configuration composed with `overrides`;
    returns the report and the mirror panels of the crop figure."""
    from pipeline.bench.common import compose
    from pipeline.systems import insertion_scoring

    cfg = compose("edit", overrides)
    shared = insertion_scoring.stage_setup(cfg)
    spp = int(cfg.scoring.spp) if spp is None else int(spp)
    fine_layer = insertion_scoring.scoring_layer(cfg, spp)
    oracle = _edit_oracle(edit_cases)
    names = [row_name(s) for s in sizes]
    records, panels, tallies = [], [], {}
    views = shared["views"][:max_views] if max_views else shared["views"]
    for scene, view in tqdm(views, desc="probe resolution", unit="view", disable=not progress):
        ctx, cases = insertion_scoring.view_context(shared, scene, view, cfg, oracle=False)
        v = ctx["view"]
        objects = edit_object_cases(ctx["id"], cases)
        if not objects:
            continue
        room = Room.from_json(json.loads((shared["root"] / scene / "scene.json").read_text()))
        mi_scene = mb.load_scene(room, shared["max_depth"])
        generator = torch.Generator().manual_seed(int(ctx["seed"]) + 1)  # as `light_net_radiance` seeds it
        for index, res in enumerate(insertion_scoring.score_view(ctx, objects, cfg, EDIT_ROWS)):
            case = res["case"]
            centre = insertion_scoring.case_centre(case, v.gt, v.fov, ctx["w2v"]).numpy()
            obj = {"albedo": case.albedo, "material": case.material, "normal": case.normal, "depth": case.depth}
            shading = composite_gbuffer(v.pred, case.pixel, **obj)
            case_seed = insertion_scoring.case_seed(int(ctx["seed"]), index)  # the seed `score_view` gives it
            probe = int(torch.argmin((ctx["light"].free.position - torch.from_numpy(centre)).norm(dim=-1)))
            maps = {"nearest_probe_fine": ctx["light"].free.radiance[probe : probe + 1]}
            for size, name in zip(sizes, names, strict=True):
                maps[name] = sphere_map(mi_scene, centre, ctx["w2v"], size, strata, case_seed + size[0])[0]
            renders = {}
            with torch.no_grad():
                lights = {n: _distant(m) for n, m in maps.items()}
                # each distant map guides its own samples, as `score_view` guides the nearest probe's
                guides = {n: insertion_scoring.probe_guide(m, cfg) for n, m in maps.items()}
                renders["nearest_probe"] = render_case(
                    ctx["layers"]["nearest_probe"],
                    shading,
                    v.fov,
                    case.pixel,
                    lights["nearest_probe_fine"],
                    case_seed,
                    guides["nearest_probe_fine"],
                )
                for name, light in lights.items():
                    renders[name] = render_case(fine_layer, shading, v.fov, case.pixel, light, case_seed, guides[name])
                renders.update(
                    _lightnet_renders(ctx, v, shading, case, case_seed, generator, fine_layer, maps[names[0]], tallies)
                )
            for name in EDIT_ROWS:
                if not torch.allclose(renders[name], res["renders"][name], rtol=1e-4, atol=1e-6):
                    raise RuntimeError(f"{ctx['id']} {case.name}: the {name} render differs from `edit`'s")
            rec = {"view": ctx["id"], "case": case.name, "label": case.label}
            for name in EDIT_ROWS:
                rec[name] = res["rows"][name]["psnr"]
            for name in (*FINE_ROWS, *names):
                rec[name] = case_scores(renders[name], case.radiance, v.photo, case.pixel, float(v.scale))["psnr"]
            if (ctx["id"], case.name) in oracle:
                rec["oracle"] = oracle[(ctx["id"], case.name)]
            records.append(rec)
            if case.label == "mirror" and len(panels) < figure_cases:
                shown = {n: renders[n] for n in ("lightnet_fine", "lightnet_true_out", "nearest_probe_fine", *names)}
                panels.append(
                    {
                        "label": f"{ctx['id']} {case.name}",
                        "photo": v.photo.numpy(),
                        "scale": float(v.scale),
                        "pixels": case.pixel.numpy(),
                        "gt": composite_image(v.photo, case.pixel, case.radiance).numpy(),
                        "rows": {n: composite_image(v.photo, case.pixel, r).numpy() for n, r in shown.items()},
                        "psnr": {n: rec[n] for n in shown},
                    }
                )
    if not records:
        raise ValueError(f"{cfg.data_root}: the {cfg.split} views' case files list no object case")
    rows = [*EDIT_ROWS, *FINE_ROWS, *names, *(["oracle"] if oracle else [])]
    classes = summarise(records, rows, int(cfg.bootstrap), int(cfg.seed))
    share = {label: t["out"] / t["rays"] for label, t in sorted(tallies.items()) if t.get("rays")}
    report = {
        "summary": {
            "insertion PSNR (dB), true light at the object's centre": headline(classes, rows),
            "paired differences from LightNet at the same spp": headline_differences(classes),
            "share of LightNet's sample rays held out of view (u >= 0.5)": share,
        },
        "light_path": str(cfg.light_path),
        "material_path": str(cfg.material_path),
        "split": str(cfg.split),
        "spp": {
            "lightnet": insertion_scoring.row_spp(cfg, "lightnet"),
            "nearest_probe": insertion_scoring.row_spp(cfg, "nearest_probe"),
            "centre maps": spp,
        },
        "sizes": [list(s) for s in sizes],
        "strata": int(strata),
        "rows": rows,
        "out_of_view_ray_share": share,
        "classes": classes,
        "cases": records,
    }
    return report, panels


def plot(report: dict, path: Path) -> None:
    """Per class: PSNR against the map's width (columns), with the other rows as horizontal lines."""
    labels = [c for c in (*CLASSES, "all") if c in report["classes"]]
    widths = [s[1] for s in report["sizes"]]
    fig = Figure(figsize=(3.2 * len(labels), 3.3))
    axes = fig.subplots(1, len(labels), squeeze=False)[0]
    r0, c0 = report["sizes"][0]
    styles = {  # row: (colour, line style, legend)
        "lightnet_fine": ("C0", "-", "LightNet"),
        "lightnet_true_out": ("C3", "-.", f"LightNet, true {r0}x{c0} light out of view"),
        "nearest_probe_fine": ("C1", "--", "nearest ground-truth probe"),
        "oracle": ("k", ":", "oracle (edit stage, 1 path per ray)"),
    }
    for ax, label in zip(axes, labels, strict=True):
        entry = report["classes"][label]
        curve = [entry["psnr"][f"centre_{r}x{c}"] for r, c in report["sizes"]]
        ax.plot(widths, curve, "o-", color="C2", label="true light at the object's centre")
        for row, (colour, ls, legend) in styles.items():
            if row in entry["psnr"]:
                ax.axhline(entry["psnr"][row], color=colour, ls=ls, lw=1, label=legend)
        ax.set_xscale("log", base=2)
        ax.set_xticks(widths)
        ax.set_xticklabels([f"{r}x{c}" for r, c in report["sizes"]], fontsize=7)
        ax.set_xlabel("map size (rows x columns)")
        ax.set_title(f"{label} ({entry['cases']} cases)", fontsize=9)
    axes[0].set_ylabel("insertion PSNR (dB)")
    axes[0].legend(fontsize=6)
    fig.suptitle("insertion under the true incident radiance at the object's centre, by map resolution", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default="outputs/train_lighting/model.pt", help="LightNet export")
    p.add_argument("--material", default="outputs/train_material/model.pt", help="MaterialNet export")
    p.add_argument("--sizes", nargs="+", default=list(DEFAULT_SIZES), help="map sizes ROWSxCOLS")
    p.add_argument("--strata", type=int, default=8, help="k: k x k directions per texel (training probes: 8)")
    p.add_argument("--spp", type=int, default=None, help="render spp of the centre maps (default: edit's scoring.spp)")
    p.add_argument("--edit-cases", default="reports/edit/cases.csv", help="the edit stage's cases.csv ('' for none)")
    p.add_argument("--figure-cases", type=int, default=6, help="mirror cases in the crop figure")
    p.add_argument("--views", type=int, default=None, help="only the first N test views (a quick look)")
    p.add_argument("--out", default="reports/bench/probe_resolution.json", help="JSON to write (PNGs beside it)")
    p.add_argument("--override", nargs="*", default=[], help="more `edit` config overrides (data_root=...)")
    a = p.parse_args(argv)
    try:
        sizes = parse_sizes(a.sizes)
    except ValueError as exc:
        p.error(str(exc))
    if a.strata < 2 or a.strata % 2:
        p.error(f"--strata {a.strata}: give an even number >= 2 (the standard error pairs cells)")
    out = Path(a.out)
    overrides = [f"light_path={a.model}", f"material_path={a.material}", *a.override]
    edit_cases = Path(a.edit_cases) if a.edit_cases else None
    report, panels = run(overrides, sizes, a.strata, edit_cases, a.figure_cases, a.spp, a.views)
    write_report("probe_resolution", report, path=out)
    plot(report, out.with_suffix(".png"))
    if panels:
        from pipeline.tracking.figures import insertion_grid

        insertion_grid(panels, out.with_name(out.stem + "_mirrors.png"), "mirror spheres under each light (crops)")
    for label, entry in report["classes"].items():
        cells = ", ".join(f"{row} {v:.2f}" for row, v in entry["psnr"].items())
        print(f"{label:8s} {cells}")
    print(out)


if __name__ == "__main__":
    main()
