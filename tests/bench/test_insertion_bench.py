"""`bench.insertion` on micro: seconds per insertion with and without shadows, and the accuracy part."""

import pytest


def test_insertion_bench_times_with_and_without_shadows(micro_root, micro_exports, tmp_path):
    from pipeline.bench import insertion

    report = insertion.run(
        micro_root,
        micro_exports / "material.pt",
        micro_exports / "light.pt",
        repeats=1,
        resolutions=((24, 32),),
        speed_spp=(2,),
        accuracy_spp=(1, 2),
    )
    assert [(r["shadows"], r["spp"]) for r in report["speed"]] == [(False, 2), (True, 2)]
    assert all(r["seconds_per_insertion"] > 0 and r["object_pixels"] > 0 for r in report["speed"])
    assert [r["spp"] for r in report["accuracy"]["rows"]] == [1, 2] and report["accuracy"]["cases"] > 0
    insertion.plot(report, tmp_path / "i.png")
    assert (tmp_path / "i.png").stat().st_size > 5_000
    speed_only = insertion.run(
        micro_root, micro_exports / "material.pt", micro_exports / "light.pt", 1, ("speed",), ((24, 32),), (2,)
    )
    assert "accuracy" not in speed_only
    insertion.plot(speed_only, tmp_path / "s.png")
    with pytest.raises(ValueError, match="--only"):
        insertion.run(micro_root, micro_exports / "material.pt", micro_exports / "light.pt", parts=("fast",))
