"""More training rooms for `bench.lamp_placement`: each room's photo, box and ceiling lamps, nothing else.

`synthesize` spends about 4 s a room on the lighting probes and insertion cases beside its photo; a lamp
placement learns from the photo alone, against a target read from the room (its box and lamp panels).
Here a room costs its photo only (about 1 s on one thread): the room drawn by the stage's generator
(`scene.generate_room`; its first view), the camera redrawn as the stage redraws it until usable, the photo
rendered at the stage's size and samples with its seed rule and denoised, so the photos are the stage's
own kind. Rooms come from `seed + SEED_OFFSET`, apart from the stage's rooms (`seed`), its ood set
(`seed + 1000`) and `bench.nonbox_rooms`' (`seed + 5000`).

Results go into a cache folder, one file per chunk of rooms (`chunk_<first index>.pt`) beside a
`meta.json` that names what they were made from (seed, profile, photo height, chunk size, the synth
config's hash): a later call with the same settings reuses them and renders only what is missing; other
settings refuse.
"""

from __future__ import annotations

import json
import os
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F
from tqdm import tqdm

SEED_OFFSET = 20000
CHUNK = 50  # rooms per worker job and per cache file


def photo_input(im: torch.Tensor, height: int) -> torch.Tensor:
    """(3, H, W) HDR -> (3, height, height * W / H) log radiance over the photo's mean: what a placement
    network reads (`bench.lamp_placement`)."""
    x = torch.log1p(im.clamp(min=0) / im.clamp(min=0).mean().clamp(min=1e-8))
    width = round(height * im.shape[-1] / im.shape[-2])
    return F.interpolate(x[None], size=(height, width), mode="area")[0]


def synth_config(profile: str):
    """`synthesize`'s SynthConfig on `profile` (each room drawn with the profile's views; its first is used)
    and the hash of that `synth` section (`bench.common.config_hash`)."""
    from omegaconf import OmegaConf

    from pipeline.bench.common import compose, config_hash
    from pipeline.data.synth.generate import SynthConfig

    synth = compose("synthesize", [f"profile={profile}"]).synth
    return SynthConfig.from_dict(OmegaConf.to_container(synth, resolve=True)), config_hash(synth)


def render_photos(indices: list[int], seed: int, cfg, variant: str, threads: int, height: int) -> list[dict]:
    """Rooms `indices` of `seed` (a worker job): per room its index, the photo as `lamp_placement`'s input
    (3, height, width) float16, the room's size and lamp shapes, and the camera's 4x4 world_from_view."""
    from pipeline.data.synth import mitsuba_backend as mb
    from pipeline.data.synth.generate import render_photo, scene_seed, usable_camera
    from pipeline.data.synth.scene import generate_room

    mb.init_mitsuba(variant, threads)
    out = []
    for index in indices:
        s_seed = scene_seed(seed, index)
        room, footprints, rng = generate_room(s_seed, cfg.views, cfg.room)  # the stage's draw; view 0 used
        scene = mb.load_scene(room, cfg.max_depth)
        camera, _ = usable_camera(scene, room, room.cameras[0], rng, cfg.room, footprints)
        im = render_photo(scene, camera, cfg, s_seed * 64)
        if not np.isfinite(im).all():
            raise ValueError(f"room {index} of seed {seed}: the rendered photo holds NaN or inf")
        shapes = [s for s in room.to_json()["shapes"] if s["role"] == "lamp"]
        out.append(
            {
                "index": index,
                "x": photo_input(torch.from_numpy(im).permute(2, 0, 1), height).half(),
                "room": {"size": list(room.size), "shapes": shapes},
                "world_from_view": mb.world_from_view(camera).tolist(),
            }
        )
    return out


def extra_rooms(
    cache: str | Path, rooms: int, seed: int = 0, profile: str = "tiny", height: int = 60, workers: int = 0
) -> list[dict]:
    """The first `rooms` extra rooms of `seed` (`render_photos`' records, by index), rendered into
    `cache` where missing. Refuses a cache made with other settings, naming the differing key."""
    if rooms < 0:
        raise ValueError(f"--curve: {rooms} extra rooms; the numbers must be >= 0")
    if rooms == 0:
        return []
    from pipeline.data.synth import mitsuba_backend as mb

    cfg, synth_hash = synth_config(profile)
    cache = Path(cache)
    cache.mkdir(parents=True, exist_ok=True)
    meta = {"seed": seed + SEED_OFFSET, "profile": profile, "height": height, "chunk": CHUNK, "synth_hash": synth_hash}
    meta_path = cache / "meta.json"
    if meta_path.exists():
        held = json.loads(meta_path.read_text())
        for key, value in meta.items():
            if held.get(key) != value:
                raise ValueError(
                    f"{meta_path}: made with {key}={held.get(key)!r}, this run needs {value!r}; "
                    "choose another --extra-dir"
                )
    else:
        meta_path.write_text(json.dumps(meta, indent=1))
    starts = range(0, rooms, CHUNK)
    missing = [s for s in starts if not (cache / f"chunk_{s:05d}.pt").exists()]
    if missing:
        variant = mb.choose_variant(cfg.variant)
        cores = os.cpu_count() or 1
        n_workers = max(1, min(workers or cores, len(missing)))
        threads = max(1, cores // n_workers)
        with ProcessPoolExecutor(n_workers, mp_context=get_context("spawn")) as pool:
            futures = {
                pool.submit(
                    render_photos, list(range(s, s + CHUNK)), seed + SEED_OFFSET, cfg, variant, threads, height
                ): s
                for s in missing
            }
            bar = tqdm(total=len(missing) * CHUNK, desc=f"extra rooms ({variant})", unit="room")
            for fut in futures:  # in order
                records = fut.result()
                path = cache / f"chunk_{futures[fut]:05d}.pt"
                torch.save(records, path.with_suffix(".tmp"))
                os.replace(path.with_suffix(".tmp"), path)  # a chunk on disk is whole, even if interrupted
                bar.update(len(records))
            bar.close()
    out = []
    for s in starts:
        path = cache / f"chunk_{s:05d}.pt"
        try:
            out.extend(torch.load(path, weights_only=False))
        except Exception as exc:  # a damaged file
            raise ValueError(f"{path}: unreadable ({exc}); delete it and run again") from exc
    return out[:rooms]
