"""bench.shading_placement: the irradiance a ceiling cell casts against the closed form of a rectangle's
form factor, the fit recovers lamps from the shading they cause, and the bench runs on micro data."""

import math

import pytest
import torch

from pipeline.bench import shading_placement as sp


def _corner_irradiance(a: float, b: float, h: float) -> float:
    """Irradiance under a corner of an a x b rectangle of unit radiance at height h, parallel to the
    receiver (pi times the classic point-to-rectangle form factor)."""
    A, B = a / h, b / h
    sa, sb = math.sqrt(1 + A * A), math.sqrt(1 + B * B)
    return 0.5 * (A / sa * math.atan(B / sa) + B / sb * math.atan(A / sb))


BOX = (torch.eye(3, dtype=torch.float64), torch.tensor([-2.0, 0.0, -1.5]), torch.tensor([2.0, 2.5, 1.5]))


@pytest.mark.parametrize("sub", [8, 32])
def test_a_cell_lights_a_point_as_the_closed_form_says(sub):
    point = torch.tensor([[0.0, 0.5, 0.0]], dtype=torch.float64)  # under the ceiling's centre, 2 m below
    up = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
    E = sp.irradiance_matrix(point, up, BOX, 1, sub)
    exact = 4 * _corner_irradiance(2.0, 1.5, 2.0)  # four corner rectangles of 2 m x 1.5 m
    # the midpoint rule's error falls as 1/sub^2 (0.26 / sub^2 here): twice that is the bound
    assert float(E[0, 0]) == pytest.approx(exact, rel=0.5 / sub**2)
    # a surface facing away, or lying in the ceiling's plane, gets nothing
    assert float(sp.irradiance_matrix(point, -up, BOX, 1, sub)[0, 0]) == 0.0
    on_ceiling = torch.tensor([[0.0, 2.5, 0.0]], dtype=torch.float64)
    assert float(sp.irradiance_matrix(on_ceiling, -up, BOX, 2, sub).abs().sum()) == 0.0


def test_cells_are_row_major_along_z_then_x():
    centres, area = sp.ceiling_patches(BOX, 2, 1)
    assert area == pytest.approx(4.0 * 3.0 / 4)
    assert centres[:, 0].tolist() == [[-1.0, 2.5, -0.75], [1.0, 2.5, -0.75], [-1.0, 2.5, 0.75], [1.0, 2.5, 0.75]]


def test_box_texels_are_laid_out_as_the_branch_looks_them_up():
    from pipeline.ops.roombox import exit_face

    centres, normals, areas = sp.box_texel_geometry(BOX, 4)
    assert centres.shape == (96, 3) and float(areas[:16].sum()) == pytest.approx(2.5 * 3.0)  # the left wall
    # a ray from the box's centre to a texel's centre leaves through that texel (face, t, s order)
    middle = ((BOX[1] + BOX[2]) / 2).expand(96, 3)
    face, st, _ = exit_face(middle, centres - middle, BOX[1].expand(96, 3), BOX[2].expand(96, 3))
    texel = ((st + 1) * 2).long().clamp(0, 3)
    assert torch.equal(face * 16 + texel[:, 1] * 4 + texel[:, 0], torch.arange(96))
    assert torch.equal((normals * (middle - centres)).sum(-1) > 0, torch.ones(96, dtype=torch.bool))  # inward
    # the ceiling's texels cast what the ceiling's cells cast (one patch each), on points a texel away
    point = torch.tensor([[0.3, 0.4, -0.2], [-1.5, 1.0, 1.0]], dtype=torch.float64)
    normal = torch.nn.functional.normalize(
        torch.tensor([[0.2, 1.0, 0.1], [1.0, 0.3, 0.0]], dtype=torch.float64), dim=-1
    )
    ceiling = sp.texel_transfer(point, normal, BOX, 4)[:, 3 * 16 : 4 * 16]
    assert torch.allclose(ceiling, sp.irradiance_matrix(point, normal, BOX, 4, 1), rtol=1e-12)


def test_the_fit_recovers_lamps_from_the_shading_they_cast():
    g = torch.Generator().manual_seed(0)
    P = 600
    # points on the floor and the four walls of BOX, normals into the room
    face = torch.randint(0, 5, (P,), generator=g)
    u = torch.rand(P, 3, generator=g, dtype=torch.float64)
    lo, hi = BOX[1], BOX[2]
    point = lo + u * (hi - lo)
    normal = torch.zeros(P, 3, dtype=torch.float64)
    for f, (axis, side) in enumerate([(1, 0), (0, 0), (0, 1), (2, 0), (2, 1)]):
        sel = face == f
        point[sel, axis] = (lo if side == 0 else hi)[axis]
        normal[sel, axis] = 1.0 if side == 0 else -1.0
    point[:, 1] = point[:, 1].clamp(max=2.3)  # clear of the ceiling
    albedo = 0.2 + 0.7 * torch.rand(P, 3, generator=g, dtype=torch.float64)
    grid = 3
    lamps = torch.zeros(grid * grid, 3, dtype=torch.float64)
    lamps[1] = torch.tensor([6.0, 5.0, 4.0])
    lamps[8] = torch.tensor([2.0, 2.0, 3.0])
    ambient = torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64)
    E = sp.irradiance_matrix(point, normal, BOX, grid, 4)
    radiance = albedo / math.pi * (E @ lamps) + albedo * ambient
    px = {"point": point, "normal": normal, "albedo": albedo, "radiance": radiance}
    fit = sp.fit_view(px, BOX, grid, 4, trim=0.0)
    assert torch.allclose(fit["cells"], lamps, atol=1e-6 * float(lamps.max()))
    assert torch.allclose(fit["ambient"], ambient, atol=1e-6)
    assert fit["relative_residual"] < 1e-8 and fit["pixels"] == P
    # a few specular highlights (radiance far above the model) are trimmed away by the refit
    spiked = radiance.clone()
    spiked[:6] += 50.0
    fit = sp.fit_view({**px, "radiance": spiked}, BOX, grid, 4, trim=0.02)
    assert fit["pixels"] == P - 12
    assert torch.allclose(fit["cells"], lamps, atol=1e-5 * float(lamps.max()))
    # with the walls' bounce: the seen walls' light known, the unseen walls' at one unknown radiance
    wall = sp.texel_transfer(point, normal, BOX, 4)
    seen_walls = torch.rand(96, generator=g) < 0.5
    seen_walls[48:64] = False  # the ceiling is the cells'
    unseen_walls = ~seen_walls
    unseen_walls[48:64] = False
    wall_radiance = torch.rand(96, 3, generator=g, dtype=torch.float64)
    known = wall[:, seen_walls] @ wall_radiance[seen_walls]
    unseen = wall[:, unseen_walls].sum(1)
    bounced = radiance + albedo / math.pi * (known + 0.4 * unseen[:, None])
    fit = sp.fit_view({**px, "radiance": bounced}, BOX, grid, 4, 0.0, {"known": known, "unseen": unseen})
    assert torch.allclose(fit["cells"], lamps, atol=1e-6 * float(lamps.max()))
    assert fit["relative_residual"] < 1e-8
    # a view with nothing to fit places no lamp (a uniform placement) and says so
    empty = {k: v[:0] for k, v in px.items()}
    fit = sp.fit_view(empty, BOX, grid, 4, trim=0.02)
    assert fit["pixels"] == 0 and float(fit["cells"].abs().sum()) == 0 and math.isnan(fit["relative_residual"])


def test_runs_on_the_micro_data(micro_shards, micro_exports, tmp_path):
    report = sp.run(str(micro_shards), grid=2, sub=2, pixels=200)
    names = [row["placement"] for row in report["summary"]["each placement"]]
    assert names == [
        "true lamps",
        "true placement",
        "uniform over the ceiling",
        "training rooms' mean",
        "shading fit (placement, true energy)",
        "shading fit shrunk to the mean (placement, true energy)",
        "shading fit (its own radiance)",
        "shading fit shrunk, calibrated energy",
        "seen texels, the rest at the image mean",
        "seen texels, shading-fit lamps, the rest at the image mean",
    ]
    nmse = {row["placement"]: row["surface nMSE"] for row in report["summary"]["each placement"]}
    assert all(math.isfinite(v) for v in nmse.values())
    d = report["differences"]["surf: shading fit (placement, true energy) - training rooms' mean"]
    expected = nmse["shading fit (placement, true energy)"] - nmse["training rooms' mean"]
    assert d["diff"] == pytest.approx(expected, rel=1e-6, abs=1e-9)
    assert report["pixels_used"]["min"] > 0
    sp.plot(report, tmp_path / "s.png")
    assert (tmp_path / "s.png").stat().st_size > 5_000
    assert report["gbuffers"] == "ground truth"
    validation = report["validation"]
    assert (
        validation["chosen weight"] in sp.WEIGHTS
        and len(validation["mean nMSE (surface and free) by the fit's weight"]) == 11
    )
    assert validation["energy scale (true over fitted, median)"] > 0
    # on a MaterialNet's G-buffers the fit changes, the references do not
    predicted = sp.run(
        str(micro_shards),
        grid=2,
        sub=2,
        pixels=200,
        views=2,
        material=micro_exports / "material.pt",
        light_net=micro_exports / "light.pt",
    )
    assert predicted["gbuffers"].startswith("MaterialNet") and predicted["test_views"] == 2
    assert 0 <= predicted["views_without_pixels"] <= 2
    rows = {row["placement"]: row for row in predicted["summary"]["each placement"]}
    assert all(math.isfinite(row["surface nMSE"]) for row in rows.values())
    assert "trained out-of-view branch" in rows
    d = predicted["differences"]["surf: seen texels, the rest at the image mean - trained out-of-view branch"]
    expected = (
        rows["seen texels, the rest at the image mean"]["surface nMSE"]
        - rows["trained out-of-view branch"]["surface nMSE"]
    )
    assert d["diff"] == pytest.approx(expected, rel=1e-6, abs=1e-9)
    learned = sp.run(str(micro_shards), grid=2, sub=2, pixels=200, learned_seeds=1, epochs=2)
    rows = {row["placement"] for row in learned["summary"]["each placement"]}
    assert {"from the photo, seed 0", "from the photo and the fit, seed 0"} <= rows
    assert set(learned["learned"]["kept_epoch"].values()) <= {1, 2}
    estimated = sp.run(str(micro_shards), grid=2, sub=2, pixels=200, views=2, box="estimated")
    assert estimated["box"] == "estimated" and all(
        math.isfinite(row["surface nMSE"]) for row in estimated["summary"]["each placement"]
    )
    with pytest.raises(ValueError, match="--learned-seeds -1"):
        sp.run(str(micro_shards), learned_seeds=-1)
    with pytest.raises(ValueError, match="--box floor"):
        sp.run(str(micro_shards), box="floor")
    with pytest.raises(ValueError, match="--predicted colour"):
        sp.run(str(micro_shards), material=micro_exports / "material.pt", predicted=("colour",))
    with pytest.raises(ValueError, match="--pixels 4"):
        sp.run(str(micro_shards), grid=2, pixels=4)
    with pytest.raises(ValueError, match="--depth-noise 1.5"):
        sp.run(str(micro_shards), depth_noise=1.5)
    noisy = sp.run(str(micro_shards), grid=2, sub=2, pixels=200, views=2, depth_noise=0.1)
    assert noisy["depth_noise"] == 0.1 and noisy["gbuffers"] == "ground truth, depth x (1 + 0.1 smooth field)"


def test_depth_noise_is_a_smooth_field_of_the_size_asked_for():
    """`noisy_depth`: the depth times 1 + e f, f smooth (neighbouring pixels nearly equal) with a spread that
    scales with e, the same for the same seed, another for another; pixels without depth stay without."""
    import torch

    depth = torch.full((1, 48, 64), 3.0)
    depth[0, :4] = 0.0  # no depth there
    maps = {"depth": depth, "im": torch.zeros(3, 48, 64)}
    assert sp.noisy_depth(maps, 0.0, 1) is maps
    a, b, c = (sp.noisy_depth(maps, e, s)["depth"] for e, s in ((0.1, 1), (0.1, 1), (0.1, 2)))
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert torch.equal(a[0, :4], depth[0, :4]) and a.dtype == depth.dtype
    ratio = a[0, 4:] / 3.0 - 1
    assert 0.02 < float(ratio.std()) < 0.15  # of the order of e = 0.1 (bicubic knots narrow it)
    assert float((ratio[:, 1:] - ratio[:, :-1]).abs().max()) < 0.02  # smooth: under 1/5 of e a pixel
    doubled = sp.noisy_depth(maps, 0.2, 1)["depth"][0, 4:] / 3.0 - 1
    assert torch.allclose(doubled, 2 * ratio, atol=1e-5)


def test_fitted_lamps_fill_only_the_unseen_ceiling(micro_shards):
    import json
    from pathlib import Path

    from pipeline.bench.blend_floor import ground_truth_gbuffers, view_rays
    from pipeline.bench.visible_light import TEXTURE_SIZE, box_texels, observed, seen_lookup
    from pipeline.data.datasets import ShardDataset, collate_views

    source_root = Path(json.loads((micro_shards / "manifest.json").read_text())["source_root"])
    test = ShardDataset(micro_shards, "test", lighting=True)
    batch = collate_views([test[0]])
    gb = ground_truth_gbuffers(batch)
    r = view_rays(batch, gb, "surf")
    grid = 2
    glow = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    box = sp.true_box(source_root, batch["id"][0])
    seen = observed(batch, gb, box, TEXTURE_SIZE)
    lamps = glow.expand(1, grid * grid, 3).clone()
    sources = sp.CompleteSources(grid, lamps, [box], [seen])(0, batch, gb, r)
    added = sources[sp.SEEN_AND_FIT] - sources[sp.SEEN_ONLY]
    _, was_seen = seen_lookup(seen, box, r["origin"], r["direction"], TEXTURE_SIZE)
    ceiling = box_texels(box, r["origin"], r["direction"], grid) // (grid * grid) == 3
    lit = ceiling & ~was_seen
    assert lit.any() and (~lit).any()
    assert torch.allclose(added[lit], glow.expand(int(lit.sum()), 3), rtol=0, atol=1e-12)
    assert float(added[~lit].abs().max()) == 0.0


def test_predicted_maps_replace_only_the_maps_asked_for():
    item = {
        "im": torch.rand(3, 4, 5),
        "albedo": torch.zeros(3, 4, 5),
        "normal": torch.zeros(3, 4, 5),
        "material": torch.zeros(2, 4, 5),
        "depth": torch.ones(1, 4, 5),
        "mask": torch.ones(1, 4, 5, dtype=torch.bool),
    }
    item["mask"][0, 0, 0] = False

    def net(im):
        return {"albedo": im + 1, "normal": im + 2, "material": im[:, :2] + 3, "depth": im[:, :1] + 4}

    out = sp.predicted_maps(item, net, 2.0, ("albedo", "depth"))
    assert torch.equal(out["albedo"], item["im"] + 1) and torch.equal(out["normal"], item["normal"])
    assert torch.equal(out["material"], item["material"])
    assert float(out["depth"][0, 0, 0]) == 0.0  # outside the mask
    assert torch.allclose(out["depth"][0, 1:], (item["im"][:1, 1:] + 4) * 2.0)
    every = sp.predicted_maps(item, net, 2.0)
    assert torch.equal(every["normal"], item["im"] + 2) and torch.equal(every["material"], item["im"][:2] + 3)
