"""The re-render figure's scatter of stride-grid pixels back into images."""

import numpy as np
import torch

from pipeline.ops.camera import grid_pixels
from pipeline.systems.lighting_figures import scatter_grid, spread_indices


def test_scatter_grid_puts_each_pixel_at_its_grid_cell_and_leaves_the_rest_nan():
    B, H, W, stride = 2, 5, 7, 2
    mask = torch.ones(B, H, W, dtype=torch.bool)
    mask[1, 2, 4] = False  # an invalid pixel on the grid stays NaN
    pix = grid_pixels(mask, stride)
    b, rc = pix // (H * W), pix % (H * W)
    values = torch.stack([b.float(), (rc // W).float(), (rc % W).float()], -1)  # each pixel's own coordinates
    out = scatter_grid(values, pix, (B, H, W), stride)
    assert out.shape == (B, 3, 4, 3)
    for v in range(B):
        for r in range(3):
            for c in range(4):
                if v == 1 and (r, c) == (1, 2):
                    assert np.isnan(out[v, r, c]).all()
                else:
                    np.testing.assert_array_equal(out[v, r, c], [v, r * stride, c * stride])


def test_probe_picks_spread_over_the_list_and_never_repeat():
    assert spread_indices(48, 2) == [0, 47]
    assert spread_indices(48, 3) == [0, 24, 47]
    assert spread_indices(1, 2) == [0]
    assert spread_indices(0, 2) == []
