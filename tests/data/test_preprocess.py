"""Preprocess: mask-aware resizing, shards + manifest, and bad input rejected with file and reason."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from pipeline.data import interiorverse as iv
from pipeline.data.datasets import ShardDataset, collate_views
from pipeline.data.formats.exr import write_exr
from pipeline.data.preprocess import preprocess, resize_view


def _maps(h=4, w=4):
    rng = np.random.default_rng(0)
    n = rng.normal(size=(h, w, 3))
    return {
        "im": rng.random((h, w, 3)).astype(np.float32) * 10,
        "albedo": rng.random((h, w, 3)).astype(np.float32),
        "normal": (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32),
        "depth": rng.uniform(1000, 5000, (h, w, 1)).astype(np.float32),
        "material": rng.random((h, w, 2)).astype(np.float32),
        "mask": np.ones((h, w, 1), np.float32),
    }


def test_resize_averages_valid_blocks_and_drops_mixed_ones():
    m = _maps()
    m["mask"][0, 0] = 0
    m["depth"][0, 0] = np.inf
    out = resize_view(m, 2, 2)
    assert out["mask"].tolist() == [[[0, 1], [1, 1]]]
    np.testing.assert_allclose(out["im"][:, 0, 0], m["im"][:2, :2].reshape(-1, 3).mean(0), rtol=1e-6)  # HDR: all pixels
    np.testing.assert_allclose(out["albedo"][:, 1, 1], m["albedo"][2:, 2:].reshape(-1, 3).mean(0), rtol=1e-6)
    np.testing.assert_allclose(out["depth"][0, 1, 0], m["depth"][2:, :2].mean() / 1000, rtol=1e-6)
    assert out["depth"][0, 0, 0] == 0 and np.isfinite(out["depth"]).all()
    np.testing.assert_allclose(np.linalg.norm(out["normal"][:, 1, 1]), 1.0, rtol=1e-6)
    assert out["im"].dtype == np.float32 and out["im"].shape == (3, 2, 2)


def test_resize_is_identity_at_the_same_size_and_refuses_upsampling():
    m = _maps()
    out = resize_view(m, 4, 4)
    np.testing.assert_allclose(out["albedo"], m["albedo"].transpose(2, 0, 1), rtol=1e-6)
    with pytest.raises(ValueError, match="upsample"):
        resize_view(m, 8, 8)


@pytest.fixture
def dataset_copy(micro_root, tmp_path):
    """A writable copy of the micro dataset with three extra training scenes (copies of one scene)."""
    root = tmp_path / "iv"
    shutil.copytree(micro_root, root)
    train = iv.read_split(root, "train")
    for k in range(3):
        shutil.copytree(root / train[0], root / f"extra_{k}")
    iv.write_splits(root, {**iv.read_splits(root), "train": [*train, "extra_0", "extra_1", "extra_2"]})
    return root


def test_preprocess_writes_loadable_shards(dataset_copy, tmp_path):
    res = preprocess(dataset_copy, tmp_path / "shards", 24, 32, shard_size=3, progress=False)
    assert res.rejected == [] and res.manifest["lighting"]
    manifest = json.loads((tmp_path / "shards" / "manifest.json").read_text())
    assert len(manifest["splits"]["train"]["views"]) == 8 and len(manifest["splits"]["train"]["shards"]) == 3
    ds = ShardDataset(tmp_path / "shards", "train")
    item = ds[0]
    assert (
        item["im"].shape == (3, 24, 32) and item["depth"].shape == (1, 24, 32) and item["material"].shape == (2, 24, 32)
    )
    assert item["mask"].dtype.is_floating_point is False and item["mask"].any()
    assert (item["depth"][item["mask"]] > 0.3).all() and (item["depth"][~item["mask"]] == 0).all()
    light = item["light"]  # typed: ViewLighting with surf / free Probes
    assert light.surf.radiance.ndim == 4 and light.surf.radiance.shape == light.surf.directions.shape
    assert (light.surf.pixel[:, 0] < 24).all() and (light.surf.pixel[:, 1] < 32).all()
    assert light.free.normal is None and light.free.radiance.shape[-1] == 3
    batch = collate_views([ds[0], ds[1]])
    assert batch["im"].shape == (2, 3, 24, 32) and len(batch["light"]) == 2 and batch["id"][0] == item["id"]
    scenes = {s: set(manifest["splits"][s]["scenes"]) for s in iv.SPLITS}
    assert not (scenes["train"] & scenes["test"]) and not (scenes["val"] & scenes["test"])


def test_tampered_shard_is_detected(dataset_copy, tmp_path):
    preprocess(dataset_copy, tmp_path / "shards", 48, 64, progress=False)
    shard = tmp_path / "shards" / "val_000.npz"
    shard.write_bytes(shard.read_bytes()[:-10] + b"0123456789")
    with pytest.raises(iv.DatasetError, match="val_000.npz: checksum"):
        ShardDataset(tmp_path / "shards", "val")


def _damage(root):
    """Break five training views in five different ways; returns {(scene, view): expected reason}."""
    im = iv.map_path(root, "extra_0", "000", "im")
    im.write_bytes(im.read_bytes()[:200])
    iv.map_path(root, "extra_0", "001", "albedo").unlink()
    write_exr(iv.map_path(root, "extra_1", "000", "normal"), np.zeros((48, 64), np.float32))
    bad = iv.read_view(root, "extra_1", "001").maps["im"].copy()
    bad[3, 4, 1] = np.nan
    write_exr(iv.map_path(root, "extra_1", "001", "im"), bad)
    iv.light_path(root, "extra_2", "000").write_bytes(b"PK\x03\x04 truncated zip")
    return {
        ("extra_0", "000"): "cannot decode",
        ("extra_0", "001"): "file not found",
        ("extra_1", "000"): "1 channel(s), expected 3",
        ("extra_1", "001"): "NaN/inf",
        ("extra_2", "000"): "cannot read lighting file",
    }


def test_bad_views_are_rejected_with_file_and_reason(dataset_copy, tmp_path):
    expected = _damage(dataset_copy)
    # one valid pixel with a broken depth value is masked out and counted, not a reason to drop the view
    depth = iv.read_view(dataset_copy, "extra_2", "001").maps["depth"].copy()
    mask = iv.read_view(dataset_copy, "extra_2", "001").maps["mask"]
    i, j = np.argwhere(mask[..., 0] > 0)[0]
    depth[i, j] = np.inf
    write_exr(iv.map_path(dataset_copy, "extra_2", "001", "depth"), depth)

    res = preprocess(dataset_copy, tmp_path / "shards", 48, 64, progress=False)
    got = {(r["scene"], r["view"]): r for r in res.rejected}
    assert set(got) == set(expected)
    for key, reason in expected.items():
        assert reason in got[key]["reason"], got[key]
        assert got[key]["file"].startswith(str(dataset_copy / key[0] / key[1]))
    assert res.manifest["fixed_pixels"] == 1
    assert len(res.manifest["splits"]["train"]["views"]) == 8 - 5
    assert "extra_2/001" in res.manifest["splits"]["train"]["views"]


@pytest.mark.parametrize(
    "problem, match",
    [
        ("empty", "test.txt: split file lists no scenes"),
        ("missing", "val.txt: split file not found"),
        ("twice", "both list scene"),
        ("no_folder", "test.txt: lists scene 'ghost_scene', which has no folder"),
    ],
)
def test_bad_split_files_raise_naming_the_file(dataset_copy, tmp_path, problem, match):
    if problem == "empty":
        (dataset_copy / "test.txt").write_text("\n")
    elif problem == "missing":
        (dataset_copy / "val.txt").unlink()
    elif problem == "twice":
        (dataset_copy / "test.txt").write_text((dataset_copy / "train.txt").read_text())
    else:
        (dataset_copy / "test.txt").write_text("ghost_scene\n")
    with pytest.raises(iv.DatasetError, match=match):
        preprocess(dataset_copy, tmp_path / "shards", 48, 64, progress=False)


def test_a_split_left_without_valid_views_is_an_error(dataset_copy, tmp_path):
    test_scene = iv.read_split(dataset_copy, "test")[0]
    for view in iv.list_views(dataset_copy, test_scene):
        iv.map_path(dataset_copy, test_scene, view, "mask").unlink()
    with pytest.raises(iv.DatasetError, match="no valid view left in split 'test'"):
        preprocess(dataset_copy, tmp_path / "shards", 48, 64, progress=False)


def test_real_data_without_cameras_needs_a_fov(dataset_copy, tmp_path):
    for cams in dataset_copy.glob("*/cameras.json"):
        cams.unlink()
    with pytest.raises(iv.DatasetError, match="data.interiorverse.fov_x_deg"):
        preprocess(dataset_copy, tmp_path / "shards", 48, 64, progress=False)
    res = preprocess(dataset_copy, tmp_path / "shards", 48, 64, default_fov_x_deg=60.0, progress=False)
    assert ShardDataset(tmp_path / "shards", "test")[0]["fov_x_deg"] == 60.0
    assert res.rejected == []


def test_missing_root_is_named(tmp_path):
    with pytest.raises(iv.DatasetError, match="nowhere: dataset root does not exist"):
        preprocess(tmp_path / "nowhere", tmp_path / "out", 48, 64, progress=False)


def test_datamodule_batches_by_split_with_seeded_shuffle(dataset_copy, tmp_path):
    from pipeline.data.datamodules import InteriorVerseDataModule

    preprocess(dataset_copy, tmp_path / "shards", 24, 32, progress=False)
    orders = []
    for _ in range(2):
        dm = InteriorVerseDataModule(tmp_path / "shards", batch_size=3, seed=4)
        dm.setup("fit")
        batch = next(iter(dm.train_dataloader()))
        assert batch["im"].shape == (3, 3, 24, 32) and batch["mask"].shape == (3, 1, 24, 32)
        orders.append(batch["id"])
    assert orders[0] == orders[1], "same seed, same shuffle"
    dm.setup("test")
    test_ids = [i for b in dm.test_dataloader() for i in b["id"]]
    train_scenes = {i.split("/")[0] for i in dm.splits["train"].ids}
    assert test_ids and not train_scenes & {i.split("/")[0] for i in test_ids}


def test_a_test_only_set_keeps_its_test_split_and_names_the_missing_ones(dataset_copy, tmp_path):
    """An evaluation-only set (`synthesize`'s ood: train and val files empty) preprocesses when only the
    test split is required; its manifest has no training split, and reading one is refused by name."""
    for split in ("train", "val"):
        (dataset_copy / f"{split}.txt").write_text("")
    with pytest.raises(iv.DatasetError, match="train.txt: split file lists no scenes"):
        preprocess(dataset_copy, tmp_path / "all", 24, 32, progress=False)
    res = preprocess(dataset_copy, tmp_path / "shards", 24, 32, progress=False, required=("test",))
    assert set(res.manifest["splits"]) == {"test"} and res.manifest["splits"]["test"]["views"]
    assert len(ShardDataset(tmp_path / "shards", "test")) == len(res.manifest["splits"]["test"]["views"])
    with pytest.raises(iv.DatasetError, match="has no split 'train'"):
        ShardDataset(tmp_path / "shards", "train")
    # a required split whose listed views are all rejected stays an error
    test_scene = iv.read_split(dataset_copy, "test")[0]
    for view in iv.list_views(dataset_copy, test_scene):
        iv.map_path(dataset_copy, test_scene, view, "mask").unlink()
    with pytest.raises(iv.DatasetError, match="no valid view left in split 'test'"):
        preprocess(dataset_copy, tmp_path / "again", 24, 32, progress=False, required=("test",))
