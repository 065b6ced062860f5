"""`python -m pipeline.bench.nonbox_rooms`: where a room box fails. Trained LightNets on rooms that are not
boxes, and on the out-of-distribution style with insertion cases.

Every room `synthesize` draws is a box, and the `roombox` out-of-view branch models the unseen room as
one; the out-of-distribution set (`synthesize`'s `ood`) has no insertion cases. This bench renders its own
held-out rooms in groups (`GROUPS`): `box`, `l_shaped`, `alcove` and `sloped` are the same `--rooms`
rooms of the stage's generator (its profile's config, seeds drawn from `--seed` + `SEED_OFFSET`, never a
training room), each made into that shape by `data.synth.room_shapes` (so the groups are paired by
room, their cameras drawn anew); `ood` are rooms of the out-of-distribution style (`synthesize`'s
`ood.synth`). Each room gets one view with the stage's probes and insertion cases, rendered by
`synthesize`'s own scene renderer, and is preprocessed as `preprocess` does into a test split, beside
links to the main data's training and validation shards (the baselines read the training split).

Each `--light-net NAME=PATH` export (e.g. the `train_lighting` stage's `nerf` branch and the stage run
with `model.light_net.out_of_view.kind=roombox`) is scored as `bench.out_of_view_kinds` scores it:
re-render PSNR and surface and free light nMSE per view, object insertion PSNR per case at the `edit`
stage's converged scoring (the nearest ground-truth probe's and the scaled constant's rows beside the
first export). Per group, every export after the first is paired with the first (insertion by case,
views resampled whole; the view metrics by view), 95 % bootstrap intervals; a difference whose
interval holds 0 is none. No target: the map of where each branch fails.
Writes reports/bench/nonbox_rooms.json (or `--name`) and a PNG of the groups' sample views and scores.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict
from multiprocessing import get_context
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from tqdm import tqdm

from pipeline.bench.common import add_threads_option, apply_threads, publish
from pipeline.bench.learning_curve import CLASSES  # insertion classes, "all" last
from pipeline.bench.out_of_view_kinds import VIEW_METRICS  # the per-view metrics paired between exports

GROUPS = ("box", "l_shaped", "alcove", "sloped", "ood")
SEED_OFFSET = 5000  # the stage's main rooms are drawn from its seed, the ood set from seed + 1000


def group_configs(profile: str, groups, rooms: int) -> dict:
    """{group: SynthConfig} from `synthesize`'s config on `profile`: one view a room, insertion and
    editing cases on, every room in the test split; `ood` with the out-of-distribution set's room style."""
    from omegaconf import OmegaConf

    from pipeline.bench.common import compose
    from pipeline.data.synth.generate import SynthConfig

    cfg = compose("synthesize", [f"profile={profile}"])
    base = OmegaConf.to_container(cfg.synth, resolve=True)
    ood = OmegaConf.to_container(cfg.ood.synth, resolve=True)
    out = {}
    for group in groups:
        merged = OmegaConf.merge(base, ood if group == "ood" else {})
        merged = OmegaConf.merge(
            merged, {"scenes": rooms, "views": 1, "splits": {"train": 0.0, "val": 0.0, "test": 1.0}}
        )
        merged.cases.enabled = True
        out[group] = SynthConfig.from_dict(OmegaConf.to_container(merged))
    return out


_GENERATOR: dict = {}  # a worker's own `generate.generate_room`, before any job rebound it


def render_group_scene(group: str, index: int, seed: int, cfg, out: str, variant: str, threads: int) -> dict:
    """One room of `group`, rendered by `synthesize`'s `render_scene` as `<group>_<index>` (a worker).

    `render_scene` draws its room with `generate.generate_room`; for a reshaped group this spawned worker
    process rebinds that name to the generator followed by `room_shapes.reshape_room` (and back to the
    generator alone for the next job of another group), so the scene, its probes and its cases are
    rendered exactly as the stage renders a box room."""
    from pipeline.data.synth import generate
    from pipeline.data.synth.room_shapes import reshape_room

    draw = _GENERATOR.setdefault("generate_room", generate.generate_room)  # the stage's, kept across jobs

    def reshaped(scene_seed: int, views: int, room_cfg):
        room, footprints, rng = draw(scene_seed, views, room_cfg)
        room, footprints = reshape_room(room, footprints, rng, group, room_cfg)
        return room, footprints, rng

    generate.generate_room = draw if group in ("box", "ood") else reshaped
    return generate.render_scene(index, seed, cfg, out, variant, threads, with_cases=True, prefix=group)


def synthesize_groups(root: Path, configs: dict, seed: int, workers: int, progress: bool = True) -> dict:
    """Render every group's rooms into `root` (a fresh folder), all in its test split. The rooms of the
    groups that reshape a box are the `box` group's (same seed and index). Returns per-scene statistics."""
    from pipeline.data import interiorverse as iv
    from pipeline.data.synth import mitsuba_backend as mb
    from pipeline.data.synth.generate import dataset_record, scene_name

    root.mkdir(parents=True, exist_ok=False)
    variant = mb.choose_variant("auto")
    jobs = [(g, i) for g, c in configs.items() for i in range(c.scenes)]
    workers = max(1, min(workers, len(jobs)))
    threads = max(1, (os.cpu_count() or 1) // workers)
    results = []
    with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
        futures = [
            pool.submit(render_group_scene, g, i, seed + SEED_OFFSET, configs[g], str(root), variant, threads)
            for g, i in jobs
        ]
        for fut in tqdm(futures, desc=f"rooms ({variant})", unit="room", disable=not progress):
            results.append(fut.result())
    iv.write_splits(root, {"test": sorted(scene_name(i, g) for g, i in jobs)})
    summary = {
        "variant": variant,
        "scenes": sorted(results, key=lambda r: r["scene"]),
        "splits": {"train": 0, "val": 0, "test": len(jobs)},
        "config": {g: asdict(c) for g, c in configs.items()},
        "seed": seed + SEED_OFFSET,
    }
    max_depth = {c.max_depth for c in configs.values()}
    if len(max_depth) != 1:
        raise ValueError(f"the groups' configs differ in max_depth ({sorted(max_depth)}): the scoring reads one")
    # the generator's record as `synthesize` writes it; `config` holds the one max_depth the scoring reads
    record = dataset_record(
        {**summary, "config": {**asdict(next(iter(configs.values()))), "groups": summary["config"]}}
    )
    (root / "dataset.json").write_text(json.dumps(record, indent=1, default=list))
    return summary


def stress_data_dir(root: Path, out: Path, main_data_dir: Path, height: int, width: int) -> Path:
    """`root`'s rooms preprocessed into `out` as the test split, with the main data's training and
    validation shards linked beside them (`link_main_splits`)."""
    from pipeline.data.preprocess import preprocess

    preprocess(root, out, height, width, source="synthetic", required=("test",), progress=False)
    link_main_splits(out, main_data_dir)
    return out


def check_inputs(exports: dict[str, str], main_data_dir: Path, material_path: Path, keep: Path | None) -> None:
    """Refuse, naming the option, what would fail only after the rooms are rendered: a missing export or
    MaterialNet, main data without a manifest or a training or validation split, a `--keep` folder that
    already holds rooms."""
    for name, path in exports.items():
        if not Path(path).is_file():
            raise FileNotFoundError(f"--light-net {name}: {path} not found")
    if not material_path.is_file():
        raise FileNotFoundError(f"--material {material_path}: not found")
    if not (main_data_dir / "manifest.json").is_file():
        raise FileNotFoundError(f"--data-dir {main_data_dir}: no manifest.json (run `dvc repro preprocess`)")
    main_splits(main_data_dir)
    if keep is not None and any((keep / sub).exists() for sub in ("rooms", "shards")):
        raise FileExistsError(f"--keep {keep}: already holds rooms or shards; give a new or empty folder")


MAIN_SPLITS = ("train", "val")  # what the bench takes from the main data: the baselines read the training split


def main_splits(main_data_dir: Path) -> dict:
    """{split: manifest entry} of `MAIN_SPLITS` in `main_data_dir`'s manifest; a missing one is refused."""
    splits = json.loads((main_data_dir / "manifest.json").read_text()).get("splits", {})
    for split in MAIN_SPLITS:
        if split not in splits:
            raise ValueError(f"{main_data_dir}/manifest.json: has no {split} split to score the baselines with")
    return {split: splits[split] for split in MAIN_SPLITS}


def link_main_splits(out: Path, main_data_dir: Path) -> None:
    """Link the training and validation shards of `main_data_dir` into the shard folder `out` and list
    them in its manifest: the scaled-constant baseline reads the training split."""
    main = main_splits(main_data_dir)
    manifest = json.loads((out / "manifest.json").read_text())
    for split, entry in main.items():
        for shard in entry["shards"]:
            (out / shard["file"]).symlink_to((main_data_dir / shard["file"]).resolve())
        manifest["splits"][split] = entry
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))


def group_of(view_id: str) -> str:
    """The group of a view id `<group>_<index>/<view>`."""
    return view_id.split("/")[0].rsplit("_", 1)[0]


def group_summary(records: dict, views: dict, first: str, resamples: int, seed: int) -> dict:
    """Per group and export: insertion PSNR per class (mean and interval, and the first export's rows of
    the baselines), the view metrics' means, and every later export minus the first, paired."""
    from pipeline.bench.learning_curve import compare
    from pipeline.bench.out_of_view_kinds import view_pairs

    out = {}
    for group in sorted({group_of(v["id"]) for v in views[first]}, key=GROUPS.index):
        row = {}
        ref_recs = [r for r in records[first] if group_of(r["view"]) == group]
        ref_views = [v for v in views[first] if group_of(v["id"]) == group]
        for name in records:
            recs = [r for r in records[name] if group_of(r["view"]) == group]
            per_view = [v for v in views[name] if group_of(v["id"]) == group]
            entry = {
                "views": len(per_view),
                "cases": len(recs),
                "insertion": compare(recs, ref_recs, resamples, seed),
                **{k: float(np.mean([v[k] for v in per_view])) for k in VIEW_METRICS},
            }
            if name != first:
                entry["views_minus_first"] = view_pairs(per_view, ref_views, resamples, seed)
            row[name] = entry
        row["baselines"] = {  # a group whose views drew no insertion case has none
            base: {
                c: float(np.mean([r[f"{base}/psnr"] for r in ref_recs if c == "all" or r["label"] == c]))
                for c in CLASSES
                if any(c == "all" or r["label"] == c for r in ref_recs)
            }
            for base in ("nearest_probe", "scaled_constant")
        }
        out[group] = row
    return out


def run(
    exports: dict[str, str],
    groups=GROUPS,
    rooms: int = 10,
    seed: int = 0,
    data_dir: str = "outputs/preprocess",
    material_path: str = "outputs/train_material/model.pt",
    profile: str = "tiny",
    resamples: int = 2000,
    workers: int = 0,
    edit_overrides=(),
    keep: str | None = None,
) -> dict:
    """Render the groups' rooms, score every export on them (module docstring). keep: a folder to keep
    the rendered rooms and shards in (else a temporary one)."""
    from pipeline.bench.common import training_system
    from pipeline.bench.learning_curve import REFERENCE_ROWS, score
    from pipeline.bench.out_of_view_kinds import export_kind, load_export
    from pipeline.data.datamodules import InteriorVerseDataModule

    if not exports:
        raise ValueError("give at least one --light-net NAME=PATH")
    bad = [g for g in groups if g not in GROUPS]
    if bad or not groups:
        raise ValueError(f"--groups {' '.join(groups)}: choose some of {', '.join(GROUPS)}")
    if rooms < 1:
        raise ValueError(f"--rooms {rooms}: need at least 1")
    main_dir = Path(data_dir)
    check_inputs(exports, main_dir, Path(material_path), Path(keep) if keep else None)  # before the long render
    configs = group_configs(profile, groups, rooms)
    report = {"exports": dict(exports), "groups": list(groups), "rooms": rooms, "seed": seed, "profile": profile}
    with tempfile.TemporaryDirectory() as scratch:
        work = Path(keep) if keep else Path(scratch)
        root, shards = work / "rooms", work / "shards"
        synth = synthesize_groups(root, configs, seed, workers or (os.cpu_count() or 1))
        first_cfg = next(iter(configs.values()))
        stress_data_dir(root, shards, main_dir, first_cfg.height, first_cfg.width)
        report["rooms_rendered"] = _room_statistics(root, synth)
        report["samples"] = _samples(shards)
        records, views = {}, {}
        for i, (name, path) in enumerate(exports.items()):
            o = [
                f"profile={profile}",
                f"data_dir={shards}",
                f"material_path={material_path}",
                f"model.light_net.out_of_view.kind={export_kind(path)}",
            ]
            system, _, cfg = training_system("train_lighting", o, seed)
            dm = InteriorVerseDataModule(cfg.data_dir, batch_size=1, seed=seed, lighting=True)
            dm.setup("test")
            load_export(system, path)
            per_view: list[dict] = []
            rows = REFERENCE_ROWS if i == 0 else ("lightnet",)
            edit = [f"profile={profile}", f"data_root={root}", f"data_dir={shards}", *edit_overrides]
            _, recs = score(system, cfg, dm.test_dataloader(), rows, seed, work, edit, per_view)
            records[name], views[name] = recs, per_view
        report["groups_scored"] = group_summary(records, views, next(iter(exports)), resamples, seed)
    report["summary"] = summary_tables(report)
    return report


def summary_tables(report: dict) -> dict:
    """The page's tables: each group's scores per export (and the baselines' insertion), and every later
    export minus the first per group, paired."""
    names = list(report["exports"])
    rows, pairs = [], []
    for group, row in report["groups_scored"].items():
        for name in [*names, "nearest_probe", "scaled_constant"]:
            scores = row[name] if name in names else None
            insertion = (
                {c: v["psnr"] for c, v in scores["insertion"].items()} if scores else row["baselines"].get(name, {})
            )
            rows.append(
                {
                    "group": group,
                    "light": name if scores else name.replace("_", " "),
                    "views": scores["views"] if scores else None,
                    "cases": row[names[0]]["cases"],
                    **{f"{c} (dB)": insertion.get(c) for c in CLASSES},
                    "re-render (dB)": scores["render_psnr"] if scores else None,
                    "surface nMSE": scores["surf_light_nmse"] if scores else None,
                    "free nMSE": scores["free_light_nmse"] if scores else None,
                }
            )
        for name in names[1:]:
            for c, v in row[name]["insertion"].items():
                lo, hi = v["minus_reference_lo"], v["minus_reference_hi"]
                pairs.append(
                    {"group": group, "metric": f"insertion {c} (dB)", "diff": v["minus_reference"], "lo": lo, "hi": hi}
                )
            for metric, d in row[name]["views_minus_first"].items():
                pairs.append({"group": group, "metric": metric, "diff": d["diff"], "lo": d["lo"], "hi": d["hi"]})
    out = {"each group (held-out rooms, one view each)": rows}
    if pairs:
        out[f"{' and '.join(names[1:])} minus {names[0]}, paired (95 % bootstrap)"] = pairs
    return out


def _room_statistics(root: Path, synth: dict) -> dict:
    """Per group: rooms, insertion cases, lamps and windows, and the sloped rooms' tilts (degrees)."""
    from pipeline.data.synth.room_shapes import slope_angle_deg
    from pipeline.data.synth.scene import Room

    out: dict = {"variant": synth["variant"]}
    for s in synth["scenes"]:
        g = out.setdefault(group_of(s["scene"] + "/000"), {"rooms": 0, "insertion_cases": 0, "lamps": 0, "windows": 0})
        g["rooms"] += 1
        g["insertion_cases"] += s["insertion_cases"]
        g["lamps"] += s["lamps"]
        g["windows"] += int(s["windows"] > 0)
        if s["scene"].startswith("sloped"):
            room = Room.from_json(json.loads((root / s["scene"] / "scene.json").read_text()))
            g.setdefault("tilt_deg", []).append(round(slope_angle_deg(room), 1))
    return out


def _samples(shards: Path, per_group: int = 2) -> dict:
    """The first views' photos of each group for the figure: {group: [{id, png}]}, each photo tone-mapped
    to 8 bits and PNG-encoded (base64 text: a few kilobytes, where pixel lists would bloat the JSON)."""
    from pipeline.data.datasets import ShardDataset
    from pipeline.data.formats.photo import tonemap

    data = ShardDataset(shards, "test", lighting=False)
    out: dict = {}
    for i in range(len(data)):
        item = data[i]
        picks = out.setdefault(group_of(item["id"]), [])
        if len(picks) < per_group:
            im = item["im"].clamp(min=0).permute(1, 2, 0).numpy()
            picks.append({"id": item["id"], "png": png_text(tonemap(im, exposure=1.0))})
    return out


def png_text(image: np.ndarray) -> str:
    """An (H, W, 3) image in [0, 1] as base64 PNG text (8 bits a channel)."""
    import base64
    import io

    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray((image * 255).round().astype(np.uint8)).save(buffer, format="PNG")
    return base64.b64encode(buffer.getvalue()).decode("ascii")


def png_image(text: str) -> np.ndarray:
    """`png_text`'s image back, (H, W, 3) uint8."""
    import base64
    import io

    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(base64.b64decode(text))).convert("RGB"))


def plot(report: dict, path) -> None:
    groups = list(report["groups_scored"])
    names = list(report["exports"])
    rows = max(1, min(2, max(len(v) for v in report["samples"].values())))
    fig = Figure(figsize=(2.3 * len(groups) + 1, 2.0 * rows + 4.5))
    spec = fig.add_gridspec(rows + 1, len(groups) * 2, height_ratios=[1] * rows + [2.2])
    for j, g in enumerate(groups):
        for k, sample in enumerate(report["samples"].get(g, [])[:rows]):
            ax = fig.add_subplot(spec[k, 2 * j : 2 * j + 2])
            ax.imshow(png_image(sample["png"]))
            ax.set_axis_off()
            if k == 0:
                ax.set_title(g.replace("_", " "), fontsize=10)
    width = 0.8 / (len(names) + 1)
    scored = [g for g in groups if "all" in report["groups_scored"][g][names[0]]["insertion"]]
    ax = fig.add_subplot(spec[rows, : len(groups)])
    x = np.arange(len(scored))
    for i, name in enumerate(names):
        ins = [report["groups_scored"][g][name]["insertion"]["all"] for g in scored]
        err = [[r["psnr"] - r["psnr_lo"] for r in ins], [r["psnr_hi"] - r["psnr"] for r in ins]]
        ax.bar(x + i * width, [r["psnr"] for r in ins], width, yerr=err, capsize=3, label=name)
    probe = [report["groups_scored"][g]["baselines"]["nearest_probe"]["all"] for g in scored]
    ax.bar(x + len(names) * width, probe, width, color="0.7", label="nearest ground-truth probe")
    ax.set_xticks(x + width * len(names) / 2, [g.replace("_", " ") for g in scored], fontsize=8)
    ax.set_ylabel("insertion PSNR, all objects (dB)")
    lows = [report["groups_scored"][g][n]["insertion"]["all"]["psnr_lo"] for g in scored for n in names]
    ax.set_ylim(min([*probe, *lows], default=0) - 2, None)
    ax.legend(fontsize=7, loc="lower right")
    ax = fig.add_subplot(spec[rows, len(groups) :])
    x = np.arange(len(groups))
    width = 0.8 / (2 * len(names))
    for i, name in enumerate(names):
        for k, (metric, hatch) in enumerate((("surf_light_nmse", ""), ("free_light_nmse", "//"))):
            values = [report["groups_scored"][g][name][metric] for g in groups]
            label = f"{name}, {'surface' if k == 0 else 'free'} probes"
            ax.bar(x + (2 * i + k) * width, values, width, hatch=hatch, color=f"C{i}", alpha=0.9, label=label)
    ax.axhline(1.0, color="0.5", lw=0.8)
    ax.set_xticks(x + width * (2 * len(names) - 1) / 2, [g.replace("_", " ") for g in groups], fontsize=8)
    ax.set_ylabel("light nMSE (mean over views; 1: no better than zero light)")
    shown = [report["groups_scored"][g][n][m] for g in groups for n in names for m in VIEW_METRICS[1:]]
    ax.set_ylim(max(0.0, min(shown) - 0.15), max(1.05, max(shown) + 0.05))
    ax.legend(fontsize=7, loc="lower left", ncol=2)
    fig.suptitle("Held-out rooms by shape: each group's first views; insertion (95 % bootstrap) and light error")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def parse_light_nets(items: list[str]) -> dict[str, str]:
    from pipeline.bench.out_of_view_kinds import parse_exports

    return parse_exports(items, "--light-net")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--light-net", nargs="+", required=True, metavar="NAME=PATH", help="LightNet exports to score")
    p.add_argument("--groups", nargs="+", default=list(GROUPS), help=f"of {', '.join(GROUPS)}")
    p.add_argument("--rooms", type=int, default=10, help="rooms per group (one view each)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--data-dir", default="outputs/preprocess", help="the main data (training and validation shards)")
    p.add_argument("--material", default="outputs/train_material/model.pt", help="the MaterialNet export")
    p.add_argument("--profile", default="tiny")
    p.add_argument("--resamples", type=int, default=2000)
    p.add_argument("--workers", type=int, default=0, help="render processes (0: one per core)")
    p.add_argument("--edit-override", action="append", default=[], help="an override of the edit config")
    p.add_argument("--keep", default=None, help="keep the rendered rooms and shards in this folder")
    p.add_argument("--name", default="nonbox_rooms")
    add_threads_option(p)
    args = p.parse_args(argv)
    apply_threads(args.threads)
    report = run(
        parse_light_nets(args.light_net),
        tuple(args.groups),
        args.rooms,
        args.seed,
        args.data_dir,
        args.material,
        args.profile,
        args.resamples,
        args.workers,
        args.edit_override,
        args.keep,
    )
    path = publish(args.name, report, plot)
    print(json.dumps(_headline(report), indent=1))
    print(f"wrote {path}")


def _headline(report: dict) -> dict:
    return {
        g: {n: round(r[n]["insertion"]["all"]["psnr"], 2) for n in report["exports"]}
        | {"nearest probe": round(r["baselines"]["nearest_probe"]["all"], 2)}
        for g, r in report["groups_scored"].items()
        if r["baselines"]["nearest_probe"]
    }


if __name__ == "__main__":
    main()
