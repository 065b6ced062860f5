"""The probe-resolution bench: its map sizes, the map it renders against the generator's own probes, its
summary, and a run on the micro data."""

import json
import math

import numpy as np
import pytest

from pipeline.bench import probe_resolution as pr


def test_sizes_are_parsed_sorted_and_checked():
    assert pr.parse_sizes(["32x64", "16x32", "16x32"]) == [(16, 32), (32, 64)]
    for bad in (["16"], ["16x16"], ["ax2"], ["1x2"], []):
        with pytest.raises(ValueError, match="--sizes"):
            pr.parse_sizes(bad)


def test_summary_means_and_paired_differences():
    records = []
    for i in range(6):
        label = ("mirror", "diffuse")[i % 2]
        records.append(
            {
                "view": f"v{i // 2}",
                "label": label,
                "lightnet_fine": 10.0 + i,
                "nearest_probe_fine": 11.0,
                "centre_4x8": 13.0 + i,
            }
        )
    s = pr.summarise(records, ["lightnet_fine", "nearest_probe_fine", "centre_4x8"], resamples=200, seed=0)
    assert set(s) == {"mirror", "diffuse", "all"}
    assert s["mirror"]["cases"] == 3 and s["mirror"]["views"] == 3
    assert s["all"]["psnr"]["lightnet_fine"] == pytest.approx(12.5)
    d = s["all"]["differences"]["centre_4x8_minus_lightnet_fine"]
    assert d["diff"] == pytest.approx(3.0) and d["lo"] == pytest.approx(3.0) and d["hi"] == pytest.approx(3.0)
    assert s["mirror"]["differences"]["centre_4x8_minus_nearest_probe_fine"]["diff"] == pytest.approx(4.0)
    assert [r["class"] for r in pr.headline(s, ["lightnet_fine"])] == ["mirror", "diffuse", "all"]
    diffs = pr.headline_differences(s)
    assert {r["row minus lightnet_fine"] for r in diffs} == {"centre_4x8"} and len(diffs) == 3
    assert diffs[0]["dB"] == pytest.approx(3.0)


@pytest.mark.slow
def test_a_centre_map_at_a_free_probe_is_the_generators_probe(micro_root, mitsuba_variant):
    """Rendered at a free probe's position and size, the bench's map estimates the same texel means as the
    generator's probe (`synth.views.lighting_probes`, both at 64 directions a texel): the energies agree
    within 5 sigma, the texels' z-scores are those of noise (mean z^2 near 1), and the test tells a map
    mirrored in azimuth (mean z^2 13 here) or 17 cm off (3.7) from the right one."""
    from pipeline.data.synth import mitsuba_backend as mb
    from pipeline.data.synth import views
    from pipeline.data.synth.scene import Room
    from pipeline.ops.envmap import texel_solid_angles

    room = Room.from_json(json.loads((micro_root / "scene_0000" / "scene.json").read_text()))
    camera = room.cameras[0]
    scene = mb.load_scene(room, 6)
    cfg = views.LightingConfig(surface_stride=100, hemi_size=(2, 4), free_points=2, sphere_size=(8, 16), spp=64)
    light = views.lighting_probes(scene, camera, views.gbuffer(scene, camera, 32, 24), cfg, np.random.default_rng(0), 5)
    w2v = mb.world_from_view(camera)
    omega = texel_solid_angles(8, 16, hemisphere=False)[:, None, None]

    def z_squared(ours, ours_se, p):
        truth, truth_se = light["free_radiance"][p], light["free_stderr"][p]
        energy = (omega * (ours - truth)).sum((0, 1))
        sigma = np.sqrt(((omega * ours_se) ** 2).sum((0, 1)) + ((omega * truth_se) ** 2).sum((0, 1)))
        return np.abs(energy) / sigma, float(((ours - truth) ** 2 / (ours_se**2 + truth_se**2 + 1e-12)).mean())

    for p in range(2):
        ours, ours_se = (m[0].numpy() for m in pr.sphere_map(scene, light["free_position"][p], w2v, (8, 16), 8, 11))
        assert (ours >= 0).all() and math.isfinite(float(ours.sum()))
        energy_z, mean_z2 = z_squared(ours, ours_se, p)
        assert np.all(energy_z < 5), energy_z
        assert mean_z2 < 2.0, mean_z2
        assert z_squared(ours[:, ::-1], ours_se[:, ::-1], p)[1] > 4.0  # mirrored in azimuth: told apart
        if np.linalg.norm(light["free_position"][0] - light["free_position"][1]) > 0.1:
            assert z_squared(ours, ours_se, 1 - p)[1] > 2.0  # the other probe's light: told apart


@pytest.mark.slow
def test_bench_on_micro(micro_root, micro_shards, micro_exports, tmp_path):
    out = tmp_path / "pr.json"
    pr.main(
        [
            "--model", str(micro_exports / "light.pt"),
            "--material", str(micro_exports / "material.pt"),
            "--sizes", "4x8", "8x16",
            "--strata", "2", "--spp", "4", "--views", "2", "--edit-cases", "",
            "--out", str(out),
            "--override", "profile=micro", f"data_root={micro_root}", f"data_dir={micro_shards}", "bootstrap=20",
        ]
    )  # fmt: skip
    report = json.loads(out.read_text())
    assert report["rows"] == [*pr.EDIT_ROWS, *pr.FINE_ROWS, "centre_4x8", "centre_8x16"]
    assert out.with_suffix(".png").is_file()
    entry = report["classes"]["all"]
    assert entry["cases"] == len(report["cases"]) > 0
    assert all(math.isfinite(v) for v in entry["psnr"].values())
    centre = {f"centre_{s}_minus_{b}" for s in ("4x8", "8x16") for b in ("lightnet_fine", "nearest_probe_fine")}
    assert set(entry["differences"]) == centre | {f"{r}_minus_lightnet_fine" for r in pr.SPLIT_ROWS}
    assert 0 <= report["out_of_view_ray_share"][report["cases"][0]["label"]] <= 1
    from pipeline.tracking.results_page import bench_block

    block = "\n".join(bench_block("probe_resolution", report, "tiny"))
    assert "| lightnet_true_out |" in block and "held out of view" in block
