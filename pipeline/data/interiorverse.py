"""The InteriorVerse on-disk layout, read and written identically for generated and real data.

    <root>/<scene>/<view>_{im,albedo,normal,depth,material,mask}.exr     one view = six maps
    <root>/{train,val,test}.txt                                         scene names, one per line

Maps (H, W, C): im HDR linear RGB radiance; albedo linear RGB base colour; normal unit view-space (OpenGL);
depth z-depth in millimetres, inf where invalid; material R = GGX roughness, G = metallic; mask 1 = valid.
Our extensions (docs/data.md): `<scene>/cameras.json` (intrinsics + pose per view) and
`<scene>/<view>_light.npz` (lighting ground truth).
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.data.formats.exr import ExrError, read_exr, write_exr

MAPS = ("im", "albedo", "normal", "depth", "material", "mask")
SPLITS = ("train", "val", "test")
CHANNELS = {"im": 3, "albedo": 3, "normal": 3, "depth": 1, "material": 2, "mask": 1}
LIGHT_KEYS = {
    "surf_pixel": 2,
    "surf_position": 2,
    "surf_normal": 2,
    "surf_directions": 4,
    "surf_radiance": 4,
    "surf_stderr": 4,
    "free_position": 2,
    "free_directions": 4,
    "free_radiance": 4,
    "free_stderr": 4,
}


class DatasetError(ValueError):
    """The dataset root or one of its files is unusable; the message names the file or key."""


def map_path(root: Path, scene: str, view: str, name: str) -> Path:
    return Path(root) / scene / f"{view}_{name}.exr"


def light_path(root: Path, scene: str, view: str) -> Path:
    return Path(root) / scene / f"{view}_light.npz"


# ----------------------------------------------------------------------------------------------------
# Splits and listing


def read_split(root: str | Path, split: str, allow_empty: bool = False) -> list[str]:
    """Scene names of one split file. Missing files are errors naming the file, and so are empty ones
    unless `allow_empty` (a split a test-only set leaves empty)."""
    path = Path(root) / f"{split}.txt"
    if not path.is_file():
        raise DatasetError(f"{path}: split file not found (expected train.txt, val.txt, test.txt in {root})")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{path}: split file is not UTF-8 text ({exc.reason} at byte {exc.start})") from exc
    scenes = [line.strip() for line in text.splitlines() if line.strip() and not line.startswith("#")]
    if not scenes and not allow_empty:
        raise DatasetError(f"{path}: split file lists no scenes")
    if len(set(scenes)) != len(scenes):
        raise DatasetError(f"{path}: split file lists a scene twice")
    return scenes


def read_splits(root: str | Path, optional: tuple[str, ...] = ()) -> dict[str, list[str]]:
    """All three splits (those in `optional` may be empty); a scene listed in two splits is an error (it
    would leak test data)."""
    splits = {s: read_split(root, s, allow_empty=s in optional) for s in SPLITS}
    seen: dict[str, str] = {}
    for split, scenes in splits.items():
        for scene in scenes:
            if scene in seen:
                first, second = (Path(root) / f"{name}.txt" for name in (seen[scene], split))
                raise DatasetError(f"{first}, {second}: both list scene {scene!r} (a scene belongs to one split)")
            seen[scene] = split
    return splits


def write_splits(root: str | Path, splits: dict[str, list[str]]) -> None:
    for split in SPLITS:
        (Path(root) / f"{split}.txt").write_text("".join(f"{s}\n" for s in splits.get(split, [])))


def list_views(root: str | Path, scene: str) -> list[str]:
    """View ids of a scene: every prefix that has at least one `<view>_<map>.exr` file (sorted)."""
    folder = Path(root) / scene
    if not folder.is_dir():
        raise DatasetError(f"{folder}: scene folder listed in a split file does not exist")
    views = set()
    for p in folder.glob("*_*.exr"):
        view, _, name = p.stem.rpartition("_")
        if name in MAPS:
            views.add(view)
    return sorted(views)


def split_views(root: str | Path, splits: dict[str, list[str]]) -> list[tuple[str, str, str]]:
    """Every (split, scene, view) of the listed scenes, in split-file order. A listed scene without a
    folder is an error naming the split file that lists it."""
    for split, scenes in splits.items():
        for scene in scenes:
            if not (Path(root) / scene).is_dir():
                raise DatasetError(
                    f"{Path(root) / (split + '.txt')}: lists scene {scene!r}, which has no folder in {root}"
                )
    return [
        (split, scene, view) for split, scenes in splits.items() for scene in scenes for view in list_views(root, scene)
    ]


def read_cameras(root: str | Path, scene: str) -> dict | None:
    path = Path(root) / scene / "cameras.json"
    if not path.is_file():
        return None
    try:
        cameras = json.loads(path.read_bytes().decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(cameras, dict) or not all(isinstance(v, dict) for v in cameras.values()):
        raise DatasetError(f"{path}: expected an object of views, each an object with fov_x_deg")
    return cameras


# ----------------------------------------------------------------------------------------------------
# Writing


def write_view(root: str | Path, scene: str, view: str, maps: dict[str, np.ndarray], half: bool = False) -> None:
    """Write the six maps of one view. `maps` holds im/albedo/normal (H,W,3), depth (H,W) in mm (inf
    invalid), material (H,W,2|3) (roughness, metallic), mask (H,W) in {0,1}."""
    for name in MAPS:
        arr = np.asarray(maps[name], np.float32)
        if name == "material" and arr.shape[-1] == 2:
            arr = np.concatenate([arr, np.zeros_like(arr[..., :1])], -1)  # B unused, as InteriorVerse
        # depth keeps full precision: float16 overflows above 65.5 m and loses mm resolution
        write_exr(map_path(root, scene, view, name), arr, half=half and name not in ("depth",))


def write_light(root: str | Path, scene: str, view: str, light: dict[str, np.ndarray]) -> None:
    np.savez(light_path(root, scene, view), **{k: np.asarray(v) for k, v in light.items()})


# ----------------------------------------------------------------------------------------------------
# Reading and validation


@dataclass
class ViewCheck:
    """Result of validating one view: maps (H, W, C) float32 when usable, else the reasons it is not."""

    scene: str
    view: str
    maps: dict[str, np.ndarray] | None = None
    light: dict[str, np.ndarray] | None = None
    reasons: list[dict] = field(default_factory=list)  # [{"file": ..., "reason": ...}]
    fixed_pixels: int = 0  # valid-mask pixels whose maps disagreed with the mask and were masked out

    @property
    def ok(self) -> bool:
        return not self.reasons

    def rejections(self, split: str) -> list[dict]:
        """One record per reason: split, scene, view, file and reason (the `rejected.json` rows)."""
        return [{"split": split, "scene": self.scene, "view": self.view, **r} for r in self.reasons]


def _take_channels(arr: np.ndarray, name: str, path: Path) -> np.ndarray:
    """Select the channels a map needs; depth/mask stored as 3 identical channels are accepted."""
    want, have = CHANNELS[name], arr.shape[-1]
    if name in ("depth", "mask") and have in (3, 4):
        if not np.array_equal(arr[..., 0], arr[..., 1], equal_nan=True):
            raise DatasetError(f"{path}: {name} has {have} channels that differ (expected 1)")
        return arr[..., :1]
    if name == "material" and have >= 2:
        return arr[..., :2]
    if have == want or (want == 3 and have == 4):
        return arr[..., :want]
    raise DatasetError(f"{path}: {name} map has {have} channel(s), expected {want}")


def read_view(root: str | Path, scene: str, view: str, max_inconsistent_fraction: float = 0.01) -> ViewCheck:
    """Read and validate one view (never raises for a bad view: it comes back with reasons).

    Checks: all six files exist and decode, equal H x W, channel counts, finite and non-negative
    radiance, mask in {0, 1}, and within the mask: finite positive depth, unit normals, albedo and
    material in [0, 1]. Valid pixels that break the within-mask rules are masked out and counted when
    they are at most `max_inconsistent_fraction` of the mask; beyond that the view is rejected.
    """
    check = ViewCheck(scene, view)
    maps: dict[str, np.ndarray] = {}
    for name in MAPS:
        path = map_path(root, scene, view, name)
        try:
            maps[name] = _take_channels(read_exr(path), name, path)
        except (ExrError, DatasetError) as exc:
            check.reasons.append({"file": str(path), "reason": str(exc).removeprefix(f"{path}: ")})
    if check.reasons:
        return check
    shapes = {name: m.shape[:2] for name, m in maps.items()}
    if len(set(shapes.values())) != 1:
        check.reasons.append({"file": str(map_path(root, scene, view, "im")), "reason": f"map sizes differ: {shapes}"})
        return check

    def reject(name: str, reason: str, path: Path | None = None) -> ViewCheck:
        check.reasons.append({"file": str(path or map_path(root, scene, view, name)), "reason": reason})
        return check

    im, mask = maps["im"], maps["mask"][..., 0]
    if not np.isfinite(im).all():
        return reject("im", f"{int((~np.isfinite(im)).any(-1).sum())} pixels are NaN/inf")
    if (im < 0).any():
        return reject("im", f"{int((im < 0).any(-1).sum())} pixels have negative radiance")
    if not np.isin(mask, (0.0, 1.0)).all():
        return reject("mask", "values other than 0 and 1")
    valid = mask > 0.5
    if not valid.any():
        return reject("mask", "no valid pixels")

    depth = maps["depth"][..., 0]
    norm = np.linalg.norm(maps["normal"], axis=-1)
    with np.errstate(invalid="ignore"):
        bad = (
            ~np.isfinite(depth)
            | (depth <= 0)
            | ~np.isfinite(norm)
            | (np.abs(norm - 1) > 0.05)
            | ~np.isfinite(maps["albedo"]).all(-1)
            | (maps["albedo"] < 0).any(-1)
            | (maps["albedo"] > 1.001).any(-1)
            | ~np.isfinite(maps["material"]).all(-1)
            | (maps["material"] < 0).any(-1)
            | (maps["material"] > 1.001).any(-1)
        ) & valid
    n_bad = int(bad.sum())
    if n_bad > max_inconsistent_fraction * valid.sum():
        return reject("mask", f"{n_bad} of {int(valid.sum())} valid pixels have invalid depth/normal/albedo/material")
    if n_bad:
        maps["mask"] = (valid & ~bad).astype(np.float32)[..., None]
        check.fixed_pixels = n_bad
    lp = light_path(root, scene, view)
    if lp.is_file():
        try:
            check.light = read_light(lp)
        except DatasetError as exc:
            return reject("light", str(exc).removeprefix(f"{lp}: "), path=lp)
    check.maps = maps
    return check


def read_light(path: str | Path) -> dict[str, np.ndarray]:
    """Load and check a lighting ground-truth file (keys, ranks, matching counts, finite values)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            light = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise DatasetError(f"{path}: cannot read lighting file ({exc})") from exc
    for key, ndim in LIGHT_KEYS.items():
        if key not in light:
            raise DatasetError(f"{path}: lighting file lacks key {key!r}")
        if light[key].ndim != ndim:
            raise DatasetError(f"{path}: {key} has {light[key].ndim} dims, expected {ndim}")
    for prefix in ("surf", "free"):
        n = len(light[f"{prefix}_position"])
        for key in LIGHT_KEYS:
            if key.startswith(prefix) and len(light[key]) != n:
                raise DatasetError(f"{path}: {key} has {len(light[key])} entries, {prefix}_position has {n}")
        if not np.isfinite(light[f"{prefix}_radiance"]).all() or (light[f"{prefix}_radiance"] < 0).any():
            raise DatasetError(f"{path}: {prefix}_radiance has NaN/inf or negative values")
    return light
