"""Insertion and editing cases of a view (`<view>_cases.json` + `<view>_cases.npz`), typed and checked.

Written by `synthesize` (`pipeline.data.synth.cases`) for val and test views; read by the `edit` stage
and the tests. Pixels are flat indices into the view's (H, W) grid (row-major); positions and normals
are in the view space of docs/design.md, section 3; depth is z-depth in metres; radiance is HDR, the mean of
`spp` path samples through the pixel centre, with its standard error.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.data import interiorverse as iv
from pipeline.data.interiorverse import DatasetError

# array -> channels (None: one value per pixel)
OBJECT_ARRAYS = {"pixel": None, "albedo": 3, "normal": 3, "depth_m": None, "material": 2, "radiance": 3, "stderr": 3}
# the object's surroundings (`synth.cases.surrounding_pixels`): their own length, possibly 0
RING_ARRAYS = {"ring_pixel": None, "ring_delta": 3, "ring_stderr": 3}
EDIT_ARRAYS = {"pixel": None, "albedo": 3, "material": 2, "radiance": 3, "stderr": 3}
OBJECT_FIELDS = ("kind", "spheres", "material_class", "albedo", "roughness", "metallic", "support", "anchor_pixel")
EDIT_FIELDS = ("kind", "target", "material_index", "albedo", "roughness", "metallic")


@dataclass
class Case:
    """One insertion or edit. description: its JSON entry; pixel (M,) long flat indices; albedo (M, 3),
    material (M, 2) roughness+metallic; normal (M, 3) and depth (M,) metres for objects (None for edits,
    which keep the view's geometry); radiance, stderr (M, 3) the Mitsuba ground truth. Objects also carry
    their surroundings: ring_pixel (K,) long, the room's pixels near the object, and ring_delta,
    ring_stderr (K, 3), the change the object makes there in Mitsuba's render (with it minus without it:
    its shadow and bounce light) and that change's standard error; None for edits."""

    kind: str  # object | edit
    index: int
    description: dict
    pixel: torch.Tensor
    albedo: torch.Tensor
    material: torch.Tensor
    radiance: torch.Tensor
    stderr: torch.Tensor
    normal: torch.Tensor | None = None
    depth: torch.Tensor | None = None
    ring_pixel: torch.Tensor | None = None
    ring_delta: torch.Tensor | None = None
    ring_stderr: torch.Tensor | None = None

    @property
    def label(self) -> str:
        """The class it is scored in: the object's material class, or the edit's kind."""
        d = self.description
        return d["material_class"] if self.kind == "object" else d["kind"]

    @property
    def name(self) -> str:
        return f"{self.kind}{self.index}"


def paths(root: str | Path, scene: str, view: str) -> tuple[Path, Path]:
    base = Path(root) / scene
    return base / f"{view}_cases.json", base / f"{view}_cases.npz"


def write_cases(root: str | Path, scene: str, view: str, description: dict, arrays: dict[str, np.ndarray]) -> None:
    """The arrays first, the description last: a view has cases once its JSON exists."""
    js, npz = paths(root, scene, view)
    np.savez_compressed(npz, **{k: np.ascontiguousarray(v) for k, v in arrays.items()})
    js.write_text(json.dumps(description, indent=1))


def has_cases(root: str | Path, scene: str, view: str) -> bool:
    """Either file marks a view with cases (`read_cases` then refuses a missing partner, naming it)."""
    return any(p.is_file() for p in paths(root, scene, view))


def case_views(root: str | Path, split: str) -> list[tuple[str, str]]:
    """(scene, view) of every view of `split` that has cases, in split-file and view order; refused,
    naming the root, when none has."""
    views = [(s, v) for s in iv.read_split(root, split) for v in iv.list_views(root, s)]
    views = [sv for sv in views if has_cases(root, *sv)]
    if not views:
        raise DatasetError(f"{root}: no {split} view has insertion/editing cases (synth.cases.enabled)")
    return views


def read_case_view(root: str | Path, scene: str, view: str, split: str) -> tuple[dict, list[Case], dict]:
    """One view of `split` with cases, read and checked (`interiorverse.read_view`; refused with its
    rejections), its cases and its camera (`cameras.json`): (maps, cases, camera)."""
    check = iv.read_view(root, scene, view)
    if check.maps is None:
        raise DatasetError(f"{root}/{scene}/{view}: {check.rejections(split)}")
    H, W = check.maps["im"].shape[:2]
    cases = read_cases(root, scene, view, H, W)
    camera = (iv.read_cameras(root, scene) or {}).get(view)
    if camera is None:
        raise DatasetError(f"{root}/{scene}/cameras.json: no camera for view {view}")
    return check.maps, cases, camera


def read_cases(root: str | Path, scene: str, view: str, height: int, width: int) -> list[Case]:
    """Every case of a view, checked: both files present and readable, every array of every listed case
    present with matching lengths and finite values, pixels inside the (height, width) view."""
    js, npz = paths(root, scene, view)
    for p in (js, npz):
        if not p.is_file():
            raise DatasetError(f"{p}: missing (run synthesize with synth.cases.enabled=true)")
    try:
        desc = json.loads(js.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{js}: not valid JSON ({exc})") from exc
    if not isinstance(desc, dict):
        raise DatasetError(f"{js}: expected a JSON object with `objects` and `edits`")
    for key, fields in (("objects", OBJECT_FIELDS), ("edits", EDIT_FIELDS)):
        entries = desc.get(key, [])
        if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
            raise DatasetError(f"{js}: `{key}` must be a list of objects")
        for i, e in enumerate(entries):
            missing = [f for f in fields if f not in e]
            if missing:
                raise DatasetError(f"{js}: {key}[{i}] lacks {missing}")
            if key == "objects" and e.get("mesh") is not None:
                _check_mesh(e["mesh"], f"{js}: objects[{i}].mesh")
    try:
        with np.load(npz, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise DatasetError(f"{npz}: cannot read case arrays ({exc})") from exc
    size = arrays.get("size")
    if size is None or tuple(int(s) for s in size) != (height, width):
        raise DatasetError(
            f"{npz}: cases were rendered at {None if size is None else tuple(size)}, view is {(height, width)}"
        )
    out = []
    for kind, entries, spec in (
        ("object", desc.get("objects", []), OBJECT_ARRAYS),
        ("edit", desc.get("edits", []), EDIT_ARRAYS),
    ):
        for i, entry in enumerate(entries):
            a = {}
            for key, channels in spec.items():
                full = f"{kind}{i}_{key}"
                if full not in arrays or f"{kind}{i}_pixel" not in arrays:
                    raise DatasetError(f"{npz}: lacks {full!r} for {kind} {i} of {js.name}")
                a[key] = arrays[full]
                want = (len(arrays[f"{kind}{i}_pixel"]),) + (() if channels is None else (channels,))
                if a[key].shape != want:
                    raise DatasetError(f"{npz}: {full} has shape {a[key].shape}, expected {want}")
                if not np.isfinite(a[key]).all():
                    raise DatasetError(f"{npz}: {full} has NaN/inf values")
            pix = a["pixel"].astype(np.int64)
            if not len(pix) or pix.min() < 0 or pix.max() >= height * width:
                raise DatasetError(f"{npz}: {kind}{i}_pixel is empty or outside the {height}x{width} view")
            t = {k: torch.from_numpy(np.asarray(v, np.float32)) for k, v in a.items() if k != "pixel"}
            ring = _ring_arrays(arrays, f"{kind}{i}", npz, js, height, width) if kind == "object" else {}
            out.append(
                Case(
                    kind,
                    i,
                    entry,
                    torch.from_numpy(pix),
                    t["albedo"],
                    t["material"],
                    t["radiance"],
                    t["stderr"],
                    t.get("normal"),
                    t.get("depth_m"),
                    **ring,
                )
            )
    return out


def _check_mesh(mesh, where: str) -> None:
    """A case object's triangles: {"vertices": (V, 3) finite metres, "faces": (F >= 1, 3) indices into
    them}; refused naming `where` otherwise."""
    try:
        vertices = np.asarray(mesh["vertices"], np.float64)
        faces = np.asarray(mesh["faces"])
    except (TypeError, KeyError, ValueError) as exc:
        raise DatasetError(f"{where}: expected vertices (V, 3) and faces (F, 3) ({exc!r})") from exc
    if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.isfinite(vertices).all():
        raise DatasetError(f"{where}: vertices must be finite (V, 3), got shape {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or not len(faces) or faces.dtype.kind not in "iu":
        raise DatasetError(f"{where}: faces must be (F >= 1, 3) integers, got {faces.dtype} {faces.shape}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise DatasetError(f"{where}: faces index outside the {len(vertices)} vertices")


def _ring_arrays(arrays: dict, name: str, npz: Path, js: Path, height: int, width: int) -> dict:
    """An object's surroundings (`RING_ARRAYS`), checked: present, one length, finite, pixels inside the
    view (an empty ring is valid: an object far from every surface)."""
    out = {}
    for key, channels in RING_ARRAYS.items():
        full = f"{name}_{key}"
        if full not in arrays:
            raise DatasetError(f"{npz}: lacks {full!r} for {name} of {js.name} (re-run synthesize)")
        value = arrays[full]
        want = (len(arrays[f"{name}_ring_pixel"]),) + (() if channels is None else (channels,))
        if value.shape != want:
            raise DatasetError(f"{npz}: {full} has shape {value.shape}, expected {want}")
        if not np.isfinite(value).all():
            raise DatasetError(f"{npz}: {full} has NaN/inf values")
        out[key] = value
    pix = out["ring_pixel"].astype(np.int64)
    if len(pix) and (pix.min() < 0 or pix.max() >= height * width):
        raise DatasetError(f"{npz}: {name}_ring_pixel is outside the {height}x{width} view")
    return {
        "ring_pixel": torch.from_numpy(pix),
        "ring_delta": torch.from_numpy(out["ring_delta"].astype(np.float32)),
        "ring_stderr": torch.from_numpy(out["ring_stderr"].astype(np.float32)),
    }
