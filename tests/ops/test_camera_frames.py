import math

import torch

from pipeline.ops.camera import backproject, focal, pixel_directions, project
from pipeline.ops.frames import from_local, orthonormal_basis, to_local


def test_backproject_project_roundtrip_and_convention():
    depth = 1 + torch.rand(2, 6, 8, dtype=torch.float64)
    pts = backproject(depth, 70.0)
    uv, z = project(pts.reshape(-1, 3), 70.0, 6, 8)
    torch.testing.assert_close(z, depth.reshape(-1))
    j, i = torch.meshgrid(torch.arange(8.0), torch.arange(6.0), indexing="xy")
    centres = torch.stack([j + 0.5, i + 0.5], -1).to(torch.float64).reshape(1, -1, 2).expand(2, -1, -1).reshape(-1, 2)
    torch.testing.assert_close(uv, centres)
    d = pixel_directions(6, 8, 70.0)
    assert d[0, 0, 0] < 0 and d[0, 0, 1] > 0 and (d[..., 2] == -1).all()  # row 0 top, col 0 left, looks down -z
    assert math.isclose(float(d[0, -1, 0]), (7.5 - 4) / focal(70.0, 8), rel_tol=1e-6)  # float32 map
    assert math.isclose(focal(90.0, 100), 50.0, rel_tol=1e-12)


def test_orthonormal_basis_everywhere_including_the_poles():
    n = torch.nn.functional.normalize(torch.randn(1000, 3, dtype=torch.float64), dim=-1)
    n = torch.cat([n, torch.tensor([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, 0, -1 + 1e-12]], dtype=torch.float64)])
    n = torch.nn.functional.normalize(n, dim=-1)
    t, b = orthonormal_basis(n)
    frame = torch.stack([t, b, n], -1)
    torch.testing.assert_close(frame.transpose(-1, -2) @ frame, torch.eye(3, dtype=torch.float64).expand(len(n), 3, 3))
    torch.testing.assert_close(torch.linalg.det(frame), torch.ones(len(n), dtype=torch.float64))
    v = torch.randn(len(n), 3, dtype=torch.float64)
    torch.testing.assert_close(from_local(to_local(v, t, b, n), t, b, n), v)
