"""Bad input at every command-line entry point (`invrender predict / insert / edit / whdr / validate`):
corrupt, truncated and empty files, wrong channel counts, NaN/inf pixels, images too small or too
large, wrong or damaged model exports (a pickle payload among them), masks of the wrong size, pixels off
the image and output folders that cannot be written. Every case must end with exit status 2 (1 for
`validate`, which reports rejected views), one line on stderr naming the file or argument, no traceback,
and no file written. Hypothesis draws the corruptions; the photo and `validate` tests also check, where
they draw them, that each kind of damage was drawn and refused."""

from __future__ import annotations

import json
import pickle
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from PIL import Image

from pipeline.cli import MAX_SIDE, MIN_SIDE, main
from pipeline.data.formats.exr import write_exr

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("fuzz_entry_points")]
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
# run besides the drawn cases, which follow the test's source text (derandomize): a tally of refusals needs both
EMPTY, TRUNCATED = ("empty", 0.0, [0]), ("truncate", 0.5, [0])


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
        "envmap": ["envmap", photo, "--at", "20,20", "--out", str(out / "x.exr"), "--width", "8", "--material-net", m]
        + ["--light-net", li],
    }


def _usable_photo(path: Path) -> tuple[int, int] | None:
    """(height, width) of a photo every command must accept, decoded here without the commands' reader:
    it decodes in full to three channels or more (RGB), every value finite, non-negative and not all 0,
    MIN_SIDE to MAX_SIDE pixels a side. None for a photo they must refuse."""
    try:
        if path.suffix == ".exr":
            import OpenEXR

            with OpenEXR.File(str(path), separate_channels=True) as f:
                planes = [np.asarray(ch.pixels, np.float64) for ch in f.channels().values()]
            if len(planes) < 3 or len({p.shape for p in planes}) != 1 or planes[0].ndim != 2:
                return None
            pixels = np.stack(planes, -1)
        else:
            with Image.open(path) as img:
                pixels = np.asarray(img.convert("RGB"), np.float64)
    except Exception:  # noqa: BLE001 - whatever the decoder raises, the bytes are not a photo
        return None
    h, w = pixels.shape[:2]
    if not (np.isfinite(pixels).all() and (pixels >= 0).all() and pixels.max() > 0):
        return None
    return (h, w) if MIN_SIDE <= min(h, w) and max(h, w) <= MAX_SIDE else None


@pytest.mark.parametrize("suffix", [".png", ".jpg", ".exr"])
def test_corrupt_photos_are_refused(good, tmp_path_factory, capsys, suffix):
    """Empty and truncated photos are refused by every command; a photo with flipped bytes is refused
    unless it still decodes (checked here with the decoders themselves) to a usable photo of the same
    size, which every command must then process. The outcomes are tallied here, in the test that draws
    the cases, so that every command is known to have refused each kind of damage."""
    refused: Counter = Counter()

    @FUZZ
    @given(c=corruptions)
    @example(c=EMPTY)
    @example(c=TRUNCATED)
    def check(c):
        d = tmp_path_factory.mktemp("corrupt")
        photo = d / f"photo{suffix}"
        photo.write_bytes(_corrupt((good["dir"] / f"photo{suffix}").read_bytes(), *c))
        size = _usable_photo(photo)
        assert size is None or c[0] == "flip", f"{c[0]} left a usable photo: the case tests nothing"
        out = d / "out"
        out.mkdir()
        for name, argv in _photo_cmds(str(photo), good, out).items():
            if size is None:
                err = _run(argv, capsys, out, name)
                assert photo.name in err, err
                refused[name, c[0]] += 1
            elif size == (48, 64):  # still the photo the mask and --at were made for
                assert main(argv) == 0, (name, capsys.readouterr().err)
                assert "Traceback" not in capsys.readouterr().err
            else:  # decodes at another size: processed, or refused in one line naming what no longer fits
                status = main(argv)
                err = capsys.readouterr().err.strip()
                assert status == 0 or (status == 2 and len(err.splitlines()) == 1), (name, status, err)
                assert "Traceback" not in err and (status == 0 or any(k in err for k in ("--mask", "--at", photo.name)))
        shutil.rmtree(out)

    check()
    for name in ("predict", "insert", "edit", "envmap"):
        for how in ("empty", "truncate"):
            assert refused[name, how], f"{name}: no {how} {suffix} photo was tried"


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


@pytest.mark.parametrize("which", ["im", "depth", "normal", "mask", "light", "cameras", "split"])
def test_validate_reports_damaged_views_and_roots(micro_root, tmp_path_factory, capsys, which):
    """validate names the damaged file (exit 1: a rejected view, 2: an unusable root) with no traceback,
    and reports nothing only when the damage left a valid file. The kinds of damage reported are tallied
    here, so that each file is known to have been reported empty and truncated."""
    from pipeline.data import interiorverse as iv

    root = tmp_path_factory.mktemp("root") / "copy"
    shutil.copytree(micro_root, root)
    scene = iv.read_split(root, "test")[0]
    target = {
        "light": iv.light_path(root, scene, "000"),
        "cameras": root / scene / "cameras.json",
        "split": root / "test.txt",
    }.get(which, iv.map_path(root, scene, "000", which))
    original = target.read_bytes()
    reported: Counter = Counter()

    @FUZZ
    @given(c=corruptions)
    @example(c=EMPTY)
    @example(c=TRUNCATED)
    def check(c):
        damaged = _corrupt(original, *c)
        target.write_bytes(damaged)
        try:
            status = main(["validate", str(root)])
        finally:
            target.write_bytes(original)
        captured = capsys.readouterr()
        assert "Traceback" not in captured.err
        if status == 0:  # valid after all: a flipped byte that decodes, a split file cut after its last name
            assert c[0] == "flip" or (which == "split" and damaged.split() == original.split()), (which, c)
            return
        assert status in (1, 2), status
        assert str(target) in captured.out + captured.err, captured
        reported[c[0]] += 1

    check()
    assert reported["empty"] and reported["truncate"], f"{which}: damage reported {dict(reported)}"
