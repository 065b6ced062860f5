"""Save and load trained models: the one I/O boundary for weights.

An export is a plain dict read with `torch.load(weights_only=True)`: a format tag, the network's
constructor arguments, its state dict and what inference needs besides weights. MaterialNet's export
also carries the training resolution `input_size` (h, w) and `depth_scale`, the factor that turns its
scale-free depth into metres (calibrated on validation views). An export that lacks a field is refused
with an error naming it: there is no silent default (a depth written at scale 1.0 and labelled
millimetres would be wrong by orders of magnitude). The loaders sit beside their networks
(`material_net.load_material_export`, `light_net.load_light_export`), so loading one network does not
import the other.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

MATERIAL_FORMAT = "invrender.material_net/1"
LIGHT_FORMAT = "invrender.light_net/1"
REQUIRED = {
    MATERIAL_FORMAT: ("model", "state_dict", "input_size", "depth_scale"),
    LIGHT_FORMAT: ("light_net", "state_dict"),
}


class ExportError(Exception):
    """A missing, unreadable or incompatible model export; the message names the file (and field)."""


def _save(path: str | Path, fmt: str, net: nn.Module, **fields) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    blob = {"format": fmt, **fields, "state_dict": {k: v.detach().cpu() for k, v in net.state_dict().items()}}
    missing = [k for k in REQUIRED[fmt] if blob.get(k) is None]
    if missing:
        raise ExportError(f"{path}: refusing to write a {fmt} export without {missing}")
    torch.save(blob, path)
    return path


def save_material_export(path, model: dict, net: nn.Module, input_size, depth_scale: float, **extra) -> Path:
    """MaterialNet export: model kwargs, weights, training resolution (h, w), depth scale (m per unit)."""
    return _save(
        path,
        MATERIAL_FORMAT,
        net,
        model=dict(model),
        input_size=[int(input_size[0]), int(input_size[1])],
        depth_scale=float(depth_scale),
        **extra,
    )


def save_light_export(path, light_net: dict, net: nn.Module) -> Path:
    """LightNet export: LightNet kwargs and weights."""
    return _save(path, LIGHT_FORMAT, net, light_net=dict(light_net))


def read_export(path: str | Path, fmt: str) -> dict:
    """The export at `path` as a dict, checked to be `fmt` with every required field."""
    path = Path(path)
    if not path.is_file():
        raise ExportError(f"{path}: no such model export (train it with `dvc repro` or pass another path)")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # pickle/zip errors differ by cause; all mean "not a weights-only export"
        raise ExportError(f"{path}: not a weights-only torch file ({type(exc).__name__}: {exc})") from exc
    if not isinstance(blob, dict) or blob.get("format") != fmt:
        found = blob.get("format") if isinstance(blob, dict) else type(blob).__name__
        hint = (
            " (a Lightning .ckpt holds no depth scale or resolution: use the stage's model.pt)"
            if (isinstance(blob, dict) and "hyper_parameters" in blob)
            else ""
        )
        raise ExportError(f"{path}: not a {fmt!r} export (format {found!r}){hint}")
    missing = [k for k in REQUIRED[fmt] if blob.get(k) is None]
    if missing:
        raise ExportError(f"{path}: export lacks {', '.join(missing)}")
    return blob


def build_from_export(path, cls, kwargs: dict, state: dict) -> nn.Module:
    """cls(**kwargs) with `state` loaded, in eval mode; a mismatch is refused naming the file."""
    try:
        net = cls(**kwargs)
        net.load_state_dict(state)
    except (TypeError, ValueError, RuntimeError, KeyError) as exc:
        raise ExportError(f"{path}: incompatible with {cls.__name__} ({exc})") from exc
    return net.eval()
