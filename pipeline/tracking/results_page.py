"""docs/results.md, written by the `report` stage from the files the stages and benches wrote under
reports/: nothing in it is typed by hand, and it computes no interval of its own: each is read from the
metrics the stage or bench that made it published (`evaluate` publishes the stage sections' intervals over
the test views and images, `edit` the insertion's, the `report` stage the ablation claims'). A test renders
it from the committed reports and requires it to equal the committed file, so it cannot drift from them.

`render(reports, ablation_tables)` returns the document; every section reads only its own files and says
which, and a section whose files are missing says so instead of printing numbers.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

EVALUATE = "evaluate/metrics.json"  # the stage that publishes the intervals of the stage sections

MATERIAL_METRICS = ("albedo_mse", "normal_angle_deg", "roughness_mse", "metallic_mse", "depth_log_mse")
LIGHT_METRICS = (
    ("render_psnr", "re-render PSNR (dB)"),
    ("surf_light_nmse", "surface nMSE"),
    ("free_light_nmse", "free nMSE"),
    ("surf_light_relmse", "surface relMSE"),
    ("free_light_relmse", "free relMSE"),
    ("surf_light_log_l1", "surface log-L1"),
    ("free_light_log_l1", "free log-L1"),
)
LIGHT_BASELINES = ("constant", "scaled_constant", "probe_mean_oracle", "probe_median_oracle", "probe_profile_oracle")
EDIT_ROWS = ("lightnet", "lightnet_gt_gbuffers", "constant", "scaled_constant", "nearest_probe", "oracle")
INSERT_GROUPS = ("mirror", "glossy", "diffuse", "all")


def num(v, digits: int = 4) -> str:
    """A number as the document prints it: 4 significant digits, n/a for missing or non-finite."""
    if v is None or isinstance(v, str) or not math.isfinite(float(v)):
        return "n/a"
    return f"{float(v):.{digits}g}"


def interval(lo, hi) -> str:
    return "n/a" if not (math.isfinite(lo) and math.isfinite(hi)) else f"[{num(lo)}, {num(hi)}]"


def signed(v) -> str:
    return "n/a" if not math.isfinite(v) else f"{v:+.4g}"


def md_table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header), *("| " + " | ".join(r) + " |" for r in rows)]


def read_json(path: Path) -> dict | None:
    """The JSON object at `path`, or None when the file is absent; a corrupt file raises naming it."""
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not valid JSON ({e})") from e
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data


def read_views(path: Path) -> dict[str, np.ndarray] | None:
    """Per-view scores {column: (n,) array} of a CSV whose first column is the view id; None if absent.
    Non-numeric or non-finite cells raise naming the file, row and column."""
    if not path.is_file():
        return None
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    if len(rows) < 2:
        raise ValueError(f"{path}: no per-view rows")
    header, body = rows[0], rows[1:]
    cols: dict[str, np.ndarray] = {header[0]: np.array([r[0] for r in body])}
    for j, name in enumerate(header[1:], start=1):
        values = []
        for i, r in enumerate(body, start=2):
            try:
                values.append(float(r[j]))
            except (IndexError, ValueError) as e:
                raise ValueError(f"{path}: row {i}, column {name!r} is not a number") from e
        cols[name] = np.asarray(values)
    return cols


MODELS = ("trained", "finetuned")  # the evaluate stage's MaterialNet models, in its CSVs' names


def model_scores(views: dict[str, np.ndarray] | None) -> dict[str, np.ndarray] | None:
    """A per-view table without its baselines' columns: the id, then the model's own scores (a
    `<model>_<split>_views.csv` names them `model/<metric>`; the benchmarks' CSVs hold nothing else)."""
    if views is None or not any(k.startswith("model/") for k in views):
        return views
    id_col = next(iter(views))
    return {id_col: views[id_col], **{k.removeprefix("model/"): v for k, v in views.items() if k.startswith("model/")}}


def shown(reports: Path, path: Path) -> str:
    """`path` as the document names it: under `reports/`, wherever the reports folder is."""
    return "reports/" + path.relative_to(reports).as_posix()


def missing(section: str, path: Path) -> list[str]:
    return [
        f"No `{path.name}` in `{path.parent.name}/`: run the stage that writes it (`dvc repro`) "
        f"to fill this {section}.",
        "",
    ]


def section_data(reports: Path) -> list[str]:
    syn, pre = read_json(reports / "synthesize/metrics.json"), read_json(reports / "preprocess/metrics.json")
    lines = [
        "## Data counters",
        "",
        "From `reports/synthesize/metrics.json` and `reports/preprocess/metrics.json`.",
        "",
    ]
    rows = [[f"synthesize: {k}", num(v)] for k, v in sorted((syn or {}).items()) if isinstance(v, int | float)]
    rows += [[f"preprocess: {k}", num(v)] for k, v in sorted((pre or {}).items()) if isinstance(v, int | float)]
    return lines + (md_table(["quantity", "value"], rows) if rows else ["No data reports."]) + [""]


def section_material(reports: Path, facts: dict | None = None) -> list[str]:
    path = reports / "train_material/metrics.json"
    m = read_json(path)
    lines = ["## MaterialNet (`train_material`, test split)", ""]
    if m is None:
        return lines + missing("section", path)
    ev = read_json(reports / EVALUATE) or {}
    lines += [
        f"From `{shown(reports, path)}`.",
        "Gate ratio: the model's error over the baseline's on the same views (lower is better); the gate",
        "passes when every ratio is at most the stage's margin. Intervals: 95 % bootstrap over test views,",
        f"model and baseline resampled together, from `reports/{EVALUATE}` (`evaluate` scores this model on",
        "the same views: `reports/evaluate/trained_synthetic_views.csv`).",
        "",
    ]
    rows = []
    for metric in MATERIAL_METRICS:
        for key in sorted(k for k in m if k.startswith("baseline/") and k.endswith(f"/{metric}")):
            base = key.split("/")[1]
            ci = published_interval(ev, f"trained/synthetic/gate/{base}/{metric}")
            ratio = m.get(f"gate/{base}/{metric}")
            rows.append([metric, num(m.get(f"test/{metric}")), base, num(m[key]), num(ratio), ci])
            if facts is not None:
                facts.setdefault("material", []).append((metric, m.get(f"test/{metric}"), base, m[key], ratio, ci))
    lines += md_table(["metric", "model", "baseline", "baseline's", "gate ratio", "ratio 95 % interval"], rows)
    passed = m.get("gate/passed")
    if facts is not None:
        facts["material_gate"] = passed
    lines += [
        "",
        f"Gate passed: {'yes' if passed == 1 else 'no' if passed == 0 else 'n/a'}. "
        f"Epochs {num(m.get('epochs'))}, steps {num(m.get('global_step'))}, "
        f"parameters {num(m.get('parameters'), 7)}.",
        "",
    ]
    return lines


def section_lighting(reports: Path, facts: dict | None = None) -> list[str]:
    path = reports / "train_lighting/metrics.json"
    m = read_json(path)
    lines = ["## LightNet (`train_lighting`, test split)", ""]
    if m is None:
        return lines + missing("section", path)
    modes = sorted({k.split("/test/")[0] for k in m if "/test/" in k and not k.startswith("baseline/")})
    lines += [
        f"From `{shown(reports, path)}`: each tested mode of the trained model (and the same network untrained),",
        "the constant lights and the probe oracles (which read the ground-truth probes) on the same views.",
        "Each number is the stage's: the metric of each test batch's pooled pixels or texels, averaged over",
        "batches (the per-view means in the paired table below are another aggregation and differ from it).",
        "",
    ]
    rows = []
    for name in modes:
        rows.append([f"LightNet `{name}`", *(num(m.get(f"{name}/test/{k}")) for k, _ in LIGHT_METRICS)])
    for b in LIGHT_BASELINES:
        if any(f"baseline/{b}/{k}" in m for k, _ in LIGHT_METRICS):
            rows.append([b, *(num(m.get(f"baseline/{b}/{k}")) for k, _ in LIGHT_METRICS)])
    lines += md_table(["predictor", *(label for _, label in LIGHT_METRICS)], rows)
    probes = {k.split("/")[1]: v for k, v in m.items() if k.endswith("/render_psnr_at_probes")}
    if probes:
        lines += ["", "Re-render PSNR at probe pixels (dB): " + ", ".join(f"{k} {num(v)}" for k, v in probes.items())]
    views = read_views(reports / "train_lighting/test_views.csv")
    if views:
        published = read_json(reports / EVALUATE) or {}
        lines += ["", *paired_rows(views, published, "lightnet/synthetic", "train_lighting/test_views.csv", facts)]
    lines.append("")
    return lines


def paired_rows(
    views: dict[str, np.ndarray], published: dict, prefix: str, source: str, facts: dict | None = None
) -> list[str]:
    """Paired per-view differences of the model's columns (`model/<metric>`, or `<mode>/<metric>` for
    the first mode) against every other predictor's same metric, as `evaluate` published them for the
    same views (`<prefix>/minus_<predictor>/<metric>` with `_lo`, `_hi`, `_n`); each is also recorded in
    `facts["paired"]` under (metric, other predictor) with the two per-view means over the views scored."""
    cols = [c for c in views if "/" in c]
    predictors = list(dict.fromkeys(c.split("/")[0] for c in cols))
    if not predictors:
        return []
    model = "model" if "model" in predictors else predictors[0]
    rows = []
    for col in cols:
        who, metric = col.split("/", 1)
        key = f"{prefix}/minus_{who}/{metric}"
        if who == model or f"{model}/{metric}" not in views or key not in published:
            continue
        d = {k: published.get(f"{key}{s}", float("nan")) for k, s in (("diff", ""), ("lo", "_lo"), ("hi", "_hi"))}
        d["n"] = published.get(f"{key}_n", float("nan"))
        rows.append([metric, f"{model} - {who}", num(d["n"]), signed(d["diff"]), interval(d["lo"], d["hi"])])
        if facts is not None:
            scored = np.isfinite(views[f"{model}/{metric}"] - views[col])
            means = (float(views[f"{model}/{metric}"][scored].mean()), float(views[col][scored].mean()))
            facts.setdefault("paired", {})[(metric, who)] = {**d, "means": means}
    head = [
        f"Paired per-view differences over the views of `reports/{source}`: the mean over views of each",
        f"view's own value (95 % bootstrap over views, published by `evaluate` in `reports/{EVALUATE}`):",
        "",
    ]
    return head + md_table(["metric", "difference", "views scored", "mean", "95 % interval"], rows)


def published_interval(published: dict, key: str) -> str:
    """`[lo, hi]` of the published `<key>_lo`, `<key>_hi`, or n/a."""
    lo, hi = published.get(f"{key}_lo"), published.get(f"{key}_hi")
    return "n/a" if lo is None or hi is None else interval(lo, hi)


def published_cell(published: dict, key: str, fmt: Callable = num, missing: str = "n/a") -> str:
    """`<value> [lo, hi]` of a published figure `<key>` (`fmt` writes the value), or `missing`."""
    return missing if key not in published else f"{fmt(published[key])} {published_interval(published, key)}"


def section_edit(reports: Path, facts: dict | None = None) -> list[str]:
    path = reports / "edit/metrics.json"
    m = read_json(path)
    lines = ["## Object insertion and material editing (`edit`)", ""]
    if m is None:
        return lines + missing("section", path)
    if facts is not None:
        facts["edit"] = m
    lines += [
        f"From `{shown(reports, path)}` and `reports/edit/timings.json`: PSNR (dB) on the case's pixels against",
        "Mitsuba's render of the same case. Differences are paired by case, with the stage's 95 % bootstrap",
        "interval over views; a difference whose interval holds 0 is no difference. The oracle's light (Mitsuba's",
        "paths for each sample ray) is noisy itself: its PSNR is the converged render's, estimated from independent",
        "parts of its samples (`oracle.psnr`: two halves, each extrapolated to infinite samples from its quarters,",
        "the product of their errors); beside, the product of the halves' errors alone (decorrelated) and its",
        "plain PSNR, noise included.",
        "",
    ]
    groups = [("insert", g) for g in INSERT_GROUPS] + sorted(
        {("edit", k.split("/")[1]) for k in m if k.startswith("edit/")}
    )
    header = ["row", *(f"{kind} {g}" for kind, g in groups)]
    rows = [["cases", *(num(m.get(f"{kind}/{g}/cases")) for kind, g in groups)]]
    for who in EDIT_ROWS:
        rows.append([who, *(num(m.get(f"{kind}/{g}/{who}/psnr")) for kind, g in groups)])
        for variant, name in (("psnr_decorrelated", "decorrelated"), ("psnr_with_noise", "plain")):
            if any(f"{kind}/{g}/{who}/{variant}" in m for kind, g in groups):  # a row scored in parts
                rows.append([f"{who}, {name} PSNR", *(num(m.get(f"{kind}/{g}/{who}/{variant}")) for kind, g in groups)])
    rows.append(["noise floor", *(num(m.get(f"{kind}/{g}/ground_truth/noise_floor_psnr")) for kind, g in groups)])
    lines += md_table(header, rows)
    lines += ["", "LightNet minus each other row, PSNR (dB):", ""]
    diff_rows = []
    for kind, g in groups:
        for who in EDIT_ROWS[1:]:
            p = f"{kind}/{g}/lightnet_minus_{who}/psnr"
            if f"{p}_diff" in m:  # no interval where a group's cases come from one view
                ci = interval(m[f"{p}_lo"], m[f"{p}_hi"]) if f"{p}_lo" in m else "n/a (one view)"
                diff_rows.append([f"{kind} {g}", who, signed(m[f"{p}_diff"]), ci])
    lines += md_table(["cases", "against", "difference", "95 % interval"], diff_rows)
    lines += shape_lines(m)
    lines += ring_lines(m, read_json(reports / "bench/scoring_convergence_ring.json"))
    a = {w: m.get(f"insert/all/{w}/psnr") for w in ("lightnet", "scaled_constant", "oracle")}
    if all(v is not None for v in a.values()) and a["oracle"] != a["scaled_constant"]:
        closed = (a["lightnet"] - a["scaled_constant"]) / (a["oracle"] - a["scaled_constant"])
        lines += [
            "",
            f"All objects: LightNet closes {closed:.1%} of the PSNR gap from the scaled constant to the oracle.",
        ]
    t = read_json(reports / "edit/timings.json") or {}
    per_case = {k.split("/", 1)[1]: v for k, v in t.items() if k.startswith("seconds_per_case/")}
    if per_case:
        lines += ["", "Seconds per case: " + ", ".join(f"{k} {num(v, 3)}" for k, v in sorted(per_case.items()))]
        lines[-1] += f"; the stage's wall time {num(t.get('wall_seconds'), 3)} s."
    lines.append("")
    return lines


OBJECT_SHAPES = ("sphere", "vase", "snowman")  # the insertion cases' shapes (the vase a triangle mesh)


def difference_cell(m: dict, key: str, missing: str) -> str:
    """`<diff> [lo, hi]` of a paired difference published as `<key>_diff`, `_lo`, `_hi`, or `missing` where
    it has no interval (cases from one view, or none)."""
    return f"{signed(m[f'{key}_diff'])} {interval(m[f'{key}_lo'], m[f'{key}_hi'])}" if f"{key}_lo" in m else missing


def shape_lines(m: dict, prefix: str = "") -> list[str]:
    """The insertion cases by the object's shape (`insert/<shape>`): each row's mean PSNR and LightNet minus
    the nearest probe and the scaled constant; [] when the metrics hold no shape group."""
    shapes = [g for g in OBJECT_SHAPES if f"{prefix}insert/{g}/cases" in m]
    if not shapes:
        return []
    lines = ["", "By the object's shape (the vase is a triangle mesh, the snowman two spheres), PSNR (dB):", ""]
    rows = [["cases", *(num(m[f"{prefix}insert/{g}/cases"]) for g in shapes)]]
    rows += [
        [who, *(num(m.get(f"{prefix}insert/{g}/{who}/psnr")) for g in shapes)]
        for who in EDIT_ROWS
        if f"{prefix}insert/{shapes[0]}/{who}/psnr" in m
    ]
    for who in ("nearest_probe", "scaled_constant"):
        p = [f"{prefix}insert/{g}/lightnet_minus_{who}/psnr" for g in shapes]
        cells = [difference_cell(m, k, "n/a (one view)") for k in p]
        if any(f"{k}_diff" in m for k in p):
            rows.append([f"lightnet - {who}", *cells])
    return lines + md_table(["row", *shapes], rows)


def ood_insertion_lines(reports: Path) -> list[str]:
    """The `edit` stage's insertion cases in the out-of-distribution rooms (`ood/` metrics) beside the test
    split's: each row's mean PSNR per class and LightNet minus each other row; [] without them."""
    m = read_json(reports / "edit/metrics.json") or {}
    if "ood/insert/all/cases" not in m:
        return []
    rows_ood = [who for who in EDIT_ROWS if f"ood/insert/all/{who}/psnr" in m]
    lines = [
        "",
        "Object insertion (`edit`, `reports/edit/metrics.json`, `ood/` keys; `reports/edit/ood_insertion.png`):",
        "PSNR (dB) on the objects' pixels, the test split's beside the out-of-distribution rooms', the same rows",
        "and scoring (no oracle on the latter).",
        "",
    ]
    header = ["row", *(f"{g}, {label}" for g in INSERT_GROUPS for label in ("test", "ood"))]
    rows = [["cases", *(num(m.get(f"{p}insert/{g}/cases")) for g in INSERT_GROUPS for p in ("", "ood/"))]]
    for who in rows_ood:
        rows.append([who, *(num(m.get(f"{p}insert/{g}/{who}/psnr")) for g in INSERT_GROUPS for p in ("", "ood/"))])
    lines += md_table(header, rows)
    diff_rows = []
    for g in INSERT_GROUPS:
        for who in rows_ood[1:]:
            key = f"insert/{g}/lightnet_minus_{who}/psnr"
            diff_rows.append([g, who, *(difference_cell(m, f"{p}{key}", "n/a") for p in ("", "ood/"))])
    lines += ["", "LightNet minus each other row, PSNR (dB), 95 % interval over views:", ""]
    lines += md_table(["objects", "against", "test", "out of distribution"], diff_rows)
    lines += shape_lines(m, "ood/")
    return lines


RING_ROWS = ("no_shadows", "lightnet", "scaled_constant", "nearest_probe")


def ring_lines(m: dict, convergence: dict | None = None) -> list[str]:
    """The room around inserted objects (`systems.ring_scoring`): each row's PSNR on the ring and on the
    whole surroundings, the paired differences, and each row's change at 4x the ring's samples where
    `bench.scoring_convergence --ring` measured it (`convergence`, its JSON); nothing when the stage
    scored no ring."""
    if "insert/all/ring/cases" not in m:
        return []
    lines = [
        "",
        "The room around each inserted object: the photo plus each row's shadow and bounce light (differential",
        "rendering under the row's light, the proxy's geometry where the object truly stands, its materials",
        "predicted; `no_shadows` leaves the photo as it is) against the photo plus Mitsuba's change (its render",
        "with the object minus without it). PSNR (dB) on",
        "the ring, the pixels the object changes in Mitsuba's render, and on all its surroundings (pixels within",
        f"3 bounding radii), at {num(m.get('scoring_spp/ring'))} samples per pixel; `reports/edit/shadows.png`.",
        "",
    ]
    ring = (convergence or {}).get("ring", {})
    moved = {k.removeprefix("ring_"): v["change_at_4x"].get("1") for k, v in ring.items()}
    moved = {k: v for k, v in moved.items() if v}
    if moved:
        lines += [
            f"Ring PSNR at 4x the samples minus at {num(convergence.get('ring_spp'))}, on "
            f"{num(convergence.get('views'))} test views (`reports/bench/scoring_convergence_ring.json`): "
            + ", ".join(f"{k} {_ci(v)}" for k, v in sorted(moved.items()))
            + ". A row that moves by more than 0.1 dB is not converged: its ring is scored low by its noise.",
            "",
        ]
    header = ["row", *(f"ring {g}" for g in INSERT_GROUPS), "surroundings all"]
    rows = [["cases", *(num(m.get(f"insert/{g}/ring/cases")) for g in INSERT_GROUPS), ""]]
    for who in RING_ROWS:
        cells = [num(m.get(f"insert/{g}/ring/{who}/psnr")) for g in INSERT_GROUPS]
        rows.append([who, *cells, num(m.get(f"insert/all/ring/{who}/psnr_surround"))])
    lines += md_table(header, rows)
    diffs = []
    for g in INSERT_GROUPS:
        for a, b in [(who, "no_shadows") for who in RING_ROWS[1:]] + [("lightnet", w) for w in RING_ROWS[2:]]:
            for score, where in (("psnr", "ring"), ("psnr_surround", "surroundings")):
                p = f"insert/{g}/ring/{a}_minus_{b}/{score}"
                if f"{p}_lo" in m and (score == "psnr" or g == "all"):
                    diffs.append(
                        [f"{where} {g}", f"{a} - {b}", signed(m[f"{p}_diff"]), interval(m[f"{p}_lo"], m[f"{p}_hi"])]
                    )
    return (
        lines
        + ["", "Paired differences on the ring (dB):", ""]
        + md_table(["cases", "rows", "difference", "95 % interval"], diffs)
    )


def section_evaluate(reports: Path) -> list[str]:
    path = reports / "evaluate/metrics.json"
    m = read_json(path)
    lines = ["## Real-data benchmarks (`evaluate`)", ""]
    if m is None:
        return lines + missing("section", path)
    src = read_json(reports / "evaluate/sources.json") or {}
    lines += [
        f"From `{shown(reports, path)}` (the per-image scores are the CSVs beside it): means with their 95 %",
        "bootstrap interval over images, and the fine-tuned model minus the trained one paired by image.",
    ]
    if src:
        lines.append("Data sources: " + ", ".join(f"{k}: {v}" for k, v in sorted(src.items()) if isinstance(v, str)))
    lines.append("")
    rows = []
    for bench, csv_name in (("iiw", "iiw"), ("nyu", "nyuv2"), ("synthetic", "synthetic_views")):
        trained, tuned = (model_scores(read_views(reports / f"evaluate/{m}_{csv_name}.csv")) for m in MODELS)
        if trained is None or tuned is None:
            continue
        for metric in list(trained)[1:]:
            if metric not in tuned:
                continue
            rows.append(
                [
                    f"{bench} {metric}",
                    str(len(trained[metric])),
                    *(published_cell(m, f"{model}/{bench}/{metric}") for model in MODELS),
                    published_cell(m, f"finetuned_minus_trained/{bench}/{metric}", signed, "n/a (different images)"),
                ]
            )
    lines += md_table(["metric", "images", "trained", "fine-tuned", "fine-tuned - trained"], rows)
    pooled = {
        k: v
        for k, v in m.items()
        if k.split("/")[0] in MODELS and ("pooled" in k or "whdr" in k) and not k.endswith(("_lo", "_hi"))
    }
    lines += ["", "Pooled figures: " + ", ".join(f"{k} {num(v)}" for k, v in sorted(pooled.items())), ""]
    return lines


OOD_GATES = (
    ("albedo_mse", "mean_albedo"),
    ("normal_angle_deg", "camera_facing_normal"),
    ("roughness_mse", "mean_material"),
    ("metallic_mse", "mean_material"),
    ("depth_log_mse", "constant_depth"),
)
OOD_ENTRIES = (("synthetic", "test"), ("synthetic_ood", "out of distribution"))


def section_out_of_distribution(reports: Path) -> list[str]:
    lines = ["## Out of distribution (`evaluate`: the `ood` rooms of `synthesize`)", ""]
    path = reports / "evaluate/trained_synthetic_ood_views.csv"
    if not path.is_file():
        return lines + missing("section", path)
    n = {
        e: len(v[next(iter(v))])
        for e in ("synthetic", "synthetic_ood")
        if (v := read_views(reports / f"evaluate/trained_{e}_views.csv"))
    }
    lines += [
        "Rooms of another style, never trained on (narrow tall galleries, small cool spot lamps, saturated",
        "glossy walls, concrete floors, mostly metal and plastic boxes), scored by the same code as the test",
        f"split ({n.get('synthetic', 'n/a')} test views, {n.get('synthetic_ood', 'n/a')} out-of-distribution views).",
        "From `reports/evaluate/<model>_<split>_views.csv`.",
        "",
        "MaterialNet: each map's error over its trivial baseline's (fitted on the training split), the ratio of",
        "means over views with its 95 % interval; below 1 is better than the baseline.",
        "",
    ]
    published = read_json(reports / EVALUATE) or {}
    header = ["map / baseline", *(f"{m}, {label}" for m in MODELS for _, label in OOD_ENTRIES)]
    rows = [
        [
            f"{metric} / {baseline}",
            *(published_cell(published, f"{m}/{e}/gate/{baseline}/{metric}") for m in MODELS for e, _ in OOD_ENTRIES),
        ]
        for metric, baseline in OOD_GATES
    ]
    lines += md_table(header, rows)
    light = {e: read_views(reports / f"evaluate/lightnet_{e}_views.csv") for e, _ in OOD_ENTRIES}
    if all(v is not None for v in light.values()):
        lines += [
            "",
            "LightNet (the `train_lighting` export on MaterialNet's G-buffers): the mean over views of each view's",
            "own value (as the paired table of the LightNet section, not the stage's per-batch figure):",
            "",
        ]
        rows = []
        for key, label in LIGHT_METRICS[:3]:
            cells = []
            for e, _ in OOD_ENTRIES:
                v = light[e]
                model = v[f"model/{key}"][np.isfinite(v[f"model/{key}"])]
                cells.append(num(model.mean()) if len(model) else "n/a")
                base = v.get(f"scaled_constant/{key}")
                cells.append(num(base[np.isfinite(base)].mean()) if base is not None else "n/a")
                cells.append(published_cell(published, f"lightnet/{e}/minus_scaled_constant/{key}", signed))
            rows.append([label, *cells])
        header = ["metric"] + [
            f"{who}, {label}" for _, label in OOD_ENTRIES for who in ("LightNet", "scaled constant", "difference")
        ]
        lines += md_table(header, rows)
    lines += ood_insertion_lines(reports)
    lines.append("")
    return lines


def learning_row(run: dict) -> dict:
    """`bench.learning_curve`: one run's rooms, steps and minutes, its test re-render and insertion PSNR,
    and its all-object insertion minus the reference run's, paired by case."""
    row = {k: run.get(k) for k in ("rooms", "steps", "train_minutes", "render_psnr")}
    for c in ("mirror", "glossy", "diffuse", "all"):
        row[f"insertion {c} (dB)"] = (run.get("insertion", {}).get(c) or {}).get("psnr")
    ref = run.get("insertion", {}).get("all") or {}
    if "minus_reference" in ref:
        row["all minus reference"] = (
            f"{signed(ref['minus_reference'])} {interval(ref['minus_reference_lo'], ref['minus_reference_hi'])}"
        )
    return row


def flat_rows(rows: list) -> tuple[list[str], list[list[str]]]:
    """A list of flat dicts as (header, cells); nested values are left out."""
    keys = list(dict.fromkeys(k for r in rows for k, v in r.items() if not isinstance(v, dict | list)))
    return keys, [
        [
            num(r[k])
            if isinstance(r.get(k), int | float) and not isinstance(r.get(k), bool)
            else ("n/a" if r.get(k) is None else str(r.get(k, "")))
            for k in keys
        ]
        for r in rows
    ]


def provenance_line(data: dict, profile: str) -> str:
    """Where a bench's numbers come from (`bench.common.provenance`): commit, date, profile and config
    hashes, marked when it did not measure the current profile's configuration."""
    prov = data.get("provenance")
    if not prov:
        return (
            "**Not known to measure the current configuration**: this JSON predates the commit and "
            "configuration record; re-run the bench before relying on it."
        )
    commit = (prov.get("commit") or "unknown")[:10] + (" with uncommitted changes" if prov.get("dirty") else "")
    # each (config, hash) once: older JSONs recorded a config every time a bench composed it
    hashes = ", ".join(dict.fromkeys(f"`{c['config']}` {c['sha256']}" for c in prov.get("configs", []))) or "none"
    line = f"Measured {prov.get('date', '?')} at commit {commit}; profile {prov.get('profile')}; configs {hashes}."
    if prov.get("profile") is None:
        return line + " Its own settings (no stage config): see the JSON."
    if str(prov["profile"]) != str(profile):
        return line + f" **Not the current profile's configuration** (`{profile}`)."
    return line


def bench_block(name: str, data: dict, profile: str) -> list[str]:
    """A bench JSON's headline: where it comes from (`provenance_line`), its `measured`/`summary` scalars
    and row lists, and any `quoted` figures labelled as quoted with their source."""
    machine = data.get("machine", {})
    lines = [
        f"### `{name}`",
        "",
        f"From `reports/bench/{name}.json` (device {machine.get('device', 'n/a')}, "
        f"torch threads {machine.get('torch_threads', 'n/a')}, torch {machine.get('torch', 'n/a')}).",
        provenance_line(data, profile),
    ]
    head = data.get("measured", data.get("summary"))
    if head is None and name == "light_energy":
        head = {f"nMSE ({kind})": v.get("nmse", {}) for kind, v in data.get("kinds", {}).items()}
    elif head is None and name.startswith("learning_curve"):
        head = {"each run on the held-out test split": [learning_row(r) for r in data.get("runs", [])]}
    elif head is None and name.startswith("device_step"):
        head = {f"each case on {data.get('device')} (CPU: the same host's)": device_rows(data)}
    elif head is None and name.startswith("overfit"):
        head = {"each run's last evaluation, on its training rooms": [overfit_row(r) for r in data.get("runs", [])]}
    elif head is None:
        head = {k: v for k, v in data.items() if k in BENCH_HEADLINES.get(name, ())}
    if isinstance(head, list):  # a summary that is a list of rows: one table
        head = {"each row": head}
    if not isinstance(head, dict):
        raise ValueError(
            f"reports/bench/{name}.json: its summary is a {type(head).__name__}; write a mapping or a list of rows"
        )
    scalars = [[k, num(v)] for k, v in head.items() if isinstance(v, int | float) and not isinstance(v, bool)]
    if scalars:
        lines += ["", *md_table(["measured", "value"], scalars)]
    for k, v in head.items():
        if isinstance(v, list) and v and all(isinstance(r, dict) for r in v):
            header, cells = flat_rows(v)
            lines += ["", f"{k}:", "", *md_table(header, cells)]
        elif isinstance(v, dict) and v and all(isinstance(x, int | float) for x in v.values()):
            lines += ["", f"{k}: " + ", ".join(f"{a} {num(b)}" for a, b in v.items())]
    if name in BENCH_FIGURES:
        lines += ["", f"![{name}](../reports/bench/{name}.png)"]
    quoted = data.get("quoted", {})
    if quoted:
        rows = [
            [
                k,
                num(q.get("value")) if isinstance(q, dict) else num(q),
                str(q.get("unit", "")) if isinstance(q, dict) else "",
                str(q.get("source", "")) if isinstance(q, dict) else "",
            ]
            for k, q in quoted.items()
        ]
        lines += ["", "Quoted, not measured in this run:", "", *md_table(["figure", "value", "unit", "source"], rows)]
    return lines + [""]


def device_rows(data: dict) -> list[dict]:
    """`bench.device_step`'s rows: each case it ran (`device_row`), then each case its settings asked for
    that it never reached (a run stopped at its time limit), so a missing case reads as missing."""
    rows = [device_row(c) for c in data.get("cases", [])]
    settings = data.get("settings", {})
    done = {(c.get("profile"), c.get("stage")) for c in data.get("cases", [])}
    for profile in settings.get("profiles", []):
        for stage in settings.get("stages", []):
            if (profile, stage) not in done:
                rows.append({"profile": profile, "stage": stage, "failed or not run": "not reached: the run stopped"})
    return rows


def device_row(case: dict) -> dict:
    """`bench.device_step`: one case's profile and stage, the parts that failed, and each part's headline
    (step times in ms, peak memory, operations a step, the loss's first and last tenth, the largest
    CPU/device difference)."""
    row = {"profile": case.get("profile"), "stage": case.get("stage")}
    failed = [k for k, v in case.items() if isinstance(v, dict) and "error" in v]
    setup = case.get("setup") if isinstance(case.get("setup"), dict) else {}
    row["parameters"], row["batch"] = setup.get("parameters"), setup.get("batch_size")
    timing = {}
    for name in ("timing", "cpu_timing"):  # older runs kept the CPU's step inside `timing`
        if isinstance(case.get(name), dict) and "error" not in case[name]:
            timing.update(case[name])
    for key, label in (("device_median_s", "device step (ms)"), ("cpu_median_s", "CPU step (ms)")):
        if key in timing:
            row[label] = timing[key] * 1e3
    row["CPU / device"] = timing.get("speedup")
    row["peak memory (GiB)"] = timing.get("device_peak_memory_gib")
    ops = case.get("operations") if isinstance(case.get("operations"), dict) else {}
    row["aten operations a step"] = ops.get("aten_operations_per_step")
    row["host reads a step"] = ops.get("host_reads_per_step")
    row["synchronising a step"] = ops.get("synchronising_per_step")
    sites = ops.get("synchronising_sites_one_step") or {}
    if sites:  # the project function that makes the device wait most often
        site, count = max(sites.items(), key=lambda kv: kv[1])
        row["most synchronising site (one step)"] = f"{site}: {count}"
    learn = case.get("learning") if isinstance(case.get("learning"), dict) else {}
    row["loss, first tenth"], row["loss, last tenth"] = learn.get("loss_first_tenth"), learn.get("loss_last_tenth")
    agreement = case.get("agreement") if isinstance(case.get("agreement"), dict) else {}
    diffs = [v for v in agreement.values() if isinstance(v, int | float)]
    diffs += [
        v["radiance_relative_l2"] for v in agreement.values() if isinstance(v, dict) and "radiance_relative_l2" in v
    ]
    row["largest CPU/device relative L2"] = max(diffs) if diffs else None
    row["failed or not run"] = ", ".join(failed) or ("not reached" if not setup else "none")
    return row


def overfit_row(run: dict) -> dict:
    """`bench.overfit`: one run's variant, rooms, steps and its last evaluation's headline numbers."""
    last = (run.get("curve") or [{}])[-1]
    row = {"variant": run.get("variant"), "rooms": run.get("rooms"), "steps": run.get("steps")}
    for kind in ("surf", "free"):
        if isinstance(last.get(kind), dict):
            row[f"{kind} nMSE"] = last[kind].get("nmse")
            row[f"{kind} energy part"] = last[kind].get("energy_part")
    if "render_psnr" in last:
        row["re-render PSNR (dB)"] = last["render_psnr"]
    walls = run.get("walls")
    if isinstance(walls, dict):  # the NeRF's weight against the true walls, on miss rays
        row["NeRF weight within 20 % of the wall"] = walls.get("weight_within_20pc_of_wall")
        row["NeRF opacity"] = walls.get("opacity_mean")
    for metric in ("metallic_mse", "roughness_mse", "albedo_mse"):
        if isinstance(last.get(metric), dict):
            row[f"{metric} / mean"] = last[metric].get("ratio")
    return row


# which top-level keys are a bench's headline when its JSON has neither `measured` nor `summary`
BENCH_HEADLINES = {
    "train_step": ("settings",),
    "insertion": ("speed",),
    "light_net": ("speed", "hyper_apply"),
    "material_net": ("results",),
}


# benches whose figure the page shows (the others' PNGs lie beside their JSONs)
BENCH_FIGURES = ("real_photo", "insertion_figure", "pipeline_time", "nonbox_rooms", "lamp_placement_rooms_deep")


def section_benches(reports: Path, profile: str) -> list[str]:
    lines = ["## Benchmarks (`python -m pipeline.bench.<name>`)", ""]
    files = sorted((reports / "bench").glob("*.json"))
    if not files:
        return lines + ["No bench results under `reports/bench/`.", ""]
    for f in files:
        lines += bench_block(f.stem, read_json(f) or {}, profile)
    return lines


def _ci(d: dict) -> str:
    return f"{signed(d['diff'])} dB {interval(d['lo'], d['hi'])}"


def section_findings(facts: dict, claim_counts: dict[str, int] | None) -> list[str]:
    """The page's opening: one line per finding, each with its interval and the file it comes from, from
    the numbers the sections below computed (`facts`) and the ablation verdicts (`claim_counts`)."""
    lines = ["## Findings", ""]
    gate, material = facts.get("material_gate"), facts.get("material", [])
    if material:
        normal = next((r for r in material if r[0] == "normal_angle_deg"), None)
        worst = max((r for r in material if r[4] is not None), key=lambda r: r[4], default=None)
        line = "- MaterialNet (test split): "
        if normal:
            line += f"normal error {num(normal[1])}° against {num(normal[3])}° for the {normal[2]} baseline; "
        line += f"gate {'passed' if gate == 1 else 'not passed'}"
        if worst:
            line += f" (highest error ratio: {worst[0]} {num(worst[4])} of the {worst[2]} baseline's, {worst[5]})"
        lines.append(line + ". `reports/train_material/`.")
    paired = facts.get("paired", {})
    render = next(
        (v for (metric, who), v in paired.items() if metric == "render_psnr" and who == "scaled_constant"), None
    )
    if render:
        lines.append(
            f"- Re-render of the input (test split, mean over views): LightNet {num(render['means'][0])} dB, "
            f"{_ci(render)} over the exposure-scaled constant light. `reports/train_lighting/test_views.csv`."
        )
    m = facts.get("edit")
    if m:
        spp = {row: int(v) for key, v in m.items() if key.startswith("scoring_spp/") for row in [key.split("/")[1]]}
        at = ", ".join(f"{row} {n}" for row, n in spp.items() if row in ("lightnet", "nearest_probe", "oracle"))
        for group in ("mirror", "glossy", "diffuse", "all"):
            cells = []
            for who in ("nearest_probe", "scaled_constant"):
                p = f"insert/{group}/lightnet_minus_{who}/psnr"
                if f"{p}_lo" in m:
                    cells.append(
                        f"{_ci({'diff': m[f'{p}_diff'], 'lo': m[f'{p}_lo'], 'hi': m[f'{p}_hi']})} against {who}"
                    )
            if cells:
                lines.append(
                    f"- Insertion, {group} objects: LightNet {num(m.get(f'insert/{group}/lightnet/psnr'))} dB "
                    f"(oracle {num(m.get(f'insert/{group}/oracle/psnr'))} dB); "
                    + "; ".join(cells)
                    + (
                        f"; samples per pixel {at} (their convergence: `reports/bench/scoring_convergence.json`)"
                        if spp
                        else "; rows scored at unequal noise"
                    )
                    + ". `reports/edit/metrics.json`."
                )
        p = "insert/all/ring/lightnet_minus_no_shadows/psnr"
        if f"{p}_lo" in m:
            lines.append(
                f"- Shadows and bounce light around inserted objects ({num(m['insert/all/ring/cases'])} objects that "
                f"change the room in Mitsuba's render): LightNet with differential rendering "
                f"{num(m['insert/all/ring/lightnet/psnr'])} dB against {num(m['insert/all/ring/no_shadows/psnr'])} dB "
                f"for the plain composite, {_ci({'diff': m[f'{p}_diff'], 'lo': m[f'{p}_lo'], 'hi': m[f'{p}_hi']})}. "
                "`reports/edit/metrics.json`, `reports/edit/shadows.png`."
            )
    if claim_counts:
        told = ", ".join(f"{n} {verdict}" for verdict, n in sorted(claim_counts.items()))
        lines.append(
            f"- Paper claims tested by the ablations (each on its primary metric, Holm-adjusted): {told}. "
            "`reports/report/ablations.md`."
        )
    if len(lines) == 2:
        lines.append("No stage reports yet: run `dvc repro`.")
    return [*lines, ""]


SECTIONS: tuple[Callable[..., list[str]], ...] = (
    section_material,
    section_lighting,
    section_edit,
    section_evaluate,
    section_out_of_distribution,
)


def render(reports: Path, ablation_tables: list[str], profile: str, claim_counts: dict[str, int] | None = None) -> str:
    """The whole document from the reports under `reports`, the report stage's ablation tables and its
    count of claim verdicts: findings first, then each stage's section, the ablations, the benches and the
    data counters."""
    facts: dict = {}
    body: list[str] = []
    for section in SECTIONS:
        body += (
            section(reports, facts)
            if section in (section_material, section_lighting, section_edit)
            else section(reports)
        )
    lines = [
        f"# Results ({profile})",
        "",
        "Written by the `report` stage (`dvc repro`) from the files under `reports/`; do not edit by hand.",
        "Intervals are 95 %; each table says how its are made: a bootstrap over test views (or images) for",
        "the stage sections, a t interval over seeds for the ablation claims.",
        "Figures: [reports/report/summary.md](../reports/report/summary.md).",
        "",
        *section_findings(facts, claim_counts),
        *body,
    ]
    lines += [
        "## Ablations (`ablate`, `report`)",
        "",
        "From `reports/ablate/*/` via [reports/report/ablations.md](../reports/report/ablations.md).",
        "",
        *ablation_tables,
        "",
    ]
    lines += section_benches(reports, profile)
    lines += section_data(reports)
    return "\n".join(lines).rstrip() + "\n"
