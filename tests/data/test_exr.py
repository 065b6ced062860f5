import numpy as np
import pytest

from pipeline.data.formats.exr import ExrError, read_exr, write_exr


def test_roundtrip_float32_keeps_hdr_inf_and_noncontiguous(tmp_path):
    rng = np.random.default_rng(0)
    img = (rng.random((6, 9, 3)) * 1e4).astype(np.float32)
    img[0, 0, 0] = np.inf
    view = img[:, ::-1]  # non-contiguous: OpenEXR would write garbage without a copy
    write_exr(tmp_path / "a.exr", view)
    np.testing.assert_array_equal(read_exr(tmp_path / "a.exr"), view)


def test_single_channel_and_float64_input(tmp_path):
    depth = np.linspace(0, 5000, 20, dtype=np.float64).reshape(4, 5)
    write_exr(tmp_path / "d.exr", depth)
    back = read_exr(tmp_path / "d.exr")
    assert back.shape == (4, 5, 1) and back.dtype == np.float32
    np.testing.assert_allclose(back[..., 0], depth, rtol=1e-7)


def test_half_precision(tmp_path):
    img = np.full((2, 2, 3), 0.3, np.float32)
    write_exr(tmp_path / "h.exr", img, half=True)
    np.testing.assert_allclose(read_exr(tmp_path / "h.exr"), img, rtol=1e-3)


def test_truncated_file_names_the_file(tmp_path):
    write_exr(tmp_path / "a.exr", np.ones((8, 8, 3), np.float32))
    data = (tmp_path / "a.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 3])
    with pytest.raises(ExrError, match="cut.exr"):
        read_exr(tmp_path / "cut.exr")


def test_missing_and_garbage_files(tmp_path):
    with pytest.raises(ExrError, match="nope.exr: file not found"):
        read_exr(tmp_path / "nope.exr")
    (tmp_path / "junk.exr").write_bytes(b"not an exr at all")
    with pytest.raises(ExrError, match="junk.exr"):
        read_exr(tmp_path / "junk.exr")


def test_refuses_unwritable_shapes(tmp_path):
    with pytest.raises(ExrError, match="shape"):
        write_exr(tmp_path / "x.exr", np.zeros((4, 4, 2), np.float32))
