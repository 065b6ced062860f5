"""bench.visible_light: directions land on the right texel of a box, texel means are means, and on the
micro data every source is scored with its class parts adding up."""

import math

import pytest
import torch

from pipeline.bench import visible_light as vl


def _unit_box():
    return torch.eye(3, dtype=torch.float64), -torch.ones(3, dtype=torch.float64), torch.ones(3, dtype=torch.float64)


def test_directions_land_on_their_face_and_texel():
    origin = torch.zeros(4, 3, dtype=torch.float64)
    direction = torch.tensor([[1.0, 0, 0], [0, -1, 0], [0, 0, -1], [0, 1, 0.999]], dtype=torch.float64)
    size = 4
    index = vl.box_texels(_unit_box(), origin, direction, size)
    face = index // (size * size)
    assert face.tolist() == [1, 2, 4, 3]  # right, floor, front, ceiling (ops.roombox.FACES)
    # the ceiling hit at (x 0, z 0.999): s along x in the middle, t along z at the hi edge
    st = index[3] % (size * size)
    assert (int(st) % size, int(st) // size) == (size // 2, size - 1)


def test_texel_means_average_each_cell():
    index = torch.tensor([0, 0, 2, 2, 2])
    radiance = torch.tensor([[1.0] * 3, [3.0] * 3, [2.0] * 3, [4.0] * 3, [6.0] * 3], dtype=torch.float64)
    means = vl.texel_means(index, radiance, 4)
    assert means[:, 0].tolist() == [2.0, 0.0, 4.0, 0.0]


def test_rays_meet_a_lamp_only_from_its_emitting_side_and_inside_it():
    lamps = {
        "centre": torch.tensor([[0.0, 2.0, 0.0]], dtype=torch.float64),
        "u": torch.tensor([[0.5, 0.0, 0.0]], dtype=torch.float64),
        "v": torch.tensor([[0.0, 0.0, 0.25]], dtype=torch.float64),
        "normal": torch.tensor([[0.0, -1.0, 0.0]], dtype=torch.float64),  # a ceiling panel facing down
        "emission": torch.tensor([[5.0, 4.0, 3.0]], dtype=torch.float64),
    }
    origin = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    direction = torch.tensor([[0.0, 1.0, 0.0], [0.2, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 1.0, 0.2]], dtype=torch.float64)
    radiance, met = vl.lamp_radiance(lamps, origin, direction / direction.norm(dim=-1, keepdim=True))
    # straight up: met; 0.4 m off along u (half-size 0.5): met; from above (its back): not; 0.4 m along v
    # (half-size 0.25): not
    assert met.tolist() == [True, True, False, False]
    assert radiance[0].tolist() == [5.0, 4.0, 3.0] and radiance[2].tolist() == [0.0, 0.0, 0.0]


def test_runs_on_the_micro_data(micro_shards, micro_exports, tmp_path):
    report = vl.run(str(micro_shards), split="train", views=1, light_net=micro_exports / "light.pt")
    rows = {r["source"]: r for r in report["rows"]}
    assert {"truth", "probe mean", "network"} <= set(rows)
    assert "true lamps, the rest at the probe's mean (oracle)" in rows  # the micro rooms have lamps
    ratio = report["lamp_texel_truth_over_emission_median"]
    assert ratio is None or 0.5 < ratio < 1.5  # the lamps' radiance in the probes' units
    assert all(f"true box, {n} x {n} per face (oracle)" in rows for n in vl.LADDER)
    for row in report["rows"]:
        for kind in vl.KINDS:
            if kind in row:
                parts = sum(row[kind]["classes"].values())
                assert parts == pytest.approx(row[kind]["nmse"], rel=1e-9) and math.isfinite(parts)
    # the true light on every out-of-view direction beats one constant per probe
    assert rows["truth"]["surf"]["nmse"] < rows["probe mean"]["surf"]["nmse"]
    assert all(0.0 <= v <= 1.0 for v in report["out_of_view_directions_seen"].values())
    vl.plot(report, tmp_path / "v.png")
    assert (tmp_path / "v.png").stat().st_size > 5_000


def test_missing_room_files_and_bad_counts_are_refused(micro_shards, micro_shards_without_rooms):
    with pytest.raises(ValueError, match="--views 0"):
        vl.run(str(micro_shards), split="train", views=0)
    with pytest.raises(FileNotFoundError, match="manifest.json: source_root"):
        vl.run(str(micro_shards_without_rooms), split="train", views=1)
