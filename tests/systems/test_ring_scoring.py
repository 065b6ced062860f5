"""The ring around an inserted object (`systems.ring_scoring`): which pixels count as changed, that the
true change scores the cap and none scores below a partial one, views as the bootstrap's units, and the
world-to-view placement of an object's spheres."""

from types import SimpleNamespace

import numpy as np
import torch

from pipeline.systems.ring_scoring import changed_pixels, ring_change, ring_scores, summarise_ring, view_spheres


def _case(delta: torch.Tensor, stderr: float) -> SimpleNamespace:
    return SimpleNamespace(
        ring_pixel=torch.arange(len(delta)), ring_delta=delta, ring_stderr=torch.full_like(delta, stderr)
    )


def test_changed_pixels_need_both_significance_and_a_visible_share():
    base = torch.ones(4, 3)
    delta = torch.tensor([[-0.3] * 3, [-0.005] * 3, [0.2] * 3, [0.0] * 3])
    stderr = torch.tensor([[0.01] * 3, [0.0001] * 3, [0.1] * 3, [0.0] * 3])
    # 0: 30 standard errors and 30 % of the photo; 1: significant but 0.5 %; 2: 2 standard errors; 3: none
    assert changed_pixels(delta, stderr, base).tolist() == [True, False, False, False]


def test_the_true_change_scores_the_cap_and_no_change_scores_lowest():
    gen = torch.Generator().manual_seed(0)
    photo = 0.2 + torch.rand(4, 5, 3, generator=gen)
    delta = torch.zeros(8, 3)
    delta[:4] = -0.4 * photo.reshape(-1, 3)[:4]  # a shadow on four pixels, nothing on the other four
    scores = ring_scores(photo, _case(delta, 1e-4), {"lightnet": delta, "scaled_constant": 0.5 * delta}, scale=0.5)
    assert set(scores) == {"ring_no_shadows", "ring_lightnet", "ring_scaled_constant"}
    assert scores["ring_lightnet"]["psnr"] >= 119.9 and scores["ring_lightnet"]["psnr_surround"] >= 119.9
    none, half = scores["ring_no_shadows"], scores["ring_scaled_constant"]
    assert none["psnr"] < half["psnr"] < 119.9
    # the surroundings add exact pixels: the mean squared error halves, +3.01 dB
    assert np.isclose(none["psnr_surround"] - none["psnr"], 10 * np.log10(2), atol=1e-6)
    noisy = ring_scores(photo, _case(delta, 1.0), {"lightnet": delta}, scale=0.5)  # nothing significant
    assert np.isnan(noisy["ring_no_shadows"]["psnr"]) and np.isfinite(noisy["ring_no_shadows"]["psnr_surround"])
    empty = SimpleNamespace(ring_pixel=torch.zeros(0, dtype=torch.long), ring_delta=torch.zeros(0, 3))
    empty.ring_stderr = torch.zeros(0, 3)
    assert all(np.isnan(v) for s in ring_scores(photo, empty, {}, 0.5).values() for v in s.values())
    assert ring_change(None, {}, 60.0, torch.zeros(0, dtype=torch.long), None, None, torch.zeros(3), 0).shape == (0, 3)


def _records(effect: float, views: int = 6, seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    out = []
    for v in range(views):
        for label in ("mirror", "diffuse"):
            base = 20 + rng.normal()
            out.append(
                {
                    "view": f"s/{v}",
                    "kind": "object",
                    "label": label,
                    "ring_no_shadows/psnr": base,
                    "ring_no_shadows/psnr_surround": base + 5,
                    "ring_lightnet/psnr": base + effect + 0.1 * rng.normal(),
                    "ring_lightnet/psnr_surround": base + 5 + 0.1 * rng.normal(),
                    "ring_scaled_constant/psnr": base + rng.normal(),
                    "ring_scaled_constant/psnr_surround": base + 5 + rng.normal(),
                }
            )
    nan = dict(out[0], view="s/9", **{k: np.nan for k in out[0] if k.endswith("/psnr")})
    return [*out, nan, {"view": "s/0", "kind": "edit", "label": "metal", "lightnet/psnr": 20.0}]


def test_summary_counts_cases_with_a_ring_and_resamples_views():
    m = summarise_ring(_records(2.0), ("lightnet", "scaled_constant"), resamples=500, seed=0)
    assert m["insert/all/ring/cases"] == 12 and m["insert/mirror/ring/cases"] == 6  # the NaN case and the edit out
    key = "insert/all/ring/lightnet_minus_no_shadows/psnr"
    assert m[f"{key}_lo"] <= m[f"{key}_diff"] <= m[f"{key}_hi"] and m[f"{key}_verdict"] == 1.0
    assert abs(m[f"{key}_diff"] - 2.0) < 0.2
    assert "insert/all/ring/lightnet_minus_scaled_constant/psnr_diff" in m
    assert "insert/all/ring/no_shadows_minus_no_shadows/psnr_diff" not in m
    # the surroundings' score of the NaN case counts where finite
    assert np.isclose(m["insert/all/ring/no_shadows/psnr_surround"] - m["insert/all/ring/no_shadows/psnr"], 5, atol=0.5)
    null = summarise_ring(_records(0.0, seed=1), ("lightnet",), resamples=500, seed=0)
    assert null["insert/all/ring/lightnet_minus_no_shadows/psnr_verdict"] == 0.0


def test_view_spheres_take_world_points_into_the_cameras_frame():
    w2v = np.eye(4)
    w2v[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]  # the view's x axis along world -z
    w2v[:3, 3] = [1.0, 2.0, 3.0]
    world = [[1.0, 2.0, 1.0, 0.25]]  # 2 m along world -z from the camera: view x = +2
    out = view_spheres(world, w2v)
    assert out.dtype == torch.float64 and torch.allclose(
        out, torch.tensor([[2.0, 0.0, 0.0, 0.25]], dtype=torch.float64)
    )
