"""MaterialNet losses and metrics: least-squares scale, masking, baselines, the accuracy gate."""

import pytest
import torch

from pipeline.metrics.synthetic import albedo_mse, depth_log_mse, ls_scale, normal_angle
from pipeline.systems.material_baselines import BASELINE_MAPS, MaterialBaselines, accuracy_gate
from pipeline.systems.material_losses import MaterialLoss, depth_loss


def _batch(B=2, H=6, W=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(B, 1, H, W, generator=g) > 0.3
    normal = torch.nn.functional.normalize(torch.randn(B, 3, H, W, generator=g), dim=1)
    return {
        "im": torch.rand(B, 3, H, W, generator=g) * 5,
        "albedo": torch.rand(B, 3, H, W, generator=g),
        "normal": normal,
        "material": torch.rand(B, 2, H, W, generator=g),
        "depth": torch.where(mask, 1 + 4 * torch.rand(B, 1, H, W, generator=g), torch.zeros(B, 1, H, W)),
        "mask": mask,
    }


def test_ls_depth_scale_is_exact_on_a_scaled_ground_truth():
    b = _batch()
    gt = b["depth"].double()
    for c in (1e-3, 0.37, 250.0):
        pred = gt / c
        s = ls_scale(pred, gt, b["mask"])
        assert torch.allclose(s.flatten(), torch.full((2,), c, dtype=torch.float64), rtol=1e-12)
        assert depth_log_mse(pred, gt, b["mask"]).abs().max() < 1e-20
        assert float(depth_loss(pred, gt, b["mask"])) < 1e-20


def test_losses_and_metrics_ignore_masked_pixels():
    b = _batch()
    pred = {k: b[k].clone() * 0.8 + 0.05 for k in ("albedo", "material")}
    pred["normal"] = torch.nn.functional.normalize(b["normal"] + 0.3, dim=1)
    pred["depth"] = b["depth"].clamp(min=0.5) * 1.3 + 0.1
    loss = MaterialLoss()
    total, terms = loss(pred, b)
    # scribble over every masked-out pixel of predictions and ground truth alike
    off = ~b["mask"]
    b2 = {k: v.clone() for k, v in b.items()}
    pred2 = {k: v.clone() for k, v in pred.items()}
    for d in (b2, pred2):
        for k in ("albedo", "normal", "material", "depth"):
            d[k] = torch.where(off.expand_as(d[k]), torch.full_like(d[k], 0.77), d[k])
    total2, terms2 = loss(pred2, b2)
    assert torch.allclose(total, total2) and all(torch.allclose(terms[k], terms2[k]) for k in terms)
    for fn, key in ((albedo_mse, "albedo"), (normal_angle, "normal")):
        assert torch.allclose(fn(pred[key], b[key], b["mask"]), fn(pred2[key], b2[key], b["mask"]))


def test_perfect_prediction_has_zero_loss_and_empty_mask_gives_nan_metric():
    b = _batch()
    pred = {k: b[k] for k in ("albedo", "normal", "material", "depth")}
    total, _ = MaterialLoss()(pred, b)
    assert float(total) < 1e-6
    empty = torch.zeros_like(b["mask"])
    assert torch.isnan(albedo_mse(b["albedo"], b["albedo"], empty)).all()


def test_loss_weights_are_checked_and_perceptual_needs_weights(tmp_path):
    with pytest.raises(ValueError, match="loss.depth"):
        MaterialLoss(depth=-1)
    assert not MaterialLoss(perceptual=0.1, perceptual_weights=None).perceptual_on
    with pytest.raises(FileNotFoundError, match="loss.perceptual_weights"):
        MaterialLoss(perceptual=0.1, perceptual_weights=str(tmp_path / "vgg16.pth"))


def test_baselines_fit_the_training_means_and_score_every_map():
    b = _batch()
    base = MaterialBaselines.fit([b])
    m = b["mask"].double()
    expect = (b["albedo"].double() * m).sum(dim=(0, 2, 3)) / m.sum()
    assert torch.allclose(base.mean_albedo.flatten(), expect)
    per = base.metrics(b)
    assert set(per) == {f"{n}/{k}" for n, ks in BASELINE_MAPS.items() for k in ks}
    assert all(v.shape == (2,) and torch.isfinite(v).all() for v in per.values())
    with pytest.raises(ValueError, match="no valid pixels"):
        MaterialBaselines.fit([{**b, "mask": torch.zeros_like(b["mask"])}])


def test_accuracy_gate_needs_the_margin_on_every_map():
    base = {f"{n}/{k}": 1.0 for n, ks in BASELINE_MAPS.items() for k in ks}
    model = {k: 0.5 for ks in BASELINE_MAPS.values() for k in ks}
    assert accuracy_gate(model, base)["gate/passed"] == 1.0
    assert accuracy_gate({**model, "metallic_mse": 0.85}, base)["gate/passed"] == 0.0


def test_metallic_bce_is_the_binary_cross_entropy_and_corrects_confident_misses():
    from pipeline.systems.material_losses import material_loss

    b = _batch()
    p = torch.full_like(b["material"], 0.02, requires_grad=True)
    gt = b["material"].clone()
    gt[:, 1] = (gt[:, 1] > 0.5).float()
    m = b["mask"]
    bce = material_loss(p, gt, m, "bce")
    rough = ((p[:, :1] - gt[:, :1]) ** 2)[m].mean()
    ref = torch.nn.functional.binary_cross_entropy(p[:, 1:][m], gt[:, 1:][m])
    assert torch.allclose(bce, 0.5 * (rough + ref), rtol=1e-5)
    # a confident miss (p = sigmoid(-4), y = 1): on the logit BCE pulls with (p - y) / 2 per pixel (the
    # 1/2 averages it with roughness), L2 over both channels with 2 (p - y) p (1 - p) / 2: 28x weaker
    logit = torch.full_like(p, -4.0, requires_grad=True)
    q = torch.sigmoid(torch.tensor(-4.0))
    target = torch.cat([torch.sigmoid(logit[:, :1]).detach(), torch.ones_like(p[:, 1:])], 1)
    for kind, expect in (("bce", (q - 1) / 2), ("l2", (q - 1) * q * (1 - q))):
        logit.grad = None
        material_loss(torch.sigmoid(logit), target, m, kind).backward()
        g = logit.grad[:, 1:][m] * m.sum()
        assert torch.allclose(g, torch.full_like(g, float(expect)), rtol=1e-4)
    with pytest.raises(ValueError, match="loss.metallic"):
        MaterialLoss(metallic="focal")


def test_released_perceptual_term_is_a_pooled_mask_l2_on_relu3_3_over_four_maps(tmp_path):
    """The `paper` loss: VGG16 relu3_3 (features[:16]), sum (fx - fy)^2 m / sum m with the mask
    average-pooled to the layer, raw inputs, weights 1, 1, 0.5, 0.5 on albedo, normal, roughness, metallic;
    recomputed here from a plain torchvision VGG16 with the same (random) weights."""
    from torchvision.models import vgg16

    torch.manual_seed(0)
    path = tmp_path / "vgg16.pth"
    torch.save(vgg16(weights=None).state_dict(), path)
    maps = {"albedo": 1.0, "normal": 1.0, "roughness": 0.5, "metallic": 0.5}
    loss = MaterialLoss(
        perceptual=0.01,
        perceptual_weights=str(path),
        perceptual_maps=maps,
        perceptual_layers=["relu3_3"],
        perceptual_distance="l2_masked",
        perceptual_imagenet_norm=False,
    )
    b = _batch(H=16, W=24)
    pred = {k: (v + 0.1 * torch.rand_like(v)) for k, v in b.items() if k in ("albedo", "normal", "material", "depth")}
    _, terms = loss(pred, b)
    net = vgg16(weights=None)
    net.load_state_dict(torch.load(path, weights_only=True))
    feats = net.features[:16].eval()
    m = b["mask"].float()

    def dist(x, y):
        fx, fy = feats(x * m), feats(y * m)
        k = (m.shape[-2] // fx.shape[-2], m.shape[-1] // fx.shape[-1])  # as released: loss.py:57-60
        pooled = torch.nn.functional.avg_pool2d(m, k, k).expand_as(fx)
        return ((fx - fy) ** 2 * pooled).sum() / pooled.sum()

    rough = [x["material"][:, :1].expand(-1, 3, -1, -1) for x in (pred, b)]
    metal = [x["material"][:, 1:].expand(-1, 3, -1, -1) for x in (pred, b)]
    expect = (
        dist(pred["albedo"], b["albedo"]) + dist(pred["normal"], b["normal"]) + 0.5 * dist(*rough) + 0.5 * dist(*metal)
    )
    assert torch.allclose(terms["perceptual"], expect, rtol=1e-4)
    with pytest.raises(ValueError, match="perceptual_maps"):
        MaterialLoss(perceptual_maps={"depth": 1.0})
    with pytest.raises(ValueError, match="perceptual_layers"):
        MaterialLoss(perceptual=0.01, perceptual_weights=str(path), perceptual_layers=["relu9_9"])


def test_depth_loss_in_max_units_is_scale_free_and_names_bad_units():
    from pipeline.systems.material_losses import depth_loss

    b = _batch()
    pred = b["depth"] * 0.37 + 0.05
    a = depth_loss(pred, b["depth"], b["mask"], "max")
    c = depth_loss(pred, b["depth"] * 10, b["mask"], "max")  # ground truth in other units: same target
    assert torch.allclose(a, c, rtol=1e-5) and not torch.allclose(a, depth_loss(pred, b["depth"] * 10, b["mask"]))
    with pytest.raises(ValueError, match="depth_units"):
        depth_loss(pred, b["depth"], b["mask"], "feet")
