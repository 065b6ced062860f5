"""Stage `report` (last): every ablation preset and seed (`reports/ablate/*/`) and every main stage's
metrics gathered into `reports/report/`:

- `ablations.md`: the paper-style table. Per preset, means over seeds with their spread (half the range),
  and against its reference (`full` for LightNet, `material_small` for MaterialNet) the paired
  difference on the preset's claim metric: the mean over seeds with a t interval over the seeds'
  differences (`metrics.verdicts.seed_effect`); `full`'s test-time out-of-view thresholds as rows of
  their own (`full:out_threshold_<t>`: the same weights, paired with `full` on the re-render PSNR). The
  paper's claims are tested together, Holm-adjusted (`metrics.verdicts.decide`): supported,
  contradicted, inconclusive or not testable, with the power at a stated effect size. Then stability
  (non-finite metrics, unavailable presets, the five worst test views are in the stage reports) and the
  main stages' gates.
- `pareto.png`: accuracy (insertion PSNR over all objects, and test re-render PSNR) against full-frame
  seconds per image, one point per preset (mean over seeds) and per test-time threshold, the Pareto
  front marked; training minutes in the second row.
- `summary.md`: links to every figure under reports/ and the headline numbers.
- `metrics.json`: the table's numbers (DVC metrics).
The MLflow run `report-<profile>` holds them, with a nested `ablate-<profile>` parent run to which every
preset/seed run of the current reports is attached (MLflow's parent tag), carrying the same figures.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from pipeline.metrics.verdicts import decide, minimal_detectable_effect, power, seed_effect, seeds_needed
from pipeline.tracking import publish, stage_run
from pipeline.tracking.figures import pareto_figure
from pipeline.tracking.results_page import read_json
from pipeline.tracking.results_page import render as render_results

# (key, label, higher is better) of the table's columns
LIGHT_COLUMNS = [
    ("test/render_psnr", "re-render PSNR", True),
    ("test/glossy_render_psnr", "glossy re-render PSNR", True),
    ("test/surf_light_log_l1", "surface log-L1", False),
    ("test/free_light_log_l1", "free log-L1", False),
    ("edit/insert/mirror/lightnet/psnr", "mirror ins. PSNR", True),
    ("edit/insert/glossy/lightnet/psnr", "glossy ins. PSNR", True),
    ("edit/insert/all/lightnet/psnr", "all ins. PSNR", True),
]
MATERIAL_COLUMNS = [
    ("test/albedo_mse", "albedo MSE", False),
    ("test/normal_angle_deg", "normal deg", False),
    ("test/roughness_mse", "roughness MSE", False),
    ("test/metallic_mse", "metallic MSE", False),
    ("test/depth_log_mse", "depth log-MSE", False),
]


def read_runs(ablate_dir: Path, claims: dict | None = None) -> dict[str, dict[int, dict]]:
    """{preset: {seed: {"preset": preset.json, "metrics": ..., "timings": ...}}} of every run folder.
    claims: {preset: {claim, source, primary, secondary}} (conf/claims/, the report's own config), laid over each
    run's preset description: a claim is the report's to state, not the run's."""
    runs: dict[str, dict[int, dict]] = {}
    for folder in sorted(p for p in ablate_dir.iterdir() if p.is_dir()):
        files = {name: folder / f"{name}.json" for name in ("preset", "metrics", "timings")}
        missing = [str(f) for name, f in files.items() if name != "timings" and not f.is_file()]
        if missing:
            raise FileNotFoundError(f"{folder}: an ablation run without {', '.join(missing)} (re-run it)")
        data = {name: json.loads(f.read_text()) if f.is_file() else {} for name, f in files.items()}
        worst = folder / "worst_views.json"
        data["worst_views"] = json.loads(worst.read_text()) if worst.is_file() else []
        data["views"] = read_view_scores(folder / "views.csv") if (folder / "views.csv").is_file() else None
        data["figures"] = sorted(p.name for p in folder.glob("*.png"))
        if claims is not None:  # the report's claims replace whatever claim an older run recorded
            for key in ("claim", "source", "expect", "primary", "secondary"):
                data["preset"].pop(key, None)
        data["preset"].update((claims or {}).get(data["preset"]["name"], {}))
        runs.setdefault(data["preset"]["name"], {})[int(data["preset"]["seed"])] = data
    if not runs:
        raise FileNotFoundError(f"{ablate_dir}: no ablation run folders (run the ablate stage first)")
    return runs


def read_view_scores(path: Path) -> dict[str, dict[str, float]]:
    """An ablation run's `views.csv` (id, then one column per metric): {view id: {metric: value}}. A
    non-finite or unreadable value is refused naming the file and row (a view is never dropped)."""
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    if not rows or rows[0][:1] != ["id"]:
        raise ValueError(f"{path}: expected a header starting with 'id', got {rows[0] if rows else 'an empty file'}")
    header, out = rows[0], {}
    for n, row in enumerate(rows[1:], 2):
        if len(row) != len(header):
            raise ValueError(f"{path}: row {n} has {len(row)} fields, the header {len(header)}")
        try:
            values = {k: float(v) for k, v in zip(header[1:], row[1:], strict=True)}
        except ValueError as err:
            raise ValueError(f"{path}: row {n}: {err}") from None
        if not all(math.isfinite(v) for v in values.values()):
            raise ValueError(f"{path}: row {n} ({row[0]}): a non-finite score")
        out[row[0]] = values
    return out


def spread(values: list[float]) -> tuple[float, float]:
    """(mean, half the range) of per-seed values; half-range 0 for one seed."""
    v = np.asarray(values, float)
    return float(v.mean()), float((v.max() - v.min()) / 2) if len(v) > 1 else 0.0


# a claim's effect size for the power column: 0.5 dB on a PSNR, else this share of the reference's mean
POWER_DB, POWER_SHARE = 0.5, 0.05


def effect_size(metric: str, reference_mean: float) -> float:
    """The effect a claim's power and seed count are stated at: `POWER_DB` on a PSNR, else `POWER_SHARE`
    of the reference's mean (NaN when that mean is unknown)."""
    return POWER_DB if metric.endswith("psnr") else POWER_SHARE * abs(reference_mean)


def compare(runs: dict, preset: str, reference: str, key: str) -> dict:
    """Paired per-seed differences preset - reference on `key` (each a mean over the same test views) and
    their t interval over seeds (`metrics.verdicts.seed_effect`): {"seeds", "diffs", "diff", "lo", "hi",
    "p", "se", "reference_mean"}; no seeds with both values: seeds 0."""
    seeds = sorted(set(runs.get(preset, {})) & set(runs.get(reference, {})))
    diffs, ref, diverged = [], [], 0
    for s in seeds:
        a, b = runs[preset][s]["metrics"].get(key), runs[reference][s]["metrics"].get(key)
        if a is None or b is None:
            continue
        if not (math.isfinite(a) and math.isfinite(b)) or runs[preset][s]["metrics"].get("health/diverged", 0) > 0:
            diverged += 1  # counted, never dropped: a method that sometimes diverges is not judged on survivors
            continue
        diffs.append(a - b)
        ref.append(b)
    if not diffs:
        return {"seeds": 0, "diffs": [], "diff": float("nan"), "p": float("nan"), "diverged": diverged, "unit": "seeds"}
    effect = seed_effect([np.array([d]) for d in diffs])
    return {
        **effect,
        "seeds": len(diffs),
        "diffs": diffs,
        "reference_mean": float(np.mean(ref)),
        "diverged": diverged,
        "unit": "seeds",
    }


def compare_by_views(runs: dict, preset: str, reference: str, key: str) -> dict | None:
    """A render-time preset (it scores the reference's own weights) against its reference, with the test
    views as units: conditional on each seed's trained weights, the question is whether the layer changes
    the score on views like these, so each view's paired difference preset - reference (its mean over the
    seeds' weights) is one unit and the t interval runs over views. compare()'s fields with "seeds" the
    number of views (the units), "weights" the seeds whose weights were scored, "unit": "views"; None
    when a seed of either run wrote no per-view scores of `key` (then the claim falls back to seeds)."""
    seeds = sorted(set(runs.get(preset, {})) & set(runs.get(reference, {})))
    per_seed = []
    for s in seeds:
        a, b = runs[preset][s].get("views"), runs[reference][s].get("views")
        if not a or not b:
            return None
        d = {v: a[v][key] - b[v][key] for v in set(a) & set(b) if key in a[v] and key in b[v]}
        if not d:
            return None
        per_seed.append(d)
    if not per_seed:
        return None
    views = sorted(set.intersection(*(set(d) for d in per_seed)))
    if len(views) < 2:
        return None
    means = [float(np.mean([d[v] for d in per_seed])) for v in views]
    effect = seed_effect([np.array([m]) for m in means])
    ref = [float(np.mean([runs[reference][s]["views"][v][key] for v in views])) for s in seeds]
    return {
        **effect,
        "seeds": len(views),
        "weights": len(per_seed),
        "diffs": means,
        "reference_mean": float(np.mean(ref)),
        "diverged": 0,
        "unit": "views",
    }


def expected_sign(expect: dict) -> int:
    """The sign of preset - reference on the metric that the claim predicts (`holds_if` with the metric's
    direction)."""
    holds = expect.get("holds_if")
    if holds not in ("reference_better", "preset_better"):
        raise ValueError(f"expect.holds_if={holds!r}: choose reference_better or preset_better")
    preset_higher = (holds == "preset_better") == bool(expect["higher_is_better"])
    return 1 if preset_higher else -1


def expectations(preset: dict) -> list[dict]:
    """A preset's claim metrics, the primary first: [{metric, higher_is_better, holds_if, "role": "primary"
    | "secondary"}]; [] for a preset without a paper claim. The claim declares one `primary` (its verdict)
    and any `secondary` (reported, never judged); a lone `expect` (one metric) is the primary."""
    if not preset.get("claim"):
        return []
    primary = preset.get("primary")
    if primary is None:
        expect = preset.get("expect")
        if isinstance(expect, list):
            if len(expect) != 1:
                raise ValueError(
                    f"claim of preset {preset.get('name')!r}: {len(expect)} metrics under `expect` and no "
                    "`primary`: declare the one metric that decides the claim as `primary`, the rest `secondary`"
                )
            expect = expect[0]
        primary = expect
    if not primary:
        return []
    secondary = preset.get("secondary") or []
    if isinstance(secondary, dict):
        secondary = [secondary]
    return [{**primary, "role": "primary"}, *({**e, "role": "secondary"} for e in secondary)]


REFERENCE_TOLERANCE = 0.10  # a MaterialNet reference within 10 % of the main model's normal error is comparable


def reference_comparability(runs: dict, main_material: dict | None) -> dict[str, str]:
    """{preset: why} for every MaterialNet preset whose reference (trained under the ablation schedule)
    is not comparable with the main model the paper's claim is about: its mean test normal error over
    seeds more than `REFERENCE_TOLERANCE` above the main `train_material` model's
    (`main_material`: reports/train_material/metrics.json; None: nothing to compare, nothing marked).
    A claim judged against a half-trained reference would say nothing about the trained method."""
    main = (main_material or {}).get("test/normal_angle_deg")
    if main is None or not math.isfinite(main):
        return {}
    out = {}
    for name, seeds in runs.items():
        first = seeds[next(iter(seeds))]["preset"]
        reference = runs.get(first.get("reference"), {})
        unavailable = any("unavailable" in d["preset"] for d in seeds.values())  # says so itself
        if first["stage"] != "train_material" or name == first.get("reference") or not reference or unavailable:
            continue
        ref = [d["metrics"].get("test/normal_angle_deg", float("nan")) for d in reference.values()]
        ref_mean = float(np.mean(ref))
        if not math.isfinite(ref_mean) or ref_mean > main * (1 + REFERENCE_TOLERANCE):
            out[name] = (
                f"reference `{first['reference']}` normal error {ref_mean:.1f}° against the main model's "
                f"{main:.1f}° (more than {REFERENCE_TOLERANCE:.0%} above)"
            )
    return out


def claim_verdicts(
    runs: dict, alpha: float = 0.05, not_comparable: dict[str, str] | None = None
) -> dict[tuple[str, str], dict]:
    """Every (preset, claim metric) of every preset with a paper claim: {(preset, metric): compare()'s
    fields + "role", "metric", and for the primary metrics "p_holm", "verdict", "effect_size", "power",
    "mde", "seeds_needed"}. Only the primary metrics (one per claim) form the Holm family; a secondary
    metric gets its interval and the verdict "secondary" (reported, not judged). A preset that did not run
    here (unavailable) or has fewer than two seeds is `not testable`. `power`: the probability of a verdict
    at the family's strictest level (alpha / number of testable claims) if the true difference were
    `effect_size` (0.5 dB on a PSNR, else 5 % of the reference's mean) and the seeds spread as observed;
    `mde`: the minimal detectable effect at power 0.8 at that level and spread; `seeds_needed`: the seeds
    that would give power 0.8 at `effect_size` (NaN: over 64 seeds, or 1024 views); all three post hoc,
    from the observed spread. A seed whose run diverged is counted (`diverged`) and makes the claim
    `diverged`, never dropped. A preset in `not_comparable` ({preset: why}, `reference_comparability`)
    is left out of the family and reads `not comparable` with its reason (`why`)."""
    not_comparable = not_comparable or {}
    claims, found, secondary = {}, {}, {}
    for name, seeds in runs.items():
        first = seeds[next(iter(seeds))]["preset"]
        unavailable = any("unavailable" in d["preset"] for d in seeds.values())
        for e in expectations(first):
            c = {"seeds": 0, "diffs": [], "unit": "seeds"}
            if not unavailable and name not in not_comparable:
                c = compare(runs, name, first["reference"], e["metric"])
                if first.get("weights_from") and not c["diverged"]:  # render-time: views are the units
                    c = compare_by_views(runs, name, first["reference"], e["metric"]) or c
            if e["role"] == "secondary":
                secondary[(name, e["metric"])] = {
                    **c,
                    "role": "secondary",
                    "metric": e["metric"],
                    "verdict": "secondary",
                }
                continue
            key = f"{name}:{e['metric']}"
            found[key] = (name, c, e)
            claims[key] = {
                "diffs": [np.array([d]) for d in c["diffs"]],
                "expected_sign": expected_sign(e),
                "diverged": c.get("diverged", 0),
            }
    decided = decide(claims, alpha)
    testable = sum(1 for d in decided.values() if math.isfinite(d["p_holm"]))
    out = {}
    for key, d in decided.items():
        name, c, e = found[key]
        size = effect_size(e["metric"], c.get("reference_mean", float("nan")))
        sd = d.get("se", float("nan")) * math.sqrt(d["seeds"]) if d["seeds"] >= 2 else float("nan")
        level = alpha / max(testable, 1)
        spread_ok = math.isfinite(sd) and sd > 0
        pw = power(size, sd, int(d["seeds"]), level) if spread_ok else float("nan")
        mde = minimal_detectable_effect(sd, int(d["seeds"]), level) if spread_ok else float("nan")
        most = 64 if c.get("unit", "seeds") == "seeds" else 1024  # units: seeds, or views for a render-time claim
        needed = seeds_needed(size, sd, level, most=most) if spread_ok and math.isfinite(size) else None
        out[(name, e["metric"])] = {
            **c,
            **d,
            "role": "primary",
            "metric": e["metric"],
            "effect_size": size,
            "power": pw,
            "mde": mde,
            "seeds_needed": float("nan") if needed is None else float(needed),
        }
        if name in not_comparable:
            out[(name, e["metric"])].update(verdict="not comparable", why=not_comparable[name])
    return {**out, **secondary}


def _fmt(mean: float, half: float) -> str:
    if not math.isfinite(mean):
        return "n/a"
    digits = 3 if abs(mean) < 10 else 2
    return f"{mean:.{digits}f} ± {half:.{digits}f}" if half else f"{mean:.{digits}f}"


def _p(value: float) -> str:
    return "n/a" if not math.isfinite(value) else f"{value:.2g}"


def _seeds(n: float) -> str:
    return "n/a" if not math.isfinite(n) else f"{int(n)}"


def _interval(c: dict) -> str:
    """'-0.412 [-0.9, +0.08] (seeds: -0.3, -0.5)': the mean difference, its 95 % t interval over seeds and
    each seed's difference; 'not testable' under two seeds."""
    if c.get("unit") == "views":
        return (
            f"{c['diff']:+.3g} [{c['lo']:+.3g}, {c['hi']:+.3g}] ({int(c['seeds'])} views, each the mean over "
            f"{int(c['weights'])} seeds' weights)"
        )
    per_seed = ", ".join(f"{d:+.3g}" for d in c["diffs"])
    if c["seeds"] < 2:
        return f"{per_seed or 'no seed'} (not testable: fewer than 2 seeds)"
    return f"{c['diff']:+.3g} [{c['lo']:+.3g}, {c['hi']:+.3g}] (seeds: {per_seed})"


def table(runs: dict, stage: str, columns: list) -> tuple[list[str], dict[str, float]]:
    """Markdown rows of one stage's presets (means over seeds ± half their range) and the numbers behind
    them; `vs reference`: each preset minus its reference on the first column's metric, seed by seed."""
    lines, numbers = [], {}
    header = ["preset", "changes", "seeds", *[c[1] for c in columns], "s/image", "train min"]
    header.append(f"vs reference: {columns[0][1]} (95 % t interval over seeds)")
    lines.append("| " + " | ".join(header) + " |")
    lines.append("|" + "---|" * len(header))
    for name in sorted(runs, key=lambda n: (n != runs[n][next(iter(runs[n]))]["preset"].get("reference"), n)):
        seeds = runs[name]
        first = seeds[next(iter(seeds))]["preset"]
        if first["stage"] != stage:
            continue
        if any("unavailable" in d["preset"] for d in seeds.values()):
            why = next(d["preset"]["unavailable"] for d in seeds.values())
            dashes = " | ".join(["-"] * (len(columns) + 2))
            lines.append(f"| {name} | {first['changes']} | 0 | {dashes} | unavailable: {why} |")
            continue
        cells = []
        for key, _, _ in columns:
            vals = [d["metrics"].get(key, float("nan")) for d in seeds.values()]
            mean, half = spread(vals)
            numbers[f"{name}/{key}"] = mean
            cells.append(_fmt(mean, half))
        for key in ("seconds_per_image", "train_minutes"):
            vals = [d["timings"].get(key, float("nan")) for d in seeds.values()]
            cells.append(_fmt(*spread(vals)))
        ref, versus = first.get("reference", ""), ""
        if name != ref:
            c = compare(runs, name, ref, columns[0][0])
            versus = _interval(c)
            numbers[f"{name}/vs_reference/{columns[0][0]}"] = float(c["diff"])
        lines.append(f"| {name} | {first['changes']} | {len(seeds)} | " + " | ".join(cells) + f" | {versus} |")
    return lines, numbers


def seed_design(runs: dict, alpha: float = 0.05) -> list[dict]:
    """The seed count each training-time claim needs, designed from its reference's runs alone (what is
    known before the presets run): the spread of the reference's per-seed values of the claim's primary
    metric, times sqrt(2) for a paired difference of two independent runs (conservative: a shared seed
    correlates the pair positively), at the family's strictest level (alpha / number of claims). One
    {preset, metric, reference, reference_seeds, reference_sd, effect_size, seeds_needed (NaN: more than
    64), mde_at_seeds (the minimal detectable effect at the seeds the preset ran)} per claim whose
    reference ran on two or more seeds; render-time claims (views as units) are not in it."""
    primaries, family = [], 0
    for name, seeds in sorted(runs.items()):
        first = seeds[next(iter(seeds))]["preset"]
        metrics = expectations(first)
        family += bool(metrics)
        if metrics and not first.get("weights_from"):
            primaries.append((name, first["reference"], metrics[0]["metric"], len(seeds)))
    level = alpha / max(family, 1)
    rows = []
    for name, reference, metric, ran in primaries:
        values = [d["metrics"].get(metric) for d in runs.get(reference, {}).values()]
        values = np.asarray([v for v in values if v is not None and math.isfinite(v)], float)
        if len(values) < 2 or values.std(ddof=1) == 0:
            continue
        sd = float(values.std(ddof=1) * math.sqrt(2.0))
        size = effect_size(metric, float(values.mean()))
        needed = seeds_needed(size, sd, level)
        rows.append(
            {
                "preset": name,
                "metric": metric,
                "reference": reference,
                "reference_seeds": len(values),
                "reference_sd": float(values.std(ddof=1)),
                "effect_size": size,
                "seeds_needed": float("nan") if needed is None else float(needed),
                "seeds_run": ran,
                "mde_at_seeds": minimal_detectable_effect(sd, ran, level) if ran >= 2 else float("nan"),
            }
        )
    return rows


def verdict_text(v: dict) -> str:
    """A claim's verdict as the table reads it: an inconclusive claim bounds the effect by its minimal
    detectable effect (it does not say there is none); a diverged one counts its diverged seeds; a claim
    whose seeds all gave the same difference says why it is not testable."""
    verdict = v["verdict"]
    if verdict == "secondary":
        return "secondary: reported, no verdict"
    if verdict == "inconclusive" and math.isfinite(v.get("mde", float("nan"))):
        return f"inconclusive: no effect larger than {v['mde']:.3g} detected"
    if verdict == "diverged":
        return f"diverged ({int(v['diverged'])} of {int(v['diverged'] + v['seeds'])} seeds): unstable"
    if verdict == "not testable" and v["seeds"] >= 2 and v.get("se") == 0.0:
        return "not testable: every seed the same difference"
    if verdict == "not comparable":
        return f"not comparable: {v['why']}"
    return verdict


def claims_table(runs: dict, verdicts: dict | None = None) -> tuple[list[str], dict[str, float]]:
    """One row per paper claim and metric (`claim_verdicts`; the primary metrics are one Holm family): the
    claim and its source, the preset, the metric and its role, the preset minus its reference with the
    95 % t interval over seeds and each seed's difference, the verdict (primary only), Holm's p, the power
    at the stated effect size, the minimal detectable effect and the seeds for power 0.8; and the numbers.
    `verdicts`: `claim_verdicts(runs)` where the caller has them already."""
    verdicts = claim_verdicts(runs) if verdicts is None else verdicts
    lines = [
        "| paper claim | preset | metric | preset - reference (95 % t interval over seeds; over views for a "
        "render-time claim) | verdict | Holm p | power at effect | minimal detectable effect (power 0.8) "
        "| seeds (or views) for power 0.8 at effect |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    numbers = {}
    order = sorted(verdicts, key=lambda k: (k[0], verdicts[k]["role"] != "primary", k[1]))
    for name, metric in order:
        v = verdicts[name, metric]
        first = runs[name][next(iter(runs[name]))]["preset"]
        versus = _interval(v) if v["seeds"] else "not run"
        if v["role"] == "secondary":
            lines.append(f"| (secondary) | {name} | {metric} | {versus} | {verdict_text(v)} | - | - | - | - |")
            numbers[f"{name}/vs_reference/{metric}"] = float(v["diff"])
            for field in ("lo", "hi", "diverged"):
                numbers[f"{name}/vs_reference/{metric}/{field}"] = float(v.get(field, float("nan")))
            continue
        claim = f"{first['claim']} ({first.get('source', '')})"
        lines.append(
            f"| {claim} | {name} | **{metric}** | {versus} | {verdict_text(v)} | {_p(v['p_holm'])} "
            f"| {_p(v['power'])} at {v['effect_size']:.3g} | {_p(v['mde'])} | {_seeds(v['seeds_needed'])}"
            f"{' views' if v.get('unit') == 'views' and math.isfinite(v['seeds_needed']) else ''} |"
        )
        numbers[f"{name}/vs_reference/{metric}"] = float(v["diff"])
        for field in ("lo", "hi", "p_holm", "power", "mde", "seeds_needed", "diverged"):
            numbers[f"{name}/vs_reference/{metric}/{field}"] = float(v.get(field, float("nan")))
    design = seed_design(runs)
    if design:
        lines += [
            "",
            "Seeds designed before running (`seed_design`): from the reference's own seeds, the spread of the",
            "claim's primary metric times sqrt(2) for a paired difference (conservative), at the family's level:",
            "",
            "| preset | primary metric | reference seeds | reference's seed sd | effect | seeds for power 0.8 "
            "| seeds run | minimal detectable effect at the seeds run |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for d in design:
            lines.append(
                f"| {d['preset']} | {d['metric']} | {d['reference_seeds']} | {d['reference_sd']:.3g} "
                f"| {d['effect_size']:.3g} | {_seeds(d['seeds_needed'])} | {d['seeds_run']} | {_p(d['mde_at_seeds'])} |"
            )
            numbers[f"{d['preset']}/design/seeds_needed"] = d["seeds_needed"]
            numbers[f"{d['preset']}/design/mde_at_seeds"] = d["mde_at_seeds"]
    return lines, numbers


def threshold_runs(runs: dict, reference: str = "full") -> dict[str, dict[int, dict]]:
    """The reference preset's test-time out-of-view thresholds as rows of their own, keyed
    `<reference>:out_threshold_<t>`: its `out_threshold_<t>/` metrics and seconds per image, the same
    weights and seeds, so each seed's difference to the reference is paired on the same network. No
    training or insertion columns: neither is re-run at a threshold. (A colon, not a comma: the key
    becomes an MLflow metric name.)"""
    derived: dict[str, dict[int, dict]] = {}
    for seed, data in runs.get(reference, {}).items():
        prefixes = sorted({k.split("/", 1)[0] for k in data["metrics"] if k.startswith("out_threshold_")})
        for prefix in prefixes:
            t = prefix.removeprefix("out_threshold_")
            name = f"{reference}:out_threshold_{t}"
            preset = {
                "name": name,
                "stage": data["preset"]["stage"],
                "changes": f"test time: the out-of-view branch queried only where u >= {t} ({reference}'s weights)",
                "reference": reference,
                "seed": seed,
                "expect": {"metric": "test/render_psnr", "higher_is_better": True, "holds_if": ""},
            }
            metrics = {k.removeprefix(f"{prefix}/"): v for k, v in data["metrics"].items() if k.startswith(prefix)}
            seconds = data["timings"].get(f"{prefix}/seconds_per_image", float("nan"))
            derived.setdefault(name, {})[seed] = {
                "preset": preset,
                "metrics": metrics,
                "timings": {"seconds_per_image": seconds},
                "worst_views": [],
            }
    return derived


def stability(runs: dict, figures: str = "../ablate") -> list[str]:
    """Per preset: non-finite training losses and test metrics, diverged runs, unavailable runs, and the
    five test views LightNet renders worst (first seed; insertion PSNR, the scaled constant's beside),
    linked to that run's `worst_views.png` (`figures`: the ablation runs' folder relative to the page)."""
    lines = [
        "| preset | seeds | non-finite train losses | non-finite test metrics | diverged runs | unavailable "
        "| worst views (LightNet / scaled constant insertion PSNR, dB; first seed) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, seeds in sorted(runs.items()):
        ds = list(seeds.values())

        def total(key, ds=ds):
            return int(sum(d["metrics"].get(key, 0.0) for d in ds))

        unavailable = sum("unavailable" in d["preset"] for d in ds)
        worst = "; ".join(
            f"{w['view']} {w['lightnet_psnr']:.1f}/{w['scaled_constant_psnr']:.1f}" for w in ds[0]["worst_views"]
        )
        if worst:
            worst += f" ([figure]({figures}/{name}-s{ds[0]['preset']['seed']}/worst_views.png))"
        lines.append(
            f"| {name} | {len(ds)} | {total('health/nonfinite_train_losses')} | "
            f"{total('health/nonfinite_test_metrics')} | {total('health/diverged')} | {unavailable} | {worst} |"
        )
    return lines


def pareto_points(runs: dict) -> list[dict]:
    """One point per LightNet preset (means over seeds, and half the seeds' range as `<key>_err`) and per
    test-time threshold of `full` (`threshold_runs`: no training minutes or insertion, so those panels
    leave them out; nor a render-time preset's training minutes: it trains nothing)."""
    points = []
    for name, seeds in sorted({**runs, **threshold_runs(runs)}.items()):
        ds = list(seeds.values())
        if ds[0]["preset"]["stage"] != "train_lighting" or "unavailable" in ds[0]["preset"]:
            continue
        point = {"label": name, "seeds": len(ds)}
        for field, source, key in (
            ("seconds", "timings", "seconds_per_image"),
            ("train_minutes", "timings", "train_minutes"),
            ("insertion_psnr", "metrics", "edit/insert/all/lightnet/psnr"),
            ("render_psnr", "metrics", "test/render_psnr"),
        ):
            point[field], point[f"{field}_err"] = spread([d[source].get(key, float("nan")) for d in ds])
        points.append(point)
    return points


def ablation_tables(
    light_rows: list[str], mat_rows: list[str], claim_rows: list[str], runs: dict, figures: str
) -> list[str]:
    """The ablation tables as docs/results.md embeds them (the same rows as ablations.md; `figures`: the
    ablation runs' folder relative to the page)."""
    layers = [
        f"[{name}, seed {seed}]({figures}/{name}-s{seed}/layers.png)"
        for name, seeds in sorted(runs.items())
        for seed, d in sorted(seeds.items())
        if "layers.png" in d.get("figures", [])
    ]
    return [
        "Intervals in these tables are 95 % t intervals over seeds of the paired (same seed, same test views)",
        "differences, except a render-time claim's (a preset scoring `full`'s own weights), which runs over the",
        "test views (each view's difference averaged over the seeds' weights) where the runs wrote per-view scores.",
        "Each claim is decided on its one primary metric (bold), Holm-adjusted over the claims",
        "(`pipeline/metrics/verdicts.py`); secondary metrics are reported without a verdict.",
        "",
        "### Paper claims",
        "",
        *claim_rows,
        "",
        "The paper's fig. 4 (the same weights under the MC layer and under a changed layer, glossy crops "
        "beside the photo): " + (", ".join(layers) if layers else "no render-time preset ran") + ".",
        "",
        "### LightNet",
        "",
        *light_rows,
        "",
        "### MaterialNet",
        "",
        *mat_rows,
        "",
        "### Stability",
        "",
        *stability(runs, figures),
    ]


def main_material(reports: Path) -> dict | None:
    """The main `train_material` model's metrics (reports/train_material/metrics.json), None if absent; a
    corrupt file raises naming it."""
    return read_json(reports / "train_material" / "metrics.json")


def tabulate(runs: dict, reports: Path) -> dict:
    """The ablation tables' rows and their numbers, and the claims' verdicts (the main MaterialNet's
    metrics under `reports` decide which MaterialNet claims are comparable): {light, mat, claims: (rows,
    numbers), verdicts}. ablations.md and docs/results.md both print these."""
    verdicts = claim_verdicts(runs, not_comparable=reference_comparability(runs, main_material(reports)))
    return {
        "light": table({**runs, **threshold_runs(runs)}, "train_lighting", LIGHT_COLUMNS),
        "mat": table(runs, "train_material", MATERIAL_COLUMNS),
        "claims": claims_table(runs, verdicts),
        "verdicts": verdicts,
    }


def results_markdown(reports: Path, ablate_dir: Path, profile: str, claims: dict | None = None) -> str:
    """docs/results.md from the reports and the claims (`read_runs`) alone (what the stage writes; the test
    renders it the same way)."""
    runs = read_runs(ablate_dir, claims)
    return results_from(reports, runs, tabulate(runs, reports), profile)


def results_from(reports: Path, runs: dict, t: dict, profile: str) -> str:
    """docs/results.md from the reports, the ablation runs (`read_runs`) and their tables (`tabulate`)."""
    tables = ablation_tables(t["light"][0], t["mat"][0], t["claims"][0], runs, "../reports/ablate")
    counts: dict[str, int] = {}
    for v in t["verdicts"].values():
        if v["role"] == "primary":  # a secondary metric has no verdict to count
            counts[v["verdict"]] = counts.get(v["verdict"], 0) + 1
    return render_results(reports, tables, profile, counts)


def figure_links(reports: Path, out: Path) -> list[str]:
    lines = []
    for png in sorted(reports.rglob("*.png")):
        if out in png.parents:
            continue
        rel = Path("..") / png.relative_to(reports)
        lines.append(f"- [{png.relative_to(reports)}]({rel})")
    return lines


def run(cfg: DictConfig) -> dict[str, float]:
    import mlflow

    reports, out = Path(cfg.reports_root), Path(cfg.report_dir)
    claims = OmegaConf.to_container(cfg.claims, resolve=True)
    runs = read_runs(Path(cfg.ablate_dir), claims)
    out.mkdir(parents=True, exist_ok=True)
    t = tabulate(runs, reports)
    (light_rows, light_numbers), (mat_rows, mat_numbers) = t["light"], t["mat"]
    claim_rows, claim_numbers = t["claims"]
    doc = [
        f"# Ablations ({cfg.profile_name})",
        "",
        "Each preset changes one thing against its reference (`full` for LightNet, `material_small` for",
        "MaterialNet) on the same seed, data, schedule and test views; a render-time preset",
        "(`no_mc_render`, `uniform_render`) scores `full`'s own weights with another render layer.",
        "Paper claims: the preset minus its reference on the metrics the claim is about, the mean over",
        "seeds with its 95 % t interval over the seeds' differences (both the seeds' and the views' noise",
        "are in it) and each seed's difference; a render-time claim (`full`'s own weights under another",
        "layer) is conditional on those weights, so its units are the test views (`views.csv`: each view's",
        "difference averaged over the seeds' weights, a t interval over views), falling back to seeds for",
        "runs without per-view scores. Verdicts (`pipeline/metrics/verdicts.py`): each claim is",
        "decided on its one primary metric (bold; declared with its direction in conf/claims/), the claims",
        "one family tested at 5 % family-wise by Holm's procedure; secondary metrics are reported beside it",
        "without a verdict, so adding one never weakens another claim's test. Verdicts: supported,",
        "contradicted, inconclusive, not testable (fewer than 2 seeds, every seed the same difference, or",
        "the preset cannot run here), not comparable (a MaterialNet reference whose normal error is more",
        f"than {REFERENCE_TOLERANCE:.0%} above the main model's: a claim about the trained method is not judged",
        "against a half-trained one) or diverged (a seed's run diverged: counted, a failed stability check);",
        "`power`: the chance of a verdict if the true difference were the stated size (0.5 dB on a PSNR,",
        "else 5 % of the reference's mean) with the seed spread observed; the minimal detectable effect",
        "(power 0.8) bounds an inconclusive claim, which reads as no effect larger than it, not as none;",
        "the seeds that would give power 0.8 at the stated size (all three post hoc, from that spread).",
        "Preset tables: means over seeds ± half their range; s/image: median seconds of a full-frame",
        "re-render at the evaluation spp on this machine; glossy re-render: the test views' pixels with",
        "ground-truth roughness at most `glossy.max_roughness` (conf/ablate.yaml).",
        "`full:out_threshold_t`: `full`'s own weights tested with the",
        "out-of-view branch queried only where u >= t, paired with `full` seed by seed.",
        "",
        *ablation_tables(light_rows, mat_rows, claim_rows, runs, "../ablate")[3:],
    ]
    (out / "ablations.md").write_text("\n".join(doc) + "\n")
    results_doc = Path(cfg.results_doc)
    results_doc.parent.mkdir(parents=True, exist_ok=True)
    results_doc.write_text(results_from(reports, runs, t, cfg.profile_name))  # the runs and tables above
    points = pareto_points(runs)
    figure = pareto_figure(
        points,
        out / "pareto.png",
        title=f"accuracy against speed ({cfg.profile_name}); bars: half the range over seeds",
    )
    summary = ["# Summary", "", "- [ablations.md](ablations.md)", "- [pareto.png](pareto.png)", "", "## Figures"]
    summary += figure_links(reports, out)
    (out / "summary.md").write_text("\n".join(summary) + "\n")
    metrics = {k: v for k, v in {**light_numbers, **mat_numbers, **claim_numbers}.items() if math.isfinite(v)}
    metrics["presets"] = float(len(runs))
    metrics["runs"] = float(sum(len(s) for s in runs.values()))
    with stage_run("report", cfg) as run:
        publish(out, metrics, artifacts=(out / "ablations.md", out / "summary.md", figure))
        with mlflow.start_run(
            run_name=f"ablate-{cfg.profile_name}", nested=True, tags={"stage": "ablate", "sweep": "true"}
        ) as parent:
            mlflow.log_artifact(str(figure), "figures")
            mlflow.log_artifact(str(out / "ablations.md"))
            attach_children(parent.info.run_id, runs, run.info.experiment_id)
    return metrics


def attach_children(parent_id: str, runs: dict, experiment_id: str) -> int:
    """Make the latest finished `ablate` run of every preset and seed in the reports a child of
    `parent_id` (MLflow's parent tag); returns how many were attached."""
    import mlflow

    client = mlflow.MlflowClient()
    attached = 0
    for name, seeds in runs.items():
        for seed in seeds:
            found = client.search_runs(
                [experiment_id],
                filter_string=(
                    f"tags.stage = 'ablate' and tags.preset = '{name}' and tags.seed = '{seed}' "
                    "and attributes.status = 'FINISHED'"
                ),
                order_by=["attributes.start_time DESC"],
                max_results=1,
            )
            if found:
                client.set_tag(found[0].info.run_id, "mlflow.parentRunId", parent_id)
                attached += 1
    return attached
