"""The `synthesize` stage's work: render procedural rooms into an InteriorVerse-layout dataset.

Scenes are independent, so they render in parallel worker processes (spawned: Mitsuba's variant is
process-global), each scene deterministic in (seed, scene index).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pipeline.data import cases as case_io
from pipeline.data import interiorverse as iv
from pipeline.data.synth import mitsuba_backend as mb
from pipeline.data.synth.cases import CaseConfig, generate_cases
from pipeline.data.synth.denoise import denoise_hdr
from pipeline.data.synth.scene import RoomConfig, generate_room, propose_camera
from pipeline.data.synth.views import LightingConfig, Timer, camera_is_usable, gbuffer, lighting_probes

MARKER = ".invrender-synthesize"  # marks a folder this stage owns (and may therefore clear)


@dataclass
class SynthConfig:
    scenes: int = 20
    views: int = 5
    width: int = 160
    height: int = 120
    spp: int = 32
    max_depth: int = 6
    denoise: bool = False  # Open Image Denoise on the beauty image (see data/synth/denoise.py)
    half_float: bool = False
    splits: dict = field(default_factory=lambda: {"train": 0.7, "val": 0.15, "test": 0.15})
    variant: str = "auto"
    workers: int = 0  # 0 = one per core
    room: RoomConfig = field(default_factory=RoomConfig)
    lighting: LightingConfig = field(default_factory=LightingConfig)
    cases: CaseConfig = field(default_factory=CaseConfig)

    @staticmethod
    def from_dict(d: dict) -> SynthConfig:
        d = dict(d)
        room = RoomConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.pop("room", {}).items()})
        light = LightingConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.pop("lighting", {}).items()})
        case_keys = d.pop("cases", {})
        bad = set(case_keys) - set(CaseConfig.__dataclass_fields__)
        if bad:
            raise ValueError(f"synth.cases: unknown key(s) {sorted(bad)}")
        cases = CaseConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in case_keys.items()})
        unknown = set(d) - set(SynthConfig.__dataclass_fields__)
        if unknown:
            raise ValueError(f"synth: unknown key(s) {sorted(unknown)}")
        return SynthConfig(**d, room=room, lighting=light, cases=cases)


SCENE_PREFIX = "scene"  # the main set's rooms: scene_0000, scene_0001, ...


def scene_name(index: int, prefix: str = SCENE_PREFIX) -> str:
    """`<prefix>_<index, 4 digits>`: a second set with its own prefix (the out-of-distribution rooms) never
    names a view the way the main set does."""
    return f"{prefix}_{index:04d}"


def scene_seed(seed: int, index: int) -> int:
    """Independent 31-bit seed per scene from the stage seed (numpy SeedSequence spawning)."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1)[0] & 0x7FFFFFFF)


def assign_splits(n: int, fractions: dict, seed: int, prefix: str = SCENE_PREFIX) -> dict[str, list[str]]:
    """Split scene names by scene (never by view): shuffled, val/test get round(f*n), at least one each
    whose fraction is positive, the rest train. A split with fraction 0 stays empty (an evaluation-only
    dataset: `{train: 0, val: 0, test: 1}`); a positive training fraction needs a training scene left."""
    unknown = set(fractions) - {"train", "val", "test"}
    if unknown or any(not 0 <= float(f) <= 1 for f in fractions.values()):
        raise ValueError(f"synth.splits={fractions}: give train, val and test fractions in [0, 1]")
    f_test, f_val, f_train = (float(fractions.get(k, 0.0)) for k in ("test", "val", "train"))
    needed = sum(f > 0 for f in (f_test, f_val, f_train))
    if n < max(needed, 1):
        raise ValueError(f"synth.scenes={n}: need at least {max(needed, 1)} scenes for the non-empty splits")
    names = [scene_name(i, prefix) for i in np.random.default_rng(seed).permutation(n)]
    n_test = max(1, round(f_test * n)) if f_test > 0 else 0
    n_val = max(1, round(f_val * n)) if f_val > 0 else 0
    if f_train > 0 and n_test + n_val >= n:
        raise ValueError(f"synth.splits={fractions}: leaves no training scene out of {n}")
    if f_train == 0 and n_test + n_val != n:
        raise ValueError(f"synth.splits={fractions}: with no training fraction, val and test must hold all {n}")
    return {
        "test": sorted(names[:n_test]),
        "val": sorted(names[n_test : n_test + n_val]),
        "train": sorted(names[n_test + n_val :]),
    }


CAMERA_REDRAWS = 20  # draws of a new camera for a view whose camera is unusable, before keeping the last


def usable_camera(scene, room, camera, rng, room_cfg: RoomConfig, footprints) -> tuple:
    """A view's camera, or, while it is unusable (`views.camera_is_usable`), a new one drawn from `rng`
    (`scene.propose_camera`, at most `CAMERA_REDRAWS` times): (the camera, the draws it took)."""
    for redraws in range(CAMERA_REDRAWS):
        if camera_is_usable(scene, camera):
            return camera, redraws
        camera = propose_camera(room, rng, room_cfg, footprints)
    return camera, CAMERA_REDRAWS


def render_photo(scene, camera, cfg: SynthConfig, seed: int, timer: Timer | None = None) -> np.ndarray:
    """A view's photo as the stage writes it: (H, W, 3) float32 HDR at `cfg`'s size and samples, denoised
    when `cfg.denoise` (`timer` takes the `render` and `denoise` seconds)."""
    timer = timer or Timer()
    with timer("render"):
        im = mb.render_view(scene, camera, cfg.width, cfg.height, cfg.spp, seed=seed)
    if cfg.denoise:
        with timer("denoise"):
            im = denoise_hdr(im)
    return im


def render_scene(
    index: int,
    seed: int,
    cfg: SynthConfig,
    out: str,
    variant: str,
    threads: int,
    with_cases: bool = False,
    prefix: str = SCENE_PREFIX,
) -> dict:
    """Generate, render and write one scene, `scene_name(index, prefix)` (runs in a worker process);
    with_cases (val and test scenes) also draws and renders its insertion and editing cases. Returns
    per-scene statistics. The room and its random numbers depend on `seed` and `index` only."""
    mb.init_mitsuba(variant, threads)
    timer = Timer()
    s_seed = scene_seed(seed, index)
    with timer("build"):
        room, footprints, rng = generate_room(s_seed, cfg.views, cfg.room)
        scene = mb.load_scene(room, cfg.max_depth)
    name = scene_name(index, prefix)
    redraws = 0
    for v, cam in enumerate(room.cameras):
        with timer("camera"):
            room.cameras[v], n = usable_camera(scene, room, cam, rng, cfg.room, footprints)
        redraws += n
    cameras, valid_fraction, n_surf, n_free, n_obj, n_edit = {}, [], 0, 0, 0, 0
    for v, cam in enumerate(room.cameras):
        view = f"{v:03d}"
        with timer("gbuffer"):
            gb = gbuffer(scene, cam, cfg.width, cfg.height)
        im = render_photo(scene, cam, cfg, s_seed * 64 + v, timer)
        with timer("lighting"):
            light = lighting_probes(scene, cam, gb, cfg.lighting, rng, seed=s_seed * 64 + v)
        with timer("write"):
            iv.write_view(out, name, view, {"im": im, **gb}, half=cfg.half_float)
            iv.write_light(out, name, view, light)
        if with_cases and cfg.cases.enabled:
            with timer("cases"):
                # their own generator: adding or changing cases never moves the room's random numbers
                case_rng = np.random.default_rng([s_seed, v, 0xCA5E])
                cases, arrays = generate_cases(
                    room, scene, cam, gb, cfg.cases, case_rng, s_seed * 64 + v, cfg.max_depth
                )
                case_io.write_cases(out, name, view, cases.to_json(), arrays)
            n_obj, n_edit = n_obj + len(cases.objects), n_edit + len(cases.edits)
        cameras[view] = {
            "fov_x_deg": cam.fov_x_deg,
            "width": cfg.width,
            "height": cfg.height,
            **mb.intrinsics(cam.fov_x_deg, cfg.width, cfg.height),
            "world_from_view": mb.world_from_view(cam).tolist(),
        }
        valid_fraction.append(float(gb["mask"].mean()))
        n_surf += len(light["surf_position"])
        n_free += len(light["free_position"])
    (Path(out) / name / "cameras.json").write_text(json.dumps(cameras, indent=1))
    (Path(out) / name / "scene.json").write_text(json.dumps(room.to_json()))
    return {
        "scene": name,
        "seconds": timer.seconds,
        "redraws": redraws,
        "valid_fraction": valid_fraction,
        "surface_probes": n_surf,
        "free_probes": n_free,
        "insertion_cases": n_obj,
        "edit_cases": n_edit,
        "shapes": len(room.shapes),
        "windows": len(room.windows),
        "lamps": sum(s.role == "lamp" for s in room.shapes),
    }


def prepare_output(out: Path) -> None:
    """Start from an empty output folder. A non-empty folder is cleared only if this stage made it."""
    if out.exists() and any(out.iterdir()):
        if not (out / MARKER).exists():
            raise FileExistsError(
                f"{out}: exists, is not empty and was not written by `synthesize`; refusing to clear it"
            )
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / MARKER).write_text("written by the synthesize stage; cleared on every run\n")


def synthesize(cfg: SynthConfig, out: str | Path, seed: int, progress: bool = True, prefix: str = SCENE_PREFIX) -> dict:
    """Render `cfg.scenes` rooms into `out` (InteriorVerse layout + lighting + splits), named
    `<prefix>_0000`, ... (`scene_name`).

    Returns a summary: counts, the Mitsuba variant, timings (seconds) and per-scene statistics; the
    dataset's own `dataset.json` is the same without timings (`dataset_record`).
    """
    out = Path(out)
    splits = assign_splits(cfg.scenes, cfg.splits, seed, prefix)
    prepare_output(out)
    variant = mb.choose_variant(cfg.variant)
    cores = os.cpu_count() or 1
    workers = max(1, min(cfg.workers or cores, cfg.scenes))
    threads = max(1, cores // workers)
    t0 = time.perf_counter()
    results = []
    bar = tqdm(total=cfg.scenes, desc=f"synthesize ({variant}, {workers} workers)", unit="scene", disable=not progress)
    with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:  # variant is per process
        with_cases = set(splits["val"]) | set(splits["test"])
        futures = [
            pool.submit(
                render_scene, i, seed, cfg, str(out), variant, threads, scene_name(i, prefix) in with_cases, prefix
            )
            for i in range(cfg.scenes)
        ]
        for fut in as_completed(futures):
            results.append(fut.result())
            bar.update(1)
    bar.close()
    wall = time.perf_counter() - t0
    iv.write_splits(out, splits)
    results.sort(key=lambda r: r["scene"])
    summary = {
        "variant": variant,
        "workers": workers,
        "wall_seconds": wall,
        "scenes": results,
        "splits": {k: len(v) for k, v in splits.items()},
        "config": asdict(cfg),
        "seed": seed,
    }
    (out / "dataset.json").write_text(json.dumps(dataset_record(summary), indent=1, default=list))
    return summary


# run-dependent fields of a summary: reported (reports/, MLflow), never written into the dataset, so the
# same seed and config give byte-identical outputs (and DVC hashes) on any machine and run
TIMING_KEYS = ("workers", "wall_seconds")
SCENE_TIMING_KEYS = ("seconds",)


def dataset_record(summary: dict) -> dict:
    """`dataset.json`: the summary without timings or worker counts."""
    record = {k: v for k, v in summary.items() if k not in TIMING_KEYS}
    record["scenes"] = [{k: v for k, v in s.items() if k not in SCENE_TIMING_KEYS} for s in summary["scenes"]]
    return record
