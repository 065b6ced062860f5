"""bench.blend_floor: its blend is LightNet's rule, its network sources recombine to LightNet's own answer,
and on the micro data the class contributions add up to each rule's error."""

import math

import pytest
import torch

from pipeline.bench import blend_floor as bf


def test_blend_rule_on_known_rays():
    local = torch.tensor([[1.0, 1, 1], [2.0, 2, 2], [3.0, 3, 3], [4.0, 4, 4]], dtype=torch.float64)
    out = torch.full((4, 3), 10.0, dtype=torch.float64)
    hit = torch.tensor([False, True, True, True])
    gap = torch.tensor([0.0, 0.0, 0.05, 1.0], dtype=torch.float64)
    u = torch.tanh(10 * gap)
    # paper (t = 0): a miss takes the out-of-view source, a confident hit (gap 0) the local one, the rest mix
    got = bf.blended(local, out, hit, gap, 10.0, 0.0)
    assert torch.equal(got[0], out[0]) and torch.equal(got[1], local[1])
    assert torch.allclose(got[2], (1 - u[2]) * local[2] + u[2] * out[2])
    # t = 0.9: the uncertain hit (u = 0.46) keeps its local answer, the far one (u ~ 1) mixes
    got = bf.blended(local, out, hit, gap, 10.0, 0.9)
    assert torch.equal(got[2], local[2]) and torch.allclose(got[3], (1 - u[3]) * local[3] + u[3] * out[3])
    assert torch.equal(got[0], out[0])
    # k = 0: every hit answered locally
    assert torch.equal(bf.blended(local, out, hit, gap, 0.0, 0.0)[1:], local[1:])


def test_rules_are_parsed_or_refused():
    assert bf.parse_rule("sharp:30:0.5") == ("sharp", 30.0, 0.5)
    for bad in ("sharp", "sharp:x:0", "sharp:10:2", "sharp:-1:0"):
        with pytest.raises(SystemExit, match="--rule"):
            bf.parse_rule(bad)


def test_network_sources_recombine_to_lightnet(micro_shards, micro_exports):
    """The trained network's two sources, blended by the bench's rule, give the network's own mixed answer
    (out_threshold 0: both ways query every ray, so the volume's random draws are the same)."""
    from torch.utils.data import DataLoader, Subset

    from pipeline.data.datasets import ShardDataset, collate_views

    system = bf.network_system(micro_exports / "light.pt")
    system.net.out_threshold = 0.0
    train = ShardDataset(str(micro_shards), "train", lighting=True)
    batch = next(iter(DataLoader(Subset(train, [0]), 1, collate_fn=collate_views)))
    gb = system.gbuffers(batch)
    r = bf.view_rays(batch, gb, "surf")
    assert r is not None, "the micro training view has surface probes"
    sources = bf.network_sources(system, batch, gb, r)
    assert system.net.mode == "mixed"  # restored
    with torch.no_grad():
        ctx = system.net.encode(batch["im"], gb["depth"], system.fov(batch), normal=gb["normal"])
        b = torch.zeros(len(r["direction"]), dtype=torch.long)
        own = system.net(ctx, gb, system.fov(batch), r["origin"], r["direction"], b, system.eval_generator())
    mine = bf.blended(sources["local"], sources["out"], r["hit"], r["gap"], system.net.k, 0.0)
    assert torch.allclose(mine, own["radiance"].double(), rtol=1e-5, atol=1e-6)


def test_runs_on_the_micro_data(micro_shards, micro_exports, tmp_path):
    report = bf.run(str(micro_shards), views=1)
    assert [r["rule"] for r in report["rules"]] == [name for name, _, _ in bf.DEFAULT_RULES]
    for row in report["rules"]:
        for kind in bf.KINDS:
            if kind not in row:
                continue
            parts = sum(c["nmse_contribution"] for c in row[kind]["classes"].values())
            assert parts == pytest.approx(row[kind]["nmse"], rel=1e-9) and math.isfinite(parts)
    # with the true light on every out-of-view direction, misses are exact wherever no direction hit
    assert report["summary"][0]["surface nMSE"] is not None
    net = bf.run(str(micro_shards), views=1, light_net=micro_exports / "light.pt")
    assert [r["rule"] for r in net["rules"]] == [f"local {a}, out {b}" for a, b in bf.SOURCE_PAIRS]
    bf.plot(net, tmp_path / "b.png")
    assert (tmp_path / "b.png").stat().st_size > 5_000


def test_too_many_views_are_refused(micro_shards):
    with pytest.raises(ValueError, match="--views 10000"):
        bf.run(str(micro_shards), views=10000)


def test_the_results_page_renders_a_list_summary_and_refuses_a_scalar():
    from pipeline.tracking.results_page import bench_block

    rows = [{"rule": "k 10, t 0 (paper)", "surface nMSE": 0.0068}, {"rule": "hits local only", "surface nMSE": 0.143}]
    block = "\n".join(bench_block("blend_floor", {"summary": rows}, "tiny"))
    assert "| k 10, t 0 (paper) | 0.0068 |" in block and "| hits local only | 0.143 |" in block
    with pytest.raises(ValueError, match="reports/bench/blend_floor.json: its summary is a float"):
        bench_block("blend_floor", {"summary": 0.5}, "tiny")


def test_continued_hits_take_image_pixels_or_nothing(micro_shards):
    from torch.utils.data import DataLoader, Subset

    from pipeline.data.datasets import ShardDataset, collate_views

    train = ShardDataset(str(micro_shards), "train", lighting=True)
    batch = next(iter(DataLoader(Subset(train, [0]), 1, collate_fn=collate_views)))
    gb = bf.ground_truth_gbuffers(batch)
    r = bf.view_rays(batch, gb, "surf")
    got = bf.continued_local(batch, gb, r, bf.LABEL_K)
    uncertain = r["hit"] & (torch.tanh(bf.LABEL_K * r["gap"]) >= 0.5)
    answered = torch.isfinite(got[:, 0])
    assert not (answered & ~uncertain).any()  # only uncertain hits are marched on
    pixels = batch["im"][0].clamp(min=0).permute(1, 2, 0).reshape(-1, 3).double()
    for value in got[answered][:20]:  # each answer is one of the image's own pixels
        assert (pixels - value).abs().sum(1).min() == 0
    report = bf.run(str(micro_shards), views=1, continue_behind=True)
    names = [row["rule"] for row in report["rules"]]
    assert names[-2:] == ["k 10, t 0.9, out probe mean", "k 10, t 0.9, out probe mean, uncertain hits continued"]
    share = report["uncertain_hits_continued_to_a_confident_pixel"]
    assert share is None or 0.0 <= share <= 1.0
