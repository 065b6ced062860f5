"""`bench.insertion_figure` on micro: a test view beside Mitsuba's render of the same objects, and the real
photo, each with and without shadows; Mitsuba's render carries the objects where ours does."""

import numpy as np
import pytest


def test_insertion_figure_on_micro(micro_root, micro_exports, tmp_path, mitsuba_variant, monkeypatch):
    from pipeline.bench import insertion_figure as fig
    from pipeline.models.light_net import load_light_export
    from pipeline.models.material_net import load_material_export

    material = load_material_export(micro_exports / "material.pt")
    net, _ = load_light_export(micro_exports / "light.pt")
    tv = fig.test_view(micro_root, material, net.eval(), None, 2, 8, 0)
    images = tv["images"]
    assert set(images) == {"photo", "Mitsuba", "with shadows", "without shadows"}
    assert all(np.isfinite(image).all() for image in images.values())
    assert tv["object_pixels"] > 0
    # Mitsuba's change is where the objects are: most of our objects' pixels changed in its render too
    moved = np.abs(images["Mitsuba"] - images["photo"]).max(-1) > 0
    ours = np.abs(images["without shadows"] - images["photo"]).max(-1) > 0
    assert (moved & ours).sum() >= 0.8 * ours.sum()
    for name in ("with shadows", "without shadows"):
        assert np.isfinite(tv["psnr"][name]["objects"])
    with pytest.raises(ValueError, match="--view nowhere/000"):
        fig.test_view(micro_root, material, net, "nowhere/000", 2, 8, 0)
    # the untrained MaterialNet finds no floor in the photo: three pixels low in it instead
    monkeypatch.setattr(fig, "floor_pixels", lambda normal, depth: [(44, 15), (44, 37), (44, 58)])
    rp = fig.real_photo(material, net, 2, 0, 0.1)
    assert rp["size"] == [50, 74]
    assert not np.array_equal(rp["images"]["with shadows"], rp["images"]["without shadows"])
    report = {"settings": {"spp": 2, "mitsuba_spp": 8}, "test_view": tv, "real_photo": rp}
    fig.plot(report, tmp_path / "f.png")
    assert (tmp_path / "f.png").stat().st_size > 10_000
