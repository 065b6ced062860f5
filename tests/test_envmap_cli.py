"""`invrender envmap`: the equirectangular layout (the direction math, and a mirror sphere rendered by
Mitsuba under a written map), the command end to end on PNG and EXR photos with untrained exports, and
its refusals of bad input."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from pipeline.cli import DEFAULT_LIGHT, DEFAULT_MATERIAL, main
from pipeline.data.formats.exr import read_exr, write_exr
from pipeline.data.formats.photo import read_linear
from pipeline.ops.camera import pixel_directions
from pipeline.ops.envmap import sphere_directions
from pipeline.ops.equirect import equirect_directions, equirect_texel_directions


def test_equirect_directions_follow_the_stated_layout():
    W = 6  # 3 rows: row 1 is the equator; column 4 has phi = pi/2, column 1 phi = -pi/2
    d = equirect_directions(W)
    assert d.shape == (3, 6, 3)
    np.testing.assert_allclose(d[1, 4], [1, 0, 0], atol=1e-12)  # +x: to the right
    np.testing.assert_allclose(d[1, 1], [-1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(d[0, 4], [math.sin(math.pi / 6), math.cos(math.pi / 6), 0], atol=1e-12)  # up
    for W in (2, 8, 64):
        d = equirect_directions(W)
        rows = W // 2
        assert d.shape == (rows, W, 3)
        np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1, atol=1e-12)
        r, c = np.meshgrid(np.arange(rows), np.arange(W), indexing="ij")
        theta, phi = np.pi * (r + 0.5) / rows, 2 * np.pi * ((c + 0.5) / W - 0.5)
        want = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], -1)
        np.testing.assert_allclose(d, want, atol=1e-12)
        # the two centre columns straddle forward -z; the first row is near +y, the last near -y
        centre = d[:, W // 2 - 1] + d[:, W // 2]
        assert np.all(centre[:, 0] == pytest.approx(0, abs=1e-12)) and np.all(centre[:, 2] < 0)
        if rows > 1:
            assert (d[0, :, 1] > 0).all() and (d[-1, :, 1] < 0).all()
        np.testing.assert_allclose(np.roll(d, W // 2, 1), sphere_directions(rows, W), atol=1e-12)
    near = equirect_directions(64)[15:17, 31:33].reshape(-1, 3)
    assert (near @ np.array([0, 0, -1.0])).min() > math.cos(math.radians(5))  # centre texels look along -z
    for bad in (0, 3, -2):
        with pytest.raises(ValueError):
            equirect_directions(bad)


def test_equirect_texel_directions_stay_inside_their_texel():
    W, k = 8, 3
    d = equirect_texel_directions(W, k)
    assert d.shape == (W // 2, W, k * k, 3)
    np.testing.assert_allclose(d.norm(dim=-1), 1, atol=1e-12)
    theta = torch.acos(d[..., 1].clamp(-1, 1))
    phi = torch.atan2(d[..., 0], -d[..., 2])  # (-pi, pi]
    rows = torch.arange(W // 2, dtype=d.dtype)[:, None, None]
    cols = torch.arange(W, dtype=d.dtype)[None, :, None]
    assert (theta >= rows * math.pi / (W // 2) - 1e-9).all() and (theta <= (rows + 1) * math.pi / (W // 2) + 1e-9).all()
    lo, hi = 2 * math.pi * (cols / W - 0.5), 2 * math.pi * ((cols + 1) / W - 0.5)
    assert (phi >= lo - 1e-9).all() and (phi <= hi + 1e-9).all()
    # a texel's mean sub-direction is near its centre direction (a fifth of a 5.6 degree texel at W = 64:
    # the sub-directions are spread evenly in solid angle, whose midpoint in theta is off the polar caps')
    mean = torch.nn.functional.normalize(equirect_texel_directions(64, 2).mean(2), dim=-1).numpy()
    assert (mean * equirect_directions(64)).sum(-1).min() > math.cos(math.radians(1.2))
    assert torch.equal(d, equirect_texel_directions(W, k))  # no random number


# ---------------------------------------------------------------------------------------------------
# The layout against Mitsuba: a mirror sphere in front of a camera at the origin looking along -z

FOV, SIDE, CENTRE, RADIUS = 30.0, 64, np.array([0.0, 0.0, -4.0]), 0.8
# Mitsuba's envmap reads u = atan2(x, -z) / 2 pi from its left edge: our centre column (forward -z) sits at
# u = 1/2, so its frame is ours turned half a turn about +y
MITSUBA_FROM_OURS = np.diag([-1.0, 1.0, -1.0, 1.0])


def _camera(mi, side: int, spp: int) -> dict:
    return {
        "type": "perspective",
        "fov": FOV,
        "fov_axis": "x",
        "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, -1], up=[0, 1, 0]),
        "sampler": {"type": "independent", "sample_count": spp},
        "film": {"type": "hdrfilm", "width": side, "height": side, "rfilter": {"type": "box"}},
    }


def _expected_mirror_image(k: int = 8):
    """(colour (SIDE, SIDE, 3) of a map that shows (d + 1)/2 towards every direction d, seen directly or
    in the mirror sphere, averaged over k x k points of each pixel; on (all k^2 points hit the sphere);
    off (none does); inner (on, the surface faces the camera within 60 degrees everywhere in the pixel))."""
    f = (SIDE / 2) / math.tan(math.radians(FOV) / 2)
    acc = np.zeros((SIDE, SIDE, 3))
    hits = np.zeros((SIDE, SIDE), int)
    facing = np.ones((SIDE, SIDE))
    for a in range(k):
        for b in range(k):
            i = np.arange(SIDE)[:, None] + (a + 0.5) / k
            j = np.arange(SIDE)[None, :] + (b + 0.5) / k
            d = np.stack(np.broadcast_arrays((j - SIDE / 2) / f, -(i - SIDE / 2) / f, -1.0), -1)
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
            half_b = d @ CENTRE
            disc = half_b**2 - (CENTRE @ CENTRE - RADIUS**2)
            hit = disc > 0
            n = (d * (half_b - np.sqrt(np.maximum(disc, 0)))[..., None] - CENTRE) / RADIUS
            cos = -(d * n).sum(-1)
            r = d + 2 * cos[..., None] * n  # mirror reflection
            acc += np.where(hit[..., None], (r + 1) / 2, (d + 1) / 2)
            hits += hit
            facing = np.minimum(facing, np.where(hit, cos, 0))
    on, off = hits == k * k, hits == 0
    return acc / (k * k), on, off, on & (facing > 0.5)


@pytest.mark.slow
def test_a_written_map_lights_a_mitsuba_mirror_sphere_as_its_layout_says(mitsuba_variant, tmp_path):
    """The map is written to EXR and read back as `invrender envmap` writes it, each texel holding
    (d + 1)/2 of its centre direction d (`equirect_directions`). A mirror sphere straight ahead must show
    (r + 1)/2 of the reflected direction r at every pixel: the centre reflects +z back at the camera, its
    right side +x, its top +y; the background shows the forward directions themselves."""
    import mitsuba as mi

    W = 64
    write_exr(tmp_path / "map.exr", (equirect_directions(W) + 1) / 2)
    envmap = read_exr(tmp_path / "map.exr")
    assert envmap.shape == (W // 2, W, 3) and envmap.dtype == np.float32
    # the camera first: a small lamp up and to the right in view space shows up and to the right
    lamp = np.array([1.0, 0.6, -6.0])
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "direct"},
            "lamp": {
                "type": "sphere",
                "center": lamp.tolist(),
                "radius": 0.15,
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}},
            },
        }
    )
    img = np.array(mi.render(scene, sensor=mi.load_dict(_camera(mi, 32, 16)), spp=16, seed=0))[..., 0]
    assert img[:16, 16:].sum() > 0.99 * img.sum() > 0  # top right
    # where the project's pixel convention (ops.camera: column right = +x, row 0 at the top) puts it
    d = pixel_directions(32, 32, FOV, dtype=torch.float64).numpy()
    row, col = np.unravel_index(np.argmax(d @ lamp / np.linalg.norm(d, axis=-1)), img.shape)
    rows, cols = np.indices(img.shape)
    centroid = np.array([(img * rows).sum(), (img * cols).sum()]) / img.sum()
    np.testing.assert_allclose(centroid, [row, col], atol=1.0)

    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": 3},
            "env": {
                "type": "envmap",
                "bitmap": mi.Bitmap(np.ascontiguousarray(envmap)),
                "to_world": mi.ScalarTransform4f(MITSUBA_FROM_OURS),
            },
            "ball": {
                "type": "sphere",
                "center": CENTRE.tolist(),
                "radius": RADIUS,
                "bsdf": {"type": "conductor", "material": "none"},
            },
        }
    )
    img = np.array(mi.render(scene, sensor=mi.load_dict(_camera(mi, SIDE, 16)), spp=16, seed=0))[..., :3]
    expected, on, off, inner = _expected_mirror_image()
    assert inner.sum() > 1000 and off.sum() > 1500
    err = np.abs(img - expected).max(-1)
    # Mitsuba's envmap puts its first and last rows at the poles (theta = pi r / (rows - 1)), ours at
    # texel centres: up to half a texel apart near the poles (~0.01 here). A map off by one column
    # gives 0.036 on the sphere, any flip or turn of the layout 0.3 or more.
    assert err[inner].mean() < 0.015 and err[inner].max() < 0.06, (err[inner].mean(), err[inner].max())
    assert err[off].mean() < 0.006, err[off].mean()
    # near the horizon the two conventions meet: texel centres in azimuth agree to a small fraction of a
    # texel (half a texel off would be ~0.02)
    band = off.copy()
    band[:28] = band[36:] = False
    assert band.sum() > 30 and err[band].max() < 0.006, err[band].max()
    # named spots: the middle reflects +z (blue), 45 degrees to the right +x (red), above +y (green)
    c = SIDE // 2
    f = (SIDE / 2) / math.tan(math.radians(FOV) / 2)
    s = RADIUS * math.sqrt(0.5)
    off45 = round(f * s / (-CENTRE[2] - s))  # pixels from the centre to where the normal is at 45 degrees
    for (row, col), axis in (((c, c), 2), ((c, c + off45), 0), ((c - off45, c), 1)):
        rgb = img[row - 1 : row + 1, col - 1 : col + 1].mean((0, 1))
        assert np.argmax(rgb) == axis and rgb[axis] > 0.9, ((row, col), rgb)


# ---------------------------------------------------------------------------------------------------
# The command


@pytest.fixture(scope="module")
def photos(tmp_path_factory, micro_exports):
    """A 64x48 PNG photo, an EXR of its linear pixels, the same at twice the exposure, both exports."""
    d = tmp_path_factory.mktemp("envmap")
    rng = np.random.default_rng(0)
    Image.fromarray(rng.uniform(20, 235, size=(48, 64, 3)).astype(np.uint8)).save(d / "photo.png")
    linear = read_linear(d / "photo.png")
    write_exr(d / "photo.exr", linear)
    write_exr(d / "bright.exr", 2 * linear)
    models = ["--material-net", str(micro_exports / "material.pt"), "--light-net", str(micro_exports / "light.pt")]
    return {"dir": d, "models": models, "exports": micro_exports}


def _envmap(photo, out, photos, *extra) -> np.ndarray:
    assert main(["envmap", str(photo), "--at", "20,30", "--out", str(out), *photos["models"], *extra]) == 0
    return read_exr(out)


@pytest.mark.slow
def test_envmap_writes_the_map_in_the_photos_linear_units(photos, tmp_path, capsys):
    d = photos["dir"]
    png = _envmap(d / "photo.png", tmp_path / "png.exr", photos, "--width", "16")
    assert capsys.readouterr().out.strip() == str(tmp_path / "png.exr")
    assert png.shape == (8, 16, 3) and png.dtype == np.float32
    assert np.isfinite(png).all() and (png >= 0).all() and png.max() > 0
    # a PNG is decoded through the sRGB curve: its map is the map of an EXR of its linear pixels
    exr = _envmap(d / "photo.exr", tmp_path / "exr.exr", photos, "--width", "16")
    np.testing.assert_array_equal(png, exr)
    # LightNet predicts in units of the image mean: twice the exposure, twice the radiance
    bright = _envmap(d / "bright.exr", tmp_path / "bright.exr", photos, "--width", "16")
    np.testing.assert_allclose(bright, 2 * exr, rtol=1e-5, atol=1e-7)
    # the same call writes the same file; the default offset is 5 cm
    again = _envmap(d / "photo.exr", tmp_path / "again.exr", photos, "--width", "16", "--offset", "0.05")
    assert (tmp_path / "again.exr").read_bytes() == (tmp_path / "exr.exr").read_bytes()
    assert not np.array_equal(again[:, :8], again[:, 8:])  # the map varies with direction
    touching = _envmap(d / "photo.exr", tmp_path / "touching.exr", photos, "--width", "16", "--offset", "0")
    assert np.isfinite(touching).all() and not np.array_equal(touching, exr)


def test_envmap_defaults(monkeypatch, capsys):
    """W 64, a 5 cm offset and the stages' exports unless told otherwise."""
    import pipeline.cli as cli

    calls = []
    monkeypatch.setattr(cli, "envmap_at", lambda *args, **kwargs: calls.append((args, kwargs)) or Path("m.exr"))
    assert main(["envmap", "p.png", "--at", "1,2", "--out", "m.exr"]) == 0
    assert calls == [
        (("p.png", "1,2", "m.exr", 64, 0.05), {"material_path": DEFAULT_MATERIAL, "light_path": DEFAULT_LIGHT})
    ]
    assert DEFAULT_MATERIAL == str(Path("outputs") / "train_material" / "model.pt")
    assert DEFAULT_LIGHT == str(Path("outputs") / "train_lighting" / "model.pt")


def _refused(argv: list[str], capsys, folder) -> str:
    """Exit status 2, one `error: ` line on stderr, no traceback, nothing written into `folder`."""
    before = sorted(folder.rglob("*"))
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's usage errors
        code = exc.code
    err = capsys.readouterr().err.strip()
    assert code == 2, (argv, err)
    assert len(err.splitlines()) == 1 and err.startswith("error: ") and "Traceback" not in err, err
    assert sorted(folder.rglob("*")) == before, argv
    return err


@pytest.mark.slow
def test_envmap_refuses_bad_input_in_one_line_naming_it(photos, tmp_path, capsys, monkeypatch):
    d = photos["dir"]
    out = tmp_path / "out"
    out.mkdir()
    (tmp_path / "corrupt.png").write_bytes((d / "photo.png").read_bytes()[:100])
    (tmp_path / "corrupt.exr").write_bytes(b"not an exr at all")
    (out / "taken.exr").mkdir()
    target = str(out / "map.exr")
    photo = str(d / "photo.png")
    models = photos["models"]

    def run(*args):
        return ["envmap", *args, *models]

    cases = {
        "missing.png": run(str(tmp_path / "missing.png"), "--at", "3,3", "--out", target),
        "corrupt.png": run(str(tmp_path / "corrupt.png"), "--at", "3,3", "--out", target),
        "corrupt.exr": run(str(tmp_path / "corrupt.exr"), "--at", "3,3", "--out", target),
        "--at": run(photo, "--at", "48,3", "--out", target),
        "--at ": run(photo, "--at", "3,64", "--out", target),
        "--at  ": run(photo, "--at", "-1,3", "--out", target),
        "--at   ": run(photo, "--at", "3", "--out", target),
        "--at    ": run(photo, "--at", "a,b", "--out", target),
        "--at     ": run(photo, "--at", "1.5,3", "--out", target),
        "--width": run(photo, "--at", "3,3", "--out", target, "--width", "0"),
        "--width ": run(photo, "--at", "3,3", "--out", target, "--width", "-4"),
        "--width  ": run(photo, "--at", "3,3", "--out", target, "--width", "7"),
        "--width   ": run(photo, "--at", "3,3", "--out", target, "--width", "abc"),
        "--width    ": run(photo, "--at", "3,3", "--out", target, "--width", "2.5"),
        "--offset": run(photo, "--at", "3,3", "--out", target, "--offset", "-0.1"),
        "--offset ": run(photo, "--at", "3,3", "--out", target, "--offset", "nan"),
        "--offset  ": run(photo, "--at", "3,3", "--out", target, "--offset", "inf"),
        "--offset   ": run(photo, "--at", "3,3", "--out", target, "--offset", "x"),
        "--out": run(photo, "--at", "3,3", "--out", str(out / "map.png")),
        "--out ": run(photo, "--at", "3,3", "--out", str(tmp_path / "nowhere" / "map.exr")),
        "--out  ": run(photo, "--at", "3,3", "--out", str(out / "taken.exr")),
        "--out   ": run(photo, "--at", "3,3", "--out", str(out / "map")),
        "missing.pt": ["envmap", photo, "--at", "3,3", "--out", target, "--light-net", str(tmp_path / "missing.pt")]
        + ["--material-net", models[1]],
        "missing.pt ": ["envmap", photo, "--at", "3,3", "--out", target, "--material-net", str(tmp_path / "missing.pt")]
        + ["--light-net", models[3]],
        "light.pt": ["envmap", photo, "--at", "3,3", "--out", target, "--material-net", models[3]]
        + ["--light-net", models[3]],
    }
    for needle, argv in cases.items():
        err = _refused(argv, capsys, tmp_path)
        assert needle.strip() in err, (needle, err)
    # the stages' exports by default, named when they are missing
    monkeypatch.chdir(tmp_path)
    err = _refused(["envmap", photo, "--at", "3,3", "--out", target], capsys, tmp_path)
    assert DEFAULT_MATERIAL in err, err
    err = _refused(["envmap", photo, "--at", "3,3", "--out", target, "--material-net", models[1]], capsys, tmp_path)
    assert DEFAULT_LIGHT in err, err


@pytest.mark.slow
def test_envmap_refuses_a_pixel_without_a_predicted_surface(photos, tmp_path, capsys, monkeypatch):
    """MaterialNet's depth is not finite at the pixel (as gbuffers_from_maps reads it: no surface)."""
    import pipeline.models.insertion as insertion

    predict = insertion.predict_maps

    def holed(*args, **kwargs):
        maps = predict(*args, **kwargs)
        maps["depth"][5, 7] = np.inf
        return maps

    monkeypatch.setattr(insertion, "predict_maps", holed)
    argv = ["envmap", str(photos["dir"] / "photo.png"), "--out", str(tmp_path / "m.exr"), "--width", "16"]
    argv += photos["models"]
    err = _refused([*argv, "--at", "5,7"], capsys, tmp_path)
    assert "--at 5,7" in err and "no valid surface" in err, err
    assert main([*argv, "--at", "5,8"]) == 0  # its neighbour has one
