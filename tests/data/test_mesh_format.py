"""data.formats.mesh: OBJ, PLY and GLB read to the same triangles; every bad mesh refused naming the file."""

import numpy as np
import pytest
import trimesh

from pipeline.data.formats import mesh as mesh_format
from pipeline.data.formats.mesh import MeshError, read_mesh


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".glb"])
def test_each_format_reads_the_same_box(tmp_path, suffix):
    box = trimesh.creation.box(extents=(1.0, 2.0, 0.5))
    path = tmp_path / f"box{suffix}"
    box.export(path)
    vertices, faces = read_mesh(path)
    assert faces.shape == (12, 3) and vertices.shape == (8, 3)
    np.testing.assert_allclose(vertices.max(0) - vertices.min(0), (1.0, 2.0, 0.5), atol=1e-6)
    assert faces.dtype == np.int64 and vertices.dtype == np.float64


def test_bad_meshes_are_refused_naming_the_file(tmp_path, monkeypatch):
    (tmp_path / "garbage.glb").write_bytes(b"glTF not really")
    (tmp_path / "empty.obj").write_text("# no faces\nv 0 0 0\n")
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 nan 0\nf 1 2 3\n")
    (tmp_path / "point.obj").write_text("v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n")
    # three triangles on one edge (0-1): not a surface
    (tmp_path / "fan.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 -1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 2 5\n")
    (tmp_path / "box.stl").write_text("solid x\nendsolid x\n")
    trimesh.creation.icosphere(subdivisions=2).export(tmp_path / "big.ply")
    cases = {
        "missing.obj": "no such file",
        "box.stl": "not a mesh file",
        "garbage.glb": "unreadable as GLB",
        "empty.obj": "no triangles",
        "nan.obj": "not finite",
        "point.obj": "no extent",
        "fan.obj": "non-manifold",
    }
    for name, needle in cases.items():
        with pytest.raises(MeshError, match=needle) as info:
            read_mesh(tmp_path / name)
        assert name in str(info.value)
    monkeypatch.setattr(mesh_format, "MAX_FACES", 100)
    with pytest.raises(MeshError, match="320 triangles; at most 100"):
        read_mesh(tmp_path / "big.ply")
