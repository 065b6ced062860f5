"""Open Image Denoise on the beauty image: removes grain, keeps edges and energy, rejects bad input."""

import numpy as np
import pytest

from pipeline.data.synth.denoise import DenoiseError, denoise_hdr


def _noisy(rng, clean, spp=16):
    # a Monte Carlo estimate's noise: the mean of spp exponential samples per pixel (heavy right tail)
    return (clean[..., None] * rng.exponential(1.0, size=(*clean.shape, spp))).mean(-1).astype(np.float32)


def test_removes_grain_and_keeps_an_edge():
    rng = np.random.default_rng(0)
    clean = np.ones((96, 128, 3), np.float32) * 0.2
    clean[:, 64:] = 1.0
    noisy = _noisy(rng, clean)
    out = denoise_hdr(noisy)
    assert out.shape == noisy.shape and out.dtype == np.float32 and (out >= 0).all()
    err_in, err_out = np.mean((noisy - clean) ** 2), np.mean((out - clean) ** 2)
    assert err_out < 0.25 * err_in, (err_in, err_out)
    # the step stays a step: each half keeps its level (energy is not moved across the edge)
    np.testing.assert_allclose(out[:, 4:60].mean(), 0.2, rtol=0.1)
    np.testing.assert_allclose(out[:, 68:124].mean(), 1.0, rtol=0.1)


@pytest.mark.parametrize(
    "bad, match",
    [(np.zeros((8, 8), np.float32), "shape"), (np.full((8, 8, 3), np.nan, np.float32), "NaN")],
)
def test_rejects_bad_images(bad, match):
    with pytest.raises(DenoiseError, match=match):
        denoise_hdr(bad)
