"""Bad input at every command-line entry point (`invrender predict / insert / edit / whdr / validate`):
corrupt, truncated and empty files, wrong channel counts, NaN/inf pixels, images too small or too
large, wrong or damaged model exports (a pickle payload among them), masks of the wrong size, pixels off
the image and output folders that cannot be written. Every case must end with exit status 2 (1 for
`validate`, which reports rejected views), one line on stderr naming the file or argument, no traceback,
and no file written. Hypothesis draws the corruptions; each entry point's cases are counted in
`CASES_TRIED` and printed at the end of the module."""

from __future__ import annotations

import json
import pickle
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from pipeline.cli import main
from pipeline.data.formats.exr import write_exr

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("fuzz_entry_points")]
CASES_TRIED: Counter = Counter()
FUZZ = settings(max_examples=12, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)


@pytest.fixture(scope="module")
def good(tmp_path_factory, micro_exports):
    """Valid inputs: a 64x48 PNG, JPG and EXR photo, a mask, IIW judgements, both exports."""
    d = tmp_path_factory.mktemp("good")
    rng = np.random.default_rng(0)
    hdr = (rng.uniform(0.05, 2.0, size=(48, 64, 3))).astype(np.float32)
    write_exr(d / "photo.exr", hdr)
    srgb = (rng.uniform(0, 255, size=(48, 64, 3))).astype(np.uint8)
    Image.fromarray(srgb).save(d / "photo.png")
    Image.fromarray(srgb).save(d / "photo.jpg")
    mask = np.zeros((48, 64), np.uint8)
    mask[10:20, 10:30] = 255
    Image.fromarray(mask).save(d / "mask.png")
    points = [{"id": i, "x": 0.1 + 0.2 * i, "y": 0.5, "opaque": True} for i in range(4)]
    comps = [{"id": 0, "point1": 0, "point2": 1, "darker": "1", "darker_score": 0.8}]
    (d / "judgements.json").write_text(json.dumps({"intrinsic_points": points, "intrinsic_comparisons": comps}))
    return {"dir": d, "material": micro_exports / "material.pt", "light": micro_exports / "light.pt"}


def _run(argv: list[str], capsys, out_dir: Path, name: str, status: int = 2) -> str:
    """Run the CLI; check the status, one error line naming something, no traceback, nothing written."""
    before = sorted(out_dir.rglob("*")) if out_dir.exists() else []
    CASES_TRIED[name.strip()] += 1
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's usage errors
        code = exc.code
    assert code == status, argv
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err, err
    if status == 2:
        assert len(err.splitlines()) == 1 and err.startswith("error: "), err
    after = sorted(out_dir.rglob("*")) if out_dir.exists() else []
    assert after == before, f"{name}: wrote {set(after) - set(before)}"
    return err


def _corrupt(data: bytes, how: str, at: float, flips: list[int]) -> bytes:
    if how == "empty":
        return b""
    if how == "truncate":
        return data[: int(at * len(data))]
    buf = bytearray(data)
    for k in flips:  # overwrite bytes past the first 8 (keep magic numbers, hit the structure)
        buf[8 + k % max(1, len(buf) - 8)] ^= 0xA5
    return bytes(buf)


corruptions = st.tuples(
    st.sampled_from(["empty", "truncate", "flip"]),
    st.floats(0.0, 0.95),
    st.lists(st.integers(0, 10_000), min_size=1, max_size=8),
)


def _photo_cmds(photo: str, good: dict, out: Path) -> dict[str, list[str]]:
    m, li = str(good["material"]), str(good["light"])
    mask = str(good["dir"] / "mask.png")
    return {
        "predict": ["predict", photo, "--out", str(out), "--checkpoint", m],
        "insert": [
            "insert",
            photo,
            "--at",
            "20,20",
            "--out",
            str(out / "x.png"),
            "--material-net",
            m,
            "--light-net",
            li,
        ],
        "edit": ["edit", photo, "--mask", mask, "--metallic", "1", "--out", str(out / "x.png"), "--material-net", m]
        + ["--light-net", li],
    }


@pytest.mark.parametrize("suffix", [".png", ".jpg", ".exr"])
@FUZZ
@given(c=corruptions)
def test_corrupt_photos_are_refused(good, tmp_path_factory, capsys, suffix, c):
    d = tmp_path_factory.mktemp("corrupt")
    photo = d / f"photo{suffix}"
    data = _corrupt((good["dir"] / f"photo{suffix}").read_bytes(), *c)
    photo.write_bytes(data)
    out = d / "out"
    out.mkdir()
    for name, argv in _photo_cmds(str(photo), good, out).items():
        try:
            err = _run(argv, capsys, out, name)
        except AssertionError:
            # a flip that leaves a decodable image is a valid (if odd) photo: the command may succeed
            shutil.rmtree(out)
            out.mkdir()
            continue
        assert photo.name in err, err


@FUZZ
@given(
    h=st.sampled_from([1, 2, 5, 48]),
    w=st.sampled_from([1, 3, 64]),
    channels=st.sampled_from([2, 5]),
    bad=st.sampled_from(["nan", "inf", "-inf", "negative", "none"]),
)
def test_bad_exr_pixels_and_shapes_are_refused(good, tmp_path_factory, capsys, h, w, channels, bad):
    d = tmp_path_factory.mktemp("exr")
    rng = np.random.default_rng(h * 100 + w)
    img = rng.uniform(0.1, 1.0, size=(h, w, 3)).astype(np.float32)
    if bad != "none":
        img[0, 0, 0] = {"nan": np.nan, "inf": np.inf, "-inf": -np.inf, "negative": -1.0}[bad]
    elif h >= 8 and w >= 8:  # a valid RGB EXR: make the channel count the fault
        import OpenEXR

        names = "RGBAZ"[:channels] if channels != 2 else "YA"
        chans = {n: np.ascontiguousarray(rng.uniform(0.1, 1, size=(h, w)), np.float32) for n in names}
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        with OpenEXR.File(header, chans) as f:
            f.write(str(d / "p.exr"))
    if not (d / "p.exr").exists():
        write_exr(d / "p.exr", img)
    out = d / "out"
    out.mkdir()
    for name, argv in _photo_cmds(str(d / "p.exr"), good, out).items():
        try:
            err = _run(argv, capsys, out, name)
        except AssertionError:
            if bad == "none" and channels == 5 and h >= 8 and w >= 8:
                shutil.rmtree(out)  # RGBAZ: RGB is read, a valid photo
                out.mkdir()
                continue
            raise
        assert "p.exr" in err, err


def test_images_too_small_or_too_large_are_refused_before_decoding(good, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    Image.fromarray(np.zeros((1, 1, 3), np.uint8)).save(tmp_path / "tiny.png")
    Image.fromarray(np.zeros((8000, 8000), np.uint8)).save(tmp_path / "huge.png")  # 8-bit grey: small file
    for photo in ("tiny.png", "huge.png"):
        for name, argv in _photo_cmds(str(tmp_path / photo), good, out).items():
            err = _run(argv, capsys, out, name)
            assert photo in err and "pixels a side" in err, err


def test_wrong_truncated_and_malicious_exports_are_refused(good, tmp_path, capsys):
    """A LightNet export where a MaterialNet one is wanted (and the reverse), a truncated export, random
    bytes, and a pickle whose loading would run code: refused, and the code never runs."""
    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return (Path.touch, (marker,))

    (tmp_path / "evil.pt").write_bytes(pickle.dumps({"format": "invrender-material", "x": Payload()}))
    data = good["material"].read_bytes()
    (tmp_path / "truncated.pt").write_bytes(data[: len(data) // 2])
    (tmp_path / "noise.pt").write_bytes(np.random.default_rng(0).bytes(4096))
    out = tmp_path / "out"
    out.mkdir()
    photo = str(good["dir"] / "photo.png")
    m, li = str(good["material"]), str(good["light"])
    bad = {
        "light.pt": str(good["light"]),
        "evil.pt": str(tmp_path / "evil.pt"),
        "truncated.pt": str(tmp_path / "truncated.pt"),
        "noise.pt": str(tmp_path / "noise.pt"),
        "missing.pt": str(tmp_path / "missing.pt"),
    }
    for needle, path in bad.items():
        runs = {
            "predict": ["predict", photo, "--out", str(out), "--checkpoint", path],
            "insert": ["insert", photo, "--at", "5,5", "--out", str(out / "i.png"), "--material-net", path],
            "edit": ["edit", photo, "--mask", str(good["dir"] / "mask.png"), "--roughness", "0.2"]
            + ["--out", str(out / "e.png"), "--material-net", m, "--light-net", path if needle != "light.pt" else m],
        }
        for name, argv in runs.items():
            err = _run(argv, capsys, out, name)
            assert (needle if not (name == "edit" and needle == "light.pt") else "material.pt") in err, err
    assert not marker.exists(), "unpickling ran the payload"
    insert = ["insert", photo, "--out", str(out / "i.png"), "--material-net", m, "--light-net", li]
    for at in ("48,3", "3,64", "-1,3", "a,b", "3", "1e9,2", "12.7,3"):
        assert "--at" in _run([*insert, "--at", at], capsys, out, "insert")


@FUZZ
@given(h=st.integers(1, 100), w=st.integers(1, 100))
def test_masks_of_the_wrong_size_are_refused(good, tmp_path_factory, capsys, h, w):
    if (h, w) == (48, 64):
        return
    d = tmp_path_factory.mktemp("mask")
    Image.fromarray(np.full((h, w), 255, np.uint8)).save(d / "m.png")
    out = d / "out"
    out.mkdir()
    argv = ["edit", str(good["dir"] / "photo.png"), "--mask", str(d / "m.png"), "--albedo", "0.5,0.5,0.5"]
    argv += ["--out", str(out / "e.png"), "--material-net", str(good["material"]), "--light-net", str(good["light"])]
    assert "--mask" in _run(argv, capsys, out, "edit")


def test_unwritable_outputs_are_refused(good, tmp_path, capsys):
    (tmp_path / "file").write_text("a file, not a folder")
    (tmp_path / "taken.exr").mkdir()  # insert would write taken.png and taken.exr: one is a folder
    photo = str(good["dir"] / "photo.png")
    m, li = str(good["material"]), str(good["light"])
    for name, argv in {
        "predict": ["predict", photo, "--out", str(tmp_path / "file" / "sub"), "--checkpoint", m],
        "insert": ["insert", photo, "--at", "5,5", "--out", str(tmp_path / "file" / "x.png"), "--material-net", m]
        + ["--light-net", li],
        "edit": ["edit", photo, "--mask", str(good["dir"] / "mask.png"), "--metallic", "1"]
        + ["--out", str(tmp_path / "nowhere" / "x.exr"), "--material-net", m, "--light-net", li],
        "insert ": ["insert", photo, "--at", "5,5", "--out", str(tmp_path / "taken.png"), "--material-net", m]
        + ["--light-net", li],
    }.items():
        assert "--out" in _run(argv, capsys, tmp_path, name)


@FUZZ
@given(c=corruptions, target=st.sampled_from(["png", "json"]))
def test_whdr_refuses_corrupt_photos_and_judgements(good, tmp_path_factory, capsys, c, target):
    d = tmp_path_factory.mktemp("whdr")
    shutil.copy(good["dir"] / "photo.png", d / "r.png")
    shutil.copy(good["dir"] / "judgements.json", d / "r.json")
    path = d / f"r.{target}"
    path.write_bytes(_corrupt(path.read_bytes(), *c))
    try:
        err = _run(["whdr", str(d / "r.png"), str(d / "r.json")], capsys, d, "whdr")
    except AssertionError:
        if c[0] == "flip":  # a flipped byte may leave valid JSON / a decodable PNG: scored, no error
            return
        raise
    assert f"r.{target}" in err, err


def test_whdr_refuses_judgements_that_break_the_format(good, tmp_path, capsys):
    shutil.copy(good["dir"] / "photo.png", tmp_path / "r.png")
    valid = json.loads((good["dir"] / "judgements.json").read_text())
    broken = [
        {},
        {"intrinsic_points": valid["intrinsic_points"]},
        {**valid, "intrinsic_points": [{"id": 0, "x": 1.5, "y": 0.5, "opaque": True}]},
        {**valid, "intrinsic_comparisons": [{"id": 0, "point1": 0, "point2": 99, "darker": "1", "darker_score": 1}]},
        {**valid, "intrinsic_comparisons": [{"id": 0, "point1": 0, "point2": 1, "darker": "X", "darker_score": 1}]},
        [1, 2, 3],
    ]
    for k, payload in enumerate(broken):
        (tmp_path / "r.json").write_text(json.dumps(payload))
        assert "r.json" in _run(
            ["whdr", str(tmp_path / "r.png"), str(tmp_path / "r.json")], capsys, tmp_path, "whdr"
        ), k
    (tmp_path / "r.txt").write_text("{}")
    assert "r.txt" in _run(["whdr", str(tmp_path / "r.png"), str(tmp_path / "r.txt")], capsys, tmp_path, "whdr")


@FUZZ
@given(c=corruptions, which=st.sampled_from(["im", "depth", "normal", "mask", "light", "cameras", "split"]))
def test_validate_reports_damaged_views_and_roots(micro_root, tmp_path_factory, capsys, c, which):
    from pipeline.data import interiorverse as iv

    root = tmp_path_factory.mktemp("root") / "copy"
    shutil.copytree(micro_root, root)
    scene = iv.read_split(root, "test")[0]
    target = {
        "light": iv.light_path(root, scene, "000"),
        "cameras": root / scene / "cameras.json",
        "split": root / "test.txt",
    }.get(which, iv.map_path(root, scene, "000", which))
    target.write_bytes(_corrupt(target.read_bytes(), *c))
    CASES_TRIED["validate"] += 1
    status = main(["validate", str(root)])
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    if status == 0:  # a flipped byte that leaves the file valid: nothing to report
        assert c[0] == "flip" or which == "cameras", (which, c)
        return
    assert status in (1, 2), status
    text = captured.out + captured.err
    assert target.name in text or (which == "split" and "test.txt" in text), text


def test_zz_report_cases_tried():
    """Printed for the record (`pytest -s`); every entry point was exercised."""
    print("fuzz cases tried per entry point:", dict(CASES_TRIED))
    if CASES_TRIED:  # empty when this test runs alone or on another xdist worker
        assert {"predict", "insert", "edit"} <= set(CASES_TRIED)
