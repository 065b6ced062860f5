"""Bad input fuzzed at the data entry points that are not command lines: `preprocess` on an
InteriorVerse root with one damaged file, and the IIW and NYUv2 readers. Each case must either read
valid data or raise the reader's own error (DatasetError / IIWError / NYUError) naming the damaged file;
`preprocess` must account for every listed view (kept, or rejected with a reason naming the file).
Hypothesis draws the damage; the cases per entry point are counted and printed at the end."""

from __future__ import annotations

import json
import math
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from pipeline.data import iiw, nyuv2
from pipeline.data import interiorverse as iv
from pipeline.data.preprocess import preprocess

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("fuzz_readers")]
CASES_TRIED: Counter = Counter()
FUZZ = settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)

damage = st.tuples(
    st.sampled_from(["empty", "truncate", "flip", "garbage"]),
    st.floats(0.0, 0.95),
    st.lists(st.integers(0, 100_000), min_size=1, max_size=8),
)


def _damage(data: bytes, how: str, at: float, flips: list[int]) -> bytes:
    if how == "empty":
        return b""
    if how == "truncate":
        return data[: int(at * len(data))]
    if how == "garbage":
        return bytes((k * 37 + 11) % 256 for k in flips) * 16
    buf = bytearray(data)
    for k in flips:  # past the first 8 bytes: keep the magic number, hit the structure
        buf[8 + k % max(1, len(buf) - 8)] ^= 0xA5
    return bytes(buf)


json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-5, 5)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=4),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=3), inner, max_size=3),
    max_leaves=6,
)


# ---------------------------------------------------------------------------------------------------- preprocess
@pytest.fixture(scope="module")
def root(micro_root, tmp_path_factory) -> Path:
    """A private copy of the micro root; each case damages one file and restores it afterwards."""
    dst = tmp_path_factory.mktemp("fuzz_root") / "root"
    shutil.copytree(micro_root, dst)
    return dst


def _targets(root: Path) -> list[str]:
    scene = iv.read_split(root, "train")[0]
    view = iv.list_views(root, scene)[0]
    maps = [f"{scene}/{view}_{name}.exr" for name in iv.MAPS]
    return [*maps, f"{scene}/{view}_light.npz", f"{scene}/cameras.json", "train.txt", "val.txt"]


def _check_preprocess(root: Path, out: Path, target: Path) -> None:
    """Either a clear refusal naming `target`, or every listed view kept or rejected (naming `target`)."""
    CASES_TRIED["preprocess"] += 1
    try:
        result = preprocess(root, out, 24, 32, shard_size=4, progress=False, source="synthetic")
    except iv.DatasetError as exc:
        assert str(target) in str(exc), f"error does not name {target}: {exc}"
        return
    kept = {v for split in result.manifest["splits"].values() for v in split["views"]}
    rejected = {f"{r['scene']}/{r['view']}" for r in result.rejected}
    listed = {f"{scene}/{view}" for _, scene, view in iv.split_views(root, iv.read_splits(root))}
    assert kept | rejected == listed and not kept & rejected  # nothing lost, nothing twice
    for r in result.rejected:
        assert r["file"] == str(target), r  # only the damaged file's view, for the damaged file
    for name in out.glob("*.npz"):
        with np.load(name) as z:
            assert all(np.isfinite(z[k]).all() for k in z.files if z[k].dtype.kind == "f")


@FUZZ
@given(which=st.integers(0, 9), d=damage)
def test_preprocess_on_a_root_with_a_damaged_file(root, tmp_path_factory, which, d):
    targets = _targets(root)
    target = root / targets[which % len(targets)]
    original = target.read_bytes()
    try:
        target.write_bytes(_damage(original, *d))
        _check_preprocess(root, tmp_path_factory.mktemp("pp"), target)
    finally:
        target.write_bytes(original)


@FUZZ
@given(value=json_values, kind=st.sampled_from(["whole", "view", "fov"]))
def test_preprocess_on_cameras_json_of_the_wrong_structure(root, tmp_path_factory, value, kind):
    scene = iv.read_split(root, "train")[0]
    target = root / scene / "cameras.json"
    original = target.read_bytes()
    cams = json.loads(original)
    view = sorted(cams)[0]
    doc = {"whole": value, "view": {**cams, view: value}, "fov": {**cams, view: {**cams[view], "fov_x_deg": value}}}
    try:
        target.write_text(json.dumps(doc[kind]))
        _check_preprocess(root, tmp_path_factory.mktemp("pp"), target)
    finally:
        target.write_bytes(original)


def test_preprocess_on_split_files_that_break_the_format(root, tmp_path):
    target = root / "train.txt"
    original = target.read_bytes()
    scene = iv.read_split(root, "train")[0]
    other = iv.read_split(root, "val")[0]
    cases = {
        "twice": f"{scene}\n{scene}\n",
        "missing scene": "scene_9999\n",
        "in two splits": f"{scene}\n{other}\n",
        "binary": "\udcff",
        "only comments": "# nothing\n",
    }
    try:
        for label, text in cases.items():
            target.write_bytes(text.encode("utf-8", "surrogateescape"))
            try:
                _check_preprocess(root, tmp_path / label.replace(" ", "_"), target)
            except AssertionError as exc:
                raise AssertionError(f"{label}: {exc}") from exc
    finally:
        target.write_bytes(original)


# ---------------------------------------------------------------------------------------------------- IIW
@pytest.fixture(scope="module")
def iiw_root(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("iiw")
    rng = np.random.default_rng(0)
    for k in (1, 2):
        Image.fromarray(rng.integers(0, 255, (30, 40, 3), dtype=np.uint8)).save(d / f"{k}.png")
        points = [{"id": i, "x": 0.1 + 0.2 * i, "y": 0.5, "opaque": True} for i in range(4)]
        comps = [{"id": 0, "point1": 0, "point2": 1, "darker": "1", "darker_score": 0.8}]
        (d / f"{k}.json").write_text(json.dumps({"intrinsic_points": points, "intrinsic_comparisons": comps}))
    return d


def _check_iiw(root: Path, image_id: str, target: Path) -> None:
    from pipeline.metrics.whdr import whdr

    CASES_TRIED["iiw"] += 1
    try:
        photo = iiw.read_photo(root, image_id)
        data = iiw.read_judgements(root, image_id)
    except iiw.IIWError as exc:
        assert str(target) in str(exc), f"error does not name {target}: {exc}"
        return
    assert photo.dtype == np.uint8 and photo.ndim == 3 and photo.shape[2] == 3
    value = whdr(photo.astype(np.float32) / 255.0, data)  # what passes the reader must be scoreable
    assert math.isnan(value) or 0.0 <= value <= 1.0


@FUZZ
@given(d=damage, which=st.sampled_from(["png", "json"]))
def test_iiw_reader_on_damaged_files(iiw_root, d, which):
    target = iiw_root / f"1.{which}"
    original = target.read_bytes()
    try:
        target.write_bytes(_damage(original, *d))
        _check_iiw(iiw_root, "1", target)
    finally:
        target.write_bytes(original)


@FUZZ
@given(value=json_values, part=st.sampled_from(["doc", "points", "point", "x", "id", "comp", "point1", "score"]))
def test_iiw_reader_on_judgements_of_the_wrong_structure(iiw_root, value, part):
    target = iiw_root / "1.json"
    original = target.read_bytes()
    doc = json.loads(original)
    p, c = doc["intrinsic_points"], doc["intrinsic_comparisons"]
    edits = {
        "doc": lambda: value,
        "points": lambda: {**doc, "intrinsic_points": value},
        "point": lambda: {**doc, "intrinsic_points": [value, *p[1:]]},
        "x": lambda: {**doc, "intrinsic_points": [{**p[0], "x": value}, *p[1:]]},
        "id": lambda: {**doc, "intrinsic_points": [{**p[0], "id": value}, *p[1:]]},
        "comp": lambda: {**doc, "intrinsic_comparisons": [value]},
        "point1": lambda: {**doc, "intrinsic_comparisons": [{**c[0], "point1": value}]},
        "score": lambda: {**doc, "intrinsic_comparisons": [{**c[0], "darker_score": value}]},
    }
    try:
        target.write_text(json.dumps(edits[part]()))
        _check_iiw(iiw_root, "1", target)
    finally:
        target.write_bytes(original)


def test_iiw_root_with_orphans_or_nothing(iiw_root, tmp_path):
    CASES_TRIED["iiw"] += 3
    with pytest.raises(iiw.IIWError, match="no <id>.png"):
        iiw.list_ids(tmp_path)
    (tmp_path / "7.png").write_bytes(b"")
    with pytest.raises(iiw.IIWError, match="7.json missing"):
        iiw.list_ids(tmp_path)
    with pytest.raises(iiw.IIWError, match="not a folder"):
        iiw.list_ids(tmp_path / "7.png")


# ---------------------------------------------------------------------------------------------------- NYUv2
@pytest.fixture(scope="module")
def nyu_root(tmp_path_factory) -> Path:
    import h5py
    from scipy.io import savemat

    d = tmp_path_factory.mktemp("nyu")
    rng = np.random.default_rng(0)
    n, h, w = 4, 24, 32
    with h5py.File(d / "labeled.mat", "w") as f:
        f["images"] = rng.integers(0, 255, (n, 3, w, h), dtype=np.uint8)
        f["depths"] = rng.uniform(0.5, 5.0, (n, w, h)).astype(np.float32)
    savemat(d / "splits.mat", {"trainNdxs": np.array([[1], [2], [3]]), "testNdxs": np.array([[4]])})
    for k in range(n):
        normal = rng.normal(size=(h, w, 3))
        nyuv2.write_normal_png(d / "normals" / f"{k:04d}.png", normal / np.linalg.norm(normal, axis=-1, keepdims=True))
        Image.fromarray(np.full((h, w, 3), 255, np.uint8)).save(d / "normals" / f"mask{k:04d}.png")
    (d / "masks").mkdir()
    for k in range(n):
        shutil.move(d / "normals" / f"mask{k:04d}.png", d / "masks" / f"{k:04d}.png")
    return d


def _check_nyu(root: Path, target: Path) -> None:
    CASES_TRIED["nyuv2"] += 1
    try:
        n = nyuv2.count_images(root / "labeled.mat")
        splits = nyuv2.read_splits(root / "splits.mat", n)
        images, depths = nyuv2.read_labeled(root / "labeled.mat", splits["test"])
        normal, mask = nyuv2.read_normal(root / "normals", root / "masks", int(splits["test"][0]), depths.shape[1:])
    except nyuv2.NYUError as exc:
        assert str(target) in str(exc), f"error does not name {target}: {exc}"
        return
    assert images.dtype == np.uint8 and np.isfinite(depths).all() and np.isfinite(normal).all()
    assert mask.shape == depths.shape[1:]


@FUZZ
@given(d=damage, which=st.sampled_from(["labeled.mat", "splits.mat", "normals/0003.png", "masks/0003.png"]))
def test_nyuv2_readers_on_damaged_files(nyu_root, d, which):
    target = nyu_root / which
    original = target.read_bytes()
    try:
        target.write_bytes(_damage(original, *d))
        _check_nyu(nyu_root, target)
    finally:
        target.write_bytes(original)


@pytest.mark.parametrize(
    "case",
    ["no depths", "depths shape", "depths nan", "images float", "splits 0-based", "splits overlap", "splits empty"],
)
def test_nyuv2_readers_on_files_that_break_the_format(nyu_root, tmp_path, case):
    import h5py
    from scipy.io import savemat

    root = tmp_path / "nyu"
    shutil.copytree(nyu_root, root)
    lab, spl = root / "labeled.mat", root / "splits.mat"
    with h5py.File(lab, "a") as f:
        if case == "no depths":
            del f["depths"]
        elif case == "depths shape":
            del f["depths"]
            f["depths"] = np.ones((4, 5, 5), np.float32)
        elif case == "depths nan":
            f["depths"][3, 0, 0] = np.nan
        elif case == "images float":
            del f["images"]
            f["images"] = np.ones((4, 3, 32, 24), np.float32)
    if case.startswith("splits"):
        train = {"splits 0-based": [[0], [1]], "splits overlap": [[1], [4]], "splits empty": np.zeros((0, 1))}[case]
        savemat(spl, {"trainNdxs": np.array(train), "testNdxs": np.array([[4]])})
    target = spl if case.startswith("splits") else lab
    CASES_TRIED["nyuv2"] += 1
    with pytest.raises(nyuv2.NYUError) as err:
        _check_nyu_strict(root)
    assert str(target) in str(err.value)


def _check_nyu_strict(root: Path) -> None:
    n = nyuv2.count_images(root / "labeled.mat")
    splits = nyuv2.read_splits(root / "splits.mat", n)
    nyuv2.read_labeled(root / "labeled.mat", splits["test"])


@pytest.fixture(scope="module", autouse=True)
def report_cases_tried():
    """After the module: how many damaged inputs each entry point was fed (shown with `pytest -s`)."""
    yield
    print("\nreader fuzz cases tried per entry point:", dict(CASES_TRIED))
