"""Stand-ins are written in the published layouts, read back by the same loaders, and carry their labels."""

import numpy as np
import pytest

from pipeline.data import iiw, nyuv2, standins
from pipeline.metrics.whdr import whdr


def _views(n=4, H=12, W=16, seed=0):
    rng = np.random.default_rng(seed)
    views = []
    for k in range(n):
        albedo = np.repeat(rng.uniform(0.05, 0.9, (H, W, 1)), 3, -1)
        material = np.zeros((H, W, 2))
        material[:, :4, 1] = 1.0  # a metal strip
        depth = rng.uniform(1.5, 6.0, (H, W))
        depth[0, 0] = np.inf  # a window pixel
        mask = np.isfinite(depth)
        normal = np.zeros((H, W, 3))
        normal[..., 2] = 1.0
        views.append(
            {
                "id": f"s/{k}",
                "im": albedo * 2.0,
                "albedo": albedo,
                "material": material,
                "depth": depth,
                "mask": mask,
                "normal": normal,
            }
        )
    return views


def test_iiw_standin_reads_back_and_agrees_with_ground_truth(tmp_path):
    views = _views()
    ids = standins.build_iiw(views, tmp_path, seed=0, points=20, comparisons=30)
    assert iiw.list_ids(tmp_path) == sorted(ids)
    assert "not the IIW dataset" in (tmp_path / "SOURCE.txt").read_text()
    for image_id, view in zip(ids, views, strict=True):
        j = iiw.read_judgements(tmp_path, image_id)
        assert all(0 < c["darker_score"] <= 1 for c in j["intrinsic_comparisons"])
        for p in j["intrinsic_points"]:  # metal is marked non-opaque, exactly
            assert p["opaque"] == (int(p["x"] * 16) >= 4)
        # ground-truth albedo mostly agrees with the simulated annotators; a flat albedo calls every pair
        # equal and disagrees with every "darker" verdict
        assert whdr(view["albedo"], j, convention="linear") < 0.15
        darker = sum(c["darker_score"] for c in j["intrinsic_comparisons"] if c["darker"] != "E" and _opaque(j, c))
        total = sum(c["darker_score"] for c in j["intrinsic_comparisons"] if _opaque(j, c))
        assert whdr(np.full_like(view["albedo"], 0.5), j, convention="linear") == pytest.approx(darker / total)
        assert iiw.read_photo(tmp_path, image_id).dtype == np.uint8


def _opaque(j, c):
    pts = {p["id"]: p["opaque"] for p in j["intrinsic_points"]}
    return pts[c["point1"]] and pts[c["point2"]]


def test_nyu_standin_reads_back_through_the_loaders(tmp_path):
    views = _views(n=5)
    split = standins.build_nyuv2(views, tmp_path, test_every=3)
    assert split == {"train": [1, 2, 4], "test": [0, 3]}
    mat = tmp_path / "nyu_depth_v2_labeled.mat"
    loaded = nyuv2.read_splits(tmp_path / "splits.mat", nyuv2.count_images(mat))
    assert loaded["test"].tolist() == [0, 3]
    images, depths = nyuv2.read_labeled(mat, [3])
    assert images.shape == (1, 12, 16, 3)
    finite = views[3]["depth"].copy()
    finite[0, 0] = finite[np.isfinite(finite)].max()  # filled like NYUv2's depths
    assert np.allclose(depths[0], finite, rtol=1e-6)
    normal, valid = nyuv2.read_normal(tmp_path / "normals", tmp_path / "masks", 3, (12, 16))
    assert np.allclose(normal[..., 2], 1, atol=1e-3) and not valid[0, 0] and valid.sum() == 12 * 16 - 1


def test_standins_refuse_views_without_valid_pixels(tmp_path):
    bad = _views(n=1)
    bad[0]["mask"][:] = False
    with pytest.raises(ValueError, match="s/0"):
        standins.build_iiw(bad, tmp_path, seed=0)
