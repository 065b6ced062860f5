"""bench.lamp_placement: lamp cover on a ceiling grid is measured where the lamp is, distributions are
shares, and the bench trains, keeps its best validation epoch and scores every placement on micro data."""

import math

import pytest
import torch

from pipeline.bench import lamp_placement as lp


def test_a_lamp_covers_the_cells_it_lies_over():
    box = (torch.eye(3, dtype=torch.float64), torch.tensor([-2.0, 0.0, -2.0]), torch.tensor([2.0, 3.0, 2.0]))
    lamps = {  # one panel 1 m x 1 m centred over the ceiling's cell (row 3, column 0) of a 4 x 4 grid
        "centre": torch.tensor([[-1.5, 2.999, 1.5]], dtype=torch.float64),
        "u": torch.tensor([[0.5, 0.0, 0.0]], dtype=torch.float64),
        "v": torch.tensor([[0.0, 0.0, 0.5]], dtype=torch.float64),
        "normal": torch.tensor([[0.0, -1.0, 0.0]], dtype=torch.float64),
        "emission": torch.tensor([[10.0, 8.0, 6.0]], dtype=torch.float64),
    }
    cells = lp.ceiling_lamps(lamps, box, 4)
    assert cells[3, 0].tolist() == [10.0, 8.0, 6.0]  # rows along z, columns along x
    assert float(cells.sum()) == pytest.approx(24.0)  # nothing elsewhere
    share = lp.distribution(cells[None])
    assert float(share[0, 12]) == pytest.approx(1.0)
    empty = lp.distribution(torch.zeros(1, 4, 4, 3, dtype=torch.float64))
    assert torch.allclose(empty, torch.full_like(empty, 1 / 16))  # no lamp: a uniform share
    assert lp.ceiling_lamps(None, box, 4).abs().sum() == 0


def test_runs_on_the_micro_data(micro_shards, tmp_path):
    report = lp.run(str(micro_shards), grid=2, height=8, epochs=2, seeds=1)
    name = "from the photo, seed 0"
    assert report["kept_epoch"][name] in (1, 2) and len(report["validation_cross_entropy"][name]) == 2
    rows = report["summary"]["each placement"]
    names = [row["placement"] for row in rows]
    assert names == [
        "true lamps",
        "true placement",
        "uniform over the ceiling",
        "training rooms' mean",
        "from the photo, seed 0",
    ]
    for row in rows:
        assert math.isfinite(row["surface nMSE"])
    # a paired difference is the difference of the pooled nMSEs (same views, same energy)
    nmse = {row["placement"]: row["surface nMSE"] for row in rows}
    d = report["differences"]["surf: uniform over the ceiling - training rooms' mean"]
    expected = nmse["uniform over the ceiling"] - nmse["training rooms' mean"]
    assert d["diff"] == pytest.approx(expected, rel=1e-6, abs=1e-9)
    uniform = report["placement"]["uniform over the ceiling"]
    assert uniform["cross_entropy"] == pytest.approx(math.log(4))  # 4 cells
    lp.plot(report, tmp_path / "l.png")
    assert (tmp_path / "l.png").stat().st_size > 5_000
    with pytest.raises(ValueError, match="--seeds 0"):
        lp.run(str(micro_shards), seeds=0)


def test_extra_maps_are_mirrored_with_the_photo_and_reach_the_head():
    cells = torch.arange(2 * 2 * 9, dtype=torch.float32).view(2, 18)  # two views, two 3 x 3 maps each
    flipped = lp.mirrored_cells(cells, 3)
    assert flipped[0, :3].tolist() == [2.0, 1.0, 0.0] and flipped[0, 9:12].tolist() == [11.0, 10.0, 9.0]
    assert torch.equal(lp.mirrored_cells(flipped, 3), cells)
    net = lp.PlacementNet(3, width=8, extra=18)
    x = torch.rand(2, 3, 8, 10)
    assert net(x, cells).shape == (2, 9)
    assert not torch.allclose(net(x, cells), net(x, torch.zeros_like(cells)))  # the extra input is used


def test_training_stops_after_its_patience():
    """With `patience` p the run ends p epochs after its best validation epoch (or at the last epoch),
    and the kept net is that best epoch's."""
    g = torch.Generator().manual_seed(0)
    x, x_val = torch.rand(8, 3, 8, 10, generator=g), torch.rand(8, 3, 8, 10, generator=g)
    t = torch.softmax(torch.randn(8, 4, generator=g) * 3, -1)
    t_val = torch.softmax(torch.randn(8, 4, generator=g) * 3, -1)  # unrelated: validation soon rises
    net, curve = lp.train(x, t, x_val, t_val, 2, 40, 0, width=4, patience=2)
    best = min(range(len(curve)), key=curve.__getitem__)
    assert len(curve) == 40 or len(curve) == best + 3
    with torch.no_grad():
        kept = -(t_val * torch.log_softmax(net(x_val), -1)).sum(1).mean()
    assert float(kept) == pytest.approx(curve[best], rel=1e-5)
    _, full = lp.train(x, t, x_val, t_val, 2, 10, 0, width=4)
    assert len(full) == 10


def test_calibration_undoes_overconfidence():
    """Logits that rank the right cell first but ten times too sharply are judged at a temperature near 10,
    never worse than at 1; a calibrated net's logits are divided by its temperature."""
    g = torch.Generator().manual_seed(1)
    true_logits = torch.randn(200, 6, generator=g)
    target = torch.softmax(true_logits, -1)
    score, temperature = lp.calibrated_cross_entropy(true_logits * 10, target)
    at_one = float(-(target * torch.log_softmax(true_logits * 10, -1)).sum(1).mean())
    assert score < at_one and 7 < temperature < 14
    exact = float(-(target * torch.log_softmax(true_logits, -1)).sum(1).mean())
    assert score == pytest.approx(exact, rel=0.01)
    net = lp.PlacementNet(2, width=8, kind="deep").eval()
    x = torch.rand(3, 3, 16, 20)
    raw = net(x)
    net.temperature.fill_(4.0)
    assert raw.shape == (3, 4) and torch.allclose(net(x), raw / 4)
    with pytest.raises(ValueError, match="--net 'wide'"):
        lp.PlacementNet(2, kind="wide")


def test_the_deep_net_calibrated_on_the_micro_data(micro_shards):
    report = lp.run(str(micro_shards), grid=2, height=16, epochs=2, seeds=1, width=8, net_kind="deep", calibrate=True)
    name = "from the photo, seed 0"
    assert report["net"] == "deep" and report["calibrated"] is True
    assert float(lp.TEMPERATURES[0]) <= report["temperature"][name] <= float(lp.TEMPERATURES[-1])
    assert math.isfinite(report["light"][name]["surf"]["nmse"])
    with pytest.raises(ValueError, match="--net"):
        lp.run(str(micro_shards), net_kind="wide")
