"""bench.real_photo: the photo and its calibration, the floor pixels from the normals, the three objects."""

import math

import numpy as np
import pytest
import torch

from pipeline.bench import real_photo


def test_photo_is_linear_with_its_calibrated_field_of_view_and_stereo_depth():
    im, depth, fov = real_photo.photo()
    assert im.shape == (500, 741, 3) and im.dtype == np.float32 and 0 <= im.min() and im.max() <= 1
    assert math.isclose(fov, math.degrees(2 * math.atan(370.5 / 994.978)), rel_tol=1e-12)  # about 40.9
    finite = depth[np.isfinite(depth)]
    assert 0.5 * depth.size < finite.size < depth.size and 0.3 < np.median(finite) < 5  # metres; unmatched: NaN


def test_floor_pixels_are_low_upward_and_spread():
    H, W = 60, 90
    normal = torch.zeros(3, H, W)
    normal[2] = 1.0  # a wall facing the camera
    normal[:, 45:, 10:80] = torch.tensor([0.0, 1.0, 0.0])[:, None, None]  # the floor below row 45
    depth = torch.ones(H, W)
    pixels = real_photo.floor_pixels(normal, depth)
    assert len(pixels) == 3
    for r, c in pixels:
        assert r >= 45 and 10 <= c < 80 and normal[1, r, c] > 0.8
    assert pixels[0][1] < pixels[1][1] < pixels[2][1]
    with pytest.raises(ValueError, match="no floor"):
        real_photo.floor_pixels(torch.zeros(3, H, W), depth)


def test_objects_are_a_mirror_sphere_and_two_vases(tmp_path):
    objects = real_photo.objects_at([(50, 20), (50, 45), (50, 70)])
    assert objects[0].shape == "sphere" and objects[0].material[2] == 1.0
    vertices, faces = objects[1].shape
    assert faces.shape[1] == 3 and vertices.shape[1] == 3
    assert objects[2].material[1] > objects[1].material[1]  # the diffuse vase is rougher
    report = {
        "pixels": {"x": [(50, 20)]},
        "images": {"photo": np.full((60, 90, 3), 0.2), "x": np.full((60, 90, 3), 0.3)},
    }
    real_photo.plot(report, tmp_path / "p.png")
    assert (tmp_path / "p.png").stat().st_size > 0


def test_run_inserts_three_objects_and_checks_the_depth(micro_exports, monkeypatch):
    H, W = 48, 64
    g = np.random.default_rng(0)
    depth = np.full((H, W), 2.0)
    depth[:4] = np.nan  # no disparity there
    monkeypatch.setattr(real_photo, "photo", lambda: (g.random((H, W, 3), dtype=np.float32) * 0.5, depth, 60.0))
    monkeypatch.setattr(real_photo, "floor_pixels", lambda normal, d: [(40, 12), (40, 32), (40, 52)])
    report = real_photo.run(str(micro_exports / "material.pt"), {"a": str(micro_exports / "light.pt")}, 2, 0)
    m = report["measured"]
    assert m["depth_pixels_with_disparity"] <= (H - 4) * W and math.isfinite(m["depth_log_rmse_after_scale"])
    (row,) = m["insertions"]
    assert row["light_net"] == "a" and row["object_pixels"] > 0
    assert report["pixels"]["a"] == [(40, 12), (40, 32), (40, 52)] and set(report["images"]) == {"photo", "a"}
