"""Training augmentation of MaterialNet batches: mirror, channel permutation, crop-and-resize."""

import math

import pytest
import torch

from pipeline.data.datasets import augment_views


def _blocky_batch(B=4, H=24, W=32, seed=0):
    """Piecewise-constant 4x4-pixel blocks, the image equal to the albedo (so alignment is checkable)."""
    g = torch.Generator().manual_seed(seed)
    blocks = lambda c: torch.rand(B, c, H // 4, W // 4, generator=g).repeat_interleave(4, -2).repeat_interleave(4, -1)  # noqa: E731
    albedo = blocks(3)
    normal = torch.nn.functional.normalize(blocks(3) - 0.5, dim=1)
    return {
        "im": albedo.clone(),
        "albedo": albedo,
        "normal": normal,
        "depth": 1 + blocks(1),
        "material": (blocks(2) > 0.5).float(),
        "mask": blocks(1) > 0.2,
        "fov_x_deg": torch.full((B,), 80.0),
        "id": [f"v{i}" for i in range(B)],
    }


def test_crop_keeps_labels_exact_and_aligned_with_the_image():
    b = _blocky_batch()
    out = augment_views(b, torch.Generator().manual_seed(3), permute=False, min_scale=0.5)
    for k in ("im", "albedo", "normal", "depth", "material", "mask"):
        assert out[k].shape == b[k].shape and out[k].dtype == b[k].dtype
    # nearest-texel labels: every value existed before (no blending across a label edge)
    assert set(out["material"].unique().tolist()) <= {0.0, 1.0}
    assert torch.allclose(out["normal"].norm(dim=1), torch.ones(1), atol=1e-5)
    # the bilinear image agrees with the nearest-texel albedo away from block edges: same geometry
    diff = (out["im"] - out["albedo"]).abs().amax(1)
    assert diff.median() < 1e-6
    # fov shrinks as the crop's width: 2 atan(s tan(fov / 2)) with s in [0.5, 1]
    lo = math.degrees(2 * math.atan(0.5 * math.tan(math.radians(40))))
    assert ((out["fov_x_deg"] <= 80.0) & (out["fov_x_deg"] >= lo - 1e-4)).all()
    assert (out["fov_x_deg"] < 80.0).any()
    assert (b["fov_x_deg"] == 80.0).all()  # the input batch is not modified


def test_mirror_negates_normal_x_and_permutation_moves_image_and_albedo_together():
    b = _blocky_batch(B=8)
    out = augment_views(b, torch.Generator().manual_seed(0), permute=True)
    assert torch.equal(out["im"], out["albedo"])  # the same permutation of both
    for i in range(8):
        flipped = not torch.equal(out["depth"][i], b["depth"][i])
        n = b["normal"][i].flip(-1) if flipped else b["normal"][i]
        assert torch.allclose(out["normal"][i, 0], -n[0] if flipped else n[0])
        assert torch.equal(out["material"][i], b["material"][i].flip(-1) if flipped else b["material"][i])


def test_no_crop_by_default_and_bad_scale_rejected():
    b = _blocky_batch()
    out = augment_views(b, torch.Generator().manual_seed(0), permute=False)
    assert torch.equal(out["fov_x_deg"], b["fov_x_deg"])
    with pytest.raises(ValueError, match="min_scale"):
        augment_views(b, torch.Generator().manual_seed(0), min_scale=0.0)
