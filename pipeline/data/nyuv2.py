"""NYU Depth v2 (labeled set) in its published formats.

- `nyu_depth_v2_labeled.mat`: MATLAB v7.3 = HDF5 (read with h5py). h5py shows MATLAB's axes reversed:
  `images` (N, 3, W, H) uint8 and `depths` (N, W, H) float metres; we return (N, H, W, 3) and (N, H, W).
- `splits.mat` (MATLAB v5, scipy): `trainNdxs`, `testNdxs`, 1-based image numbers; we return 0-based.
- ground-truth normals: `<normals_dir>/%04d.png` (8-bit, n = v / 127.5 - 1, renormalised) and
  `<masks_dir>/%04d.png` (valid where all channels are 255), numbered by 0-based image index.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


class NYUError(ValueError):
    """A missing or malformed NYUv2 file; the message names it and the key."""


def read_labeled(path: str | Path, indices=None) -> tuple[np.ndarray, np.ndarray]:
    """images (K, H, W, 3) uint8 and depths (K, H, W) float32 metres for `indices` (0-based; all if None)."""
    import h5py

    path = Path(path)
    if not path.is_file():
        raise NYUError(f"{path}: no such file")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise NYUError(f"{path}: not an HDF5 (MATLAB v7.3) file ({exc})") from exc
    with f:
        try:
            im, dp = _read_datasets(f, path, indices)
        except NYUError:
            raise
        except Exception as exc:  # h5py raises OSError, KeyError, RuntimeError... on damaged structure
            raise NYUError(f"{path}: cannot read 'images'/'depths' ({type(exc).__name__}: {exc})") from exc
    im = np.ascontiguousarray(np.transpose(im, (0, 3, 2, 1)))  # (N, 3, W, H) -> (N, H, W, 3)
    dp = np.ascontiguousarray(np.transpose(dp, (0, 2, 1)).astype(np.float32))
    if im.dtype != np.uint8:
        raise NYUError(f"{path}: 'images' has dtype {im.dtype}, expected uint8")
    if not np.isfinite(dp).all():
        raise NYUError(f"{path}: 'depths' contains NaN or inf")
    return im, dp


def _read_datasets(f, path: Path, indices) -> tuple[np.ndarray, np.ndarray]:
    """The raw (K, 3, W, H) images and (K, W, H) depths of `indices` from the open HDF5 file `f`."""
    import h5py

    for key in ("images", "depths"):
        if not isinstance(f.get(key), h5py.Dataset):
            raise NYUError(f"{path}: missing dataset {key!r}")
    images, depths = f["images"], f["depths"]
    if images.ndim != 4 or images.shape[1] != 3:
        raise NYUError(f"{path}: 'images' has shape {images.shape}, expected (N, 3, W, H)")
    if depths.ndim != 3 or depths.shape[0] != images.shape[0] or depths.shape[1:] != images.shape[2:]:
        raise NYUError(
            f"{path}: 'depths' has shape {depths.shape}, expected (N, W, H) = {(images.shape[0],) + images.shape[2:]}"
        )
    n = images.shape[0]
    idx = np.arange(n) if indices is None else np.asarray(indices, np.int64)
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise NYUError(f"{path}: image index out of range 0..{n - 1}")
    uniq = np.unique(idx)  # h5py reads strictly increasing indices; map back to the caller's order
    im = images[list(uniq)][np.searchsorted(uniq, idx)] if idx.size else np.zeros((0, *images.shape[1:]), np.uint8)
    dp = depths[list(uniq)][np.searchsorted(uniq, idx)] if idx.size else np.zeros((0, *depths.shape[1:]), np.float32)
    return im, dp


def count_images(path: str | Path) -> int:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return int(f["images"].shape[0])
    except Exception as exc:  # not HDF5, no 'images', a group where a dataset belongs, damaged metadata
        raise NYUError(f"{path}: cannot read 'images' ({type(exc).__name__}: {exc})") from exc


def read_splits(path: str | Path, n_images: int) -> dict[str, np.ndarray]:
    """{"train", "test"}: 0-based image indices from the 1-based `trainNdxs` / `testNdxs`."""
    from scipy.io import loadmat

    path = Path(path)
    if not path.is_file():
        raise NYUError(f"{path}: no such file")
    try:
        mat = loadmat(path)
    except Exception as exc:  # scipy raises MatReadError, ValueError, NotImplementedError... by damage
        raise NYUError(f"{path}: not a MATLAB file ({type(exc).__name__}: {exc})") from exc
    out = {}
    for split, key in (("train", "trainNdxs"), ("test", "testNdxs")):
        if key not in mat:
            raise NYUError(f"{path}: missing {key!r}")
        try:
            values = np.asarray(mat[key], dtype=np.float64).ravel()
        except (TypeError, ValueError) as exc:
            raise NYUError(f"{path}: {key!r} is not numeric ({exc})") from exc
        if not np.isfinite(values).all() or (values != np.round(values)).any():
            raise NYUError(f"{path}: {key!r} holds values that are not whole image numbers")
        one_based = values.astype(np.int64)
        if one_based.size == 0:
            raise NYUError(f"{path}: {key!r} is empty")
        if one_based.min() < 1 or one_based.max() > n_images:
            raise NYUError(f"{path}: {key!r} has indices outside 1..{n_images} (it is 1-based)")
        out[split] = one_based - 1
    if np.intersect1d(out["train"], out["test"]).size:
        raise NYUError(f"{path}: trainNdxs and testNdxs overlap")
    return out


def read_normal(normals_dir: str | Path, masks_dir: str | Path, index: int, shape: tuple[int, int]):
    """Ground-truth normal (H, W, 3) unit vectors and valid mask (H, W) bool of image `index` (0-based)."""
    from PIL import Image

    npath, mpath = Path(normals_dir) / f"{index:04d}.png", Path(masks_dir) / f"{index:04d}.png"
    arrays = []
    for p in (npath, mpath):
        try:
            with Image.open(p) as img:
                arrays.append(np.asarray(img.convert("RGB")))
        except (FileNotFoundError, OSError) as exc:
            raise NYUError(f"{p}: cannot read ({exc})") from exc
    v, m = arrays
    for p, a in ((npath, v), (mpath, m)):
        if a.shape[:2] != tuple(shape):
            raise NYUError(f"{p}: size {a.shape[:2]} differs from the image's {tuple(shape)}")
    n = v.astype(np.float64) / 127.5 - 1.0
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    return n.astype(np.float32), (m == 255).all(-1)


def write_normal_png(path: str | Path, normal: np.ndarray) -> None:
    """Encode unit normals (H, W, 3) as the 8-bit PNG the reader expects."""
    from PIL import Image

    v = np.clip(np.round((np.asarray(normal, np.float64) + 1.0) * 127.5), 0, 255).astype(np.uint8)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(v).save(path)
