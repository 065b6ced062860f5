"""IIW and NYUv2 loaders on files written in the published formats, and their rejections."""

import json

import h5py
import numpy as np
import pytest
from PIL import Image
from scipy.io import savemat

from pipeline.data import iiw, nyuv2


def _iiw_root(tmp_path, ids=("10", "2", "33", "4", "5", "60", "7")):
    for i in ids:
        Image.fromarray(np.full((6, 8, 3), 100, np.uint8)).save(tmp_path / f"{i}.png")
        (tmp_path / f"{i}.json").write_text(
            json.dumps(
                {
                    "intrinsic_points": [
                        {"id": 1, "x": 0.1, "y": 0.2, "opaque": True},
                        {"id": 2, "x": 0.7, "y": 0.9, "opaque": False},
                    ],
                    "intrinsic_comparisons": [{"id": 9, "point1": 1, "point2": 2, "darker": "E", "darker_score": 0.8}],
                }
            )
        )
    return tmp_path


def test_iiw_split_is_every_fifth_string_sorted_id(tmp_path):
    ids = iiw.list_ids(_iiw_root(tmp_path))
    assert ids == ["10", "2", "33", "4", "5", "60", "7"]  # string order, not numeric
    split = iiw.split_ids(ids)
    assert split["test"] == ["10", "60"] and len(split["train"]) == 5
    assert not set(split["test"]) & set(split["train"])
    assert iiw.read_photo(tmp_path, "2").shape == (6, 8, 3)
    assert iiw.read_judgements(tmp_path, "2")["intrinsic_comparisons"][0]["darker"] == "E"


def test_iiw_rejects_orphans_and_malformed_judgements(tmp_path):
    root = _iiw_root(tmp_path)
    (root / "8.png").write_bytes((root / "2.png").read_bytes())
    with pytest.raises(iiw.IIWError, match="8"):
        iiw.list_ids(root)
    (root / "8.png").unlink()
    good = json.loads((root / "2.json").read_text())
    cases = {
        "unknown point": {**good, "intrinsic_comparisons": [{**good["intrinsic_comparisons"][0], "point2": 5}]},
        "missing list 'intrinsic_points'": {"intrinsic_comparisons": []},
        "outside": {**good, "intrinsic_points": [{"id": 1, "x": 1.2, "y": 0.1, "opaque": True}]},
        "darker='X'": {**good, "intrinsic_comparisons": [{**good["intrinsic_comparisons"][0], "darker": "X"}]},
    }
    for message, data in cases.items():
        (root / "2.json").write_text(json.dumps(data))
        with pytest.raises(iiw.IIWError, match=message.replace("(", r"\(")):
            iiw.read_judgements(root, "2")
    (root / "2.json").write_text("{not json")
    with pytest.raises(iiw.IIWError, match="2.json"):
        iiw.read_judgements(root, "2")


def test_srgb_curve_anchors_and_inverse():
    from pipeline.data.formats.photo import linear_to_srgb, srgb8_to_linear, srgb_to_linear

    # IEC 61966-2-1: 0.5 decodes to 0.2140 (a gamma 2.2 would give 0.2176), the linear toe below 0.04045
    assert srgb_to_linear(0.5) == pytest.approx(0.21404, abs=1e-5)
    assert srgb_to_linear(0.04) == pytest.approx(0.04 / 12.92, rel=1e-12)
    assert srgb_to_linear(1.0) == pytest.approx(1.0, rel=1e-12) and srgb_to_linear(0.0) == 0.0
    assert srgb8_to_linear(np.array([[[128, 0, 255]]], np.uint8))[0, 0].tolist() == pytest.approx(
        [0.21586, 0.0, 1.0], abs=1e-5
    )
    v = np.linspace(0, 1, 101)
    assert np.allclose(linear_to_srgb(srgb_to_linear(v)), v, atol=1e-12)


def test_display_tonemap_exposes_the_median_and_stays_in_unit_range():
    from pipeline.data.formats.photo import tonemap

    hdr = np.array([[[0.5, 1.0, 2.0], [np.nan, np.inf, 0.0]]])
    shown = tonemap(hdr)  # median positive value 1.0 -> 0.3, then x / (1 + x) and a 1/2.2 gamma
    assert shown[0, 0, 1] == pytest.approx((0.3 / 1.3) ** (1 / 2.2), rel=1e-12)
    assert shown[0, 1].tolist() == [0.0, 0.0, 0.0]  # NaN and +inf show as black
    assert np.allclose(tonemap(hdr * 7.5), shown)  # the default exposure follows the image
    assert tonemap(np.array([1.0]), exposure=1.0)[0] == pytest.approx(0.5 ** (1 / 2.2), rel=1e-12)
    assert ((shown >= 0) & (shown <= 1)).all()


def _nyu(tmp_path, n=5, H=4, W=6):
    rng = np.random.default_rng(0)
    images = rng.integers(0, 255, (n, H, W, 3), dtype=np.uint8)
    depths = rng.uniform(0.5, 9.0, (n, H, W)).astype(np.float32)
    path = tmp_path / "nyu_depth_v2_labeled.mat"
    with h5py.File(path, "w") as f:  # MATLAB v7.3 stores column-major: h5py sees the axes reversed
        f["images"] = np.transpose(images, (0, 3, 2, 1))
        f["depths"] = np.transpose(depths, (0, 2, 1))
    savemat(tmp_path / "splits.mat", {"trainNdxs": np.array([[1], [2], [4]]), "testNdxs": np.array([[3], [5]])})
    return path, images, depths


def test_nyu_labeled_and_splits_in_matlab_conventions(tmp_path):
    path, images, depths = _nyu(tmp_path)
    im, dp = nyuv2.read_labeled(path)
    assert np.array_equal(im, images) and np.allclose(dp, depths)
    im, dp = nyuv2.read_labeled(path, [4, 2, 4])
    assert np.array_equal(im, images[[4, 2, 4]]) and np.allclose(dp, depths[[4, 2, 4]])
    split = nyuv2.read_splits(tmp_path / "splits.mat", nyuv2.count_images(path))
    assert split["train"].tolist() == [0, 1, 3] and split["test"].tolist() == [2, 4]


def test_nyu_rejects_malformed_files(tmp_path):
    path, _, _ = _nyu(tmp_path)
    with pytest.raises(nyuv2.NYUError, match="outside 1..3"):
        nyuv2.read_splits(tmp_path / "splits.mat", 3)
    savemat(tmp_path / "bad.mat", {"trainNdxs": np.array([[0], [1]]), "testNdxs": np.array([[2]])})
    with pytest.raises(nyuv2.NYUError, match="1-based"):
        nyuv2.read_splits(tmp_path / "bad.mat", 5)
    savemat(tmp_path / "nokey.mat", {"trainNdxs": np.array([[1]])})
    with pytest.raises(nyuv2.NYUError, match="testNdxs"):
        nyuv2.read_splits(tmp_path / "nokey.mat", 5)
    with h5py.File(tmp_path / "nodepth.mat", "w") as f:
        f["images"] = np.zeros((2, 3, 6, 4), np.uint8)
    with pytest.raises(nyuv2.NYUError, match="'depths'"):
        nyuv2.read_labeled(tmp_path / "nodepth.mat")
    with h5py.File(tmp_path / "shape.mat", "w") as f:
        f["images"] = np.zeros((2, 3, 6, 4), np.uint8)
        f["depths"] = np.zeros((2, 4, 6), np.float32)
    with pytest.raises(nyuv2.NYUError, match="shape"):
        nyuv2.read_labeled(tmp_path / "shape.mat")
    with pytest.raises(nyuv2.NYUError, match="out of range"):
        nyuv2.read_labeled(path, [7])
    (tmp_path / "text.mat").write_text("MATLAB 5.0")
    with pytest.raises(nyuv2.NYUError, match="text.mat"):
        nyuv2.read_labeled(tmp_path / "text.mat")


def test_nyu_normals_png_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    n = rng.normal(size=(4, 6, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    nyuv2.write_normal_png(tmp_path / "normals" / "0003.png", n)
    mask = np.zeros((4, 6, 3), np.uint8)
    mask[1:] = 255
    mask[2, 2, 1] = 0  # one channel off -> invalid
    (tmp_path / "masks").mkdir()
    Image.fromarray(mask).save(tmp_path / "masks" / "0003.png")
    normal, valid = nyuv2.read_normal(tmp_path / "normals", tmp_path / "masks", 3, (4, 6))
    assert np.degrees(np.arccos(np.clip((normal * n).sum(-1), -1, 1))).max() < 1.0
    assert valid.sum() == 17 and not valid[0].any() and not valid[2, 2]
    with pytest.raises(nyuv2.NYUError, match="0004.png"):
        nyuv2.read_normal(tmp_path / "normals", tmp_path / "masks", 4, (4, 6))
