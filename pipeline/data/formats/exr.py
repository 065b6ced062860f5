"""OpenEXR I/O for (H, W) and (H, W, C) float maps.

OpenEXR silently writes garbage for non-contiguous arrays and refuses float64, so every write goes
through `np.ascontiguousarray(..., float32|float16)`. Reads return float32 (H, W, C) arrays.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR

_CHANNEL_SETS = {1: ("Y",), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}


class ExrError(ValueError):
    """An EXR file is missing, unreadable or has the wrong layout; the message names the file."""


def write_exr(path: str | Path, image: np.ndarray, half: bool = False) -> None:
    """Write `image` (H, W) or (H, W, C) with C in {1, 3, 4} as a scanline EXR (ZIP compressed).

    Values are written as they are (HDR, inf allowed); `half` stores float16.
    """
    arr = np.asarray(image)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[2] not in _CHANNEL_SETS:
        raise ExrError(f"{path}: cannot write array of shape {np.shape(image)} (want HxW or HxWx{{1,3,4}})")
    dtype = np.float16 if half else np.float32
    names = _CHANNEL_SETS[arr.shape[2]]
    channels = {name: np.ascontiguousarray(arr[..., i], dtype=dtype) for i, name in enumerate(names)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))


def read_exr(path: str | Path) -> np.ndarray:
    """Read an EXR into a float32 (H, W, C) array (C = 1 for a single channel, RGB(A) order otherwise).

    Raises ExrError naming the file when it is missing, truncated or not an EXR.
    """
    path = Path(path)
    if not path.is_file():
        raise ExrError(f"{path}: file not found")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            chans = {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}
    except Exception as exc:  # OpenEXR raises bare RuntimeError/OSError on corrupt data
        raise ExrError(f"{path}: cannot decode EXR ({exc})") from exc
    if not chans:
        raise ExrError(f"{path}: EXR has no channels")
    order = _channel_order(list(chans))
    planes = [chans[name] for name in order]
    shapes = {p.shape for p in planes}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ExrError(f"{path}: channels have inconsistent shapes {sorted(shapes)}")
    return np.stack(planes, axis=-1).astype(np.float32, copy=False)


def _channel_order(names: list[str]) -> list[str]:
    """RGB(A) first in that order, then any other channels alphabetically (a lone channel as is)."""
    rank = {"R": 0, "G": 1, "B": 2, "A": 3}
    return sorted(names, key=lambda n: (rank.get(n, 4), n))
