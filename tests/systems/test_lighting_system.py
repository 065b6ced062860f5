"""LightingSystem's G-buffers: the frozen MaterialNet's maps kept per view, and the depth SSRT marches
against (`lighting.ssrt_depth`)."""

import pytest
import torch

from pipeline.models.export import LIGHT_FORMAT, read_export
from pipeline.models.material_net import load_material_export
from pipeline.systems.lighting import LightingSystem

RENDER = {"estimator": "importance", "spp": 2, "eval_spp": 2, "seed": 0}


def _system(micro_exports, **kwargs):
    light = read_export(micro_exports / "light.pt", LIGHT_FORMAT)["light_net"]
    material = load_material_export(micro_exports / "material.pt")[1]
    return LightingSystem(light_net=light, material=material, render=RENDER, **kwargs)


def _batch():
    g = torch.Generator().manual_seed(0)
    mask = torch.ones(2, 1, 48, 64, dtype=torch.bool)
    mask[:, :, :8] = False  # a band without material (lamps, sky): no ground-truth depth there
    return {"im": torch.rand(2, 3, 48, 64, generator=g), "mask": mask, "id": ["a/000", "b/000"]}


def test_material_maps_run_once_per_view_and_again_for_a_new_image(micro_exports, monkeypatch):
    system = _system(micro_exports)
    calls = []
    forward = system.material.forward
    monkeypatch.setattr(system.material, "forward", lambda im: calls.append(len(im)) or forward(im))
    batch = _batch()
    first = system.material_maps(batch)
    again = system.material_maps(batch)
    assert calls == [2]
    for k in first:
        assert torch.equal(first[k], again[k])
    plain = system.material(batch["im"])
    for k in first:  # the kept maps are the network's, view by view
        torch.testing.assert_close(first[k], plain[k], rtol=1e-4, atol=1e-5)
    calls.clear()
    batch["im"][1] *= 2.0  # the same id with another image (augmented, edited): computed afresh
    system.material_maps(batch)
    assert calls == [1]
    system.cache_gbuffers = False
    calls.clear()
    system.material_maps(batch)
    assert calls == [2]


def test_ssrt_depth_every_pixel_keeps_maternet_depth_where_the_mask_is_off(micro_exports):
    batch = _batch()
    valid = _system(micro_exports).gbuffers(batch)["depth"]
    every = _system(micro_exports, ssrt_depth="every_pixel").gbuffers(batch)["depth"]
    off = ~batch["mask"][:, 0]
    assert (valid[off] == 0).all() and (every[off] > 0).all()
    assert torch.equal(valid[~off], every[~off])
    with pytest.raises(ValueError, match="ssrt_depth"):
        _system(micro_exports, ssrt_depth="everywhere")
    with pytest.raises(ValueError, match="gbuffers=predicted"):
        LightingSystem(
            light_net=read_export(micro_exports / "light.pt", LIGHT_FORMAT)["light_net"],
            material=None,
            render=RENDER,
            gbuffers="ground_truth",
            ssrt_depth="every_pixel",
        )
