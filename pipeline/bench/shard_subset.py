"""`python -m pipeline.bench.shard_subset SRC DST --views train=32 val=8 test=8`: the first views of each
split of `preprocess`'s shards at SRC, written as one compressed shard per split with its own manifest
at DST: a small copy of the data that a bench can carry to another machine (the device benches).

Every array a view owns is copied (its maps and its lighting probes, whose per-view offsets are rebuilt),
and the manifest keeps the source's keys, with the views, scenes and checksums of the subset. A split
asked for more views than it has, or a split the source lacks, is an error naming it.
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path

import numpy as np

from pipeline.data.datasets import read_manifest


def _view_arrays(z, count: int) -> list[dict[str, np.ndarray]]:
    """Per view of an open shard: {key: its rows} for every key (probe arrays cut by their offsets). Each
    array is read once: an npz file decompresses a key again on every access."""
    arrays = {key: z[key] for key in z.files}
    views = []
    for v in range(count):
        d = {}
        for key, array in arrays.items():
            if key.endswith("_offsets"):
                continue
            prefix = next((p for p in ("light_surf_", "light_free_") if key.startswith(p)), None)
            if prefix is None:
                d[key] = array[v]
            else:
                off = arrays[f"{prefix}offsets"]
                d[key] = array[off[v] : off[v + 1]]
        views.append(d)
    return views


def write_subset(src: str | Path, dst: str | Path, counts: dict[str, int]) -> Path:
    """The first `counts[split]` views of each split of SRC's shards, written under DST; DST's manifest."""
    src, dst = Path(src), Path(dst)
    manifest = read_manifest(src)
    dst.mkdir(parents=True, exist_ok=True)
    splits = {}
    for split, want in counts.items():
        if split not in manifest["splits"]:
            raise ValueError(f"{src / 'manifest.json'}: has no split {split!r}")
        entry = manifest["splits"][split]
        if want < 1 or want > len(entry["views"]):
            raise ValueError(f"--views {split}={want}: the split has {len(entry['views'])} views")
        views: list[dict] = []
        for shard in entry["shards"]:
            with np.load(src / shard["file"]) as z:
                views.extend(_view_arrays(z, shard["count"]))
            if len(views) >= want:
                break
        views = views[:want]
        arrays = {}
        for key in views[0]:
            if key.startswith(("light_surf_", "light_free_")):
                arrays[key] = np.concatenate([v[key] for v in views])
            else:
                arrays[key] = np.stack([v[key] for v in views])
        for prefix in ("light_surf_", "light_free_"):
            sizes = [len(v[f"{prefix}position"]) for v in views if f"{prefix}position" in v]
            if sizes:
                arrays[f"{prefix}offsets"] = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        name = f"{split}_000.npz"
        np.savez_compressed(dst / name, **arrays)
        ids = entry["views"][:want]
        splits[split] = {
            "views": ids,
            "shards": [
                {
                    "file": name,
                    "count": want,
                    "sha256": hashlib.sha256((dst / name).read_bytes()).hexdigest(),
                    "lighting": bool(entry["shards"][0]["lighting"]),
                }
            ],
            "scenes": sorted({i.split("/")[0] for i in ids}),
        }
    out = {**manifest, "splits": splits, "subset_of": str(src.resolve())}
    (dst / "manifest.json").write_text(json.dumps(out, indent=1) + "\n")
    return dst / "manifest.json"


def parse_counts(items: list[str]) -> dict[str, int]:
    counts = {}
    for item in items:
        split, sep, n = item.partition("=")
        if not sep or not n.isdigit():
            raise ValueError(f"--views {item!r}: write SPLIT=COUNT, e.g. train=32")
        counts[split] = int(n)
    return counts


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("src")
    p.add_argument("dst")
    p.add_argument("--views", nargs="+", default=["train=32", "val=8", "test=8"], help="SPLIT=COUNT per split")
    a = p.parse_args(argv)
    print(write_subset(a.src, a.dst, parse_counts(a.views)))


if __name__ == "__main__":
    main()
