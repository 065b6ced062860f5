"""Triangle meshes from OBJ, PLY and GLB files (trimesh), checked before anything is rendered with them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

MESH_SUFFIXES = (".obj", ".ply", ".glb")
MAX_FACES = 200_000  # more triangles than an inserted object needs, and than the CPU ray caster affords


class MeshError(ValueError):
    """A mesh file that cannot be inserted; the message names the file and why."""


def read_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, faces (F, 3) int64) of the mesh in `path` (a glTF binary's meshes joined
    into one), duplicate vertices merged. Refused, naming the file: another format, a missing or unreadable
    file, no triangles, a non-finite vertex, more than MAX_FACES triangles, no extent, and a non-manifold
    mesh (an edge shared by more than two triangles)."""
    import trimesh

    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise MeshError(f"{path}: not a mesh file (choose one of {', '.join(MESH_SUFFIXES)})")
    if not path.is_file():
        raise MeshError(f"{path}: no such file")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)  # processing would drop NaN vertices unseen
    except Exception as e:  # noqa: BLE001  any parser failure is a bad file, reported as such
        raise MeshError(f"{path}: unreadable as {path.suffix.lower()[1:].upper()} ({type(e).__name__}: {e})") from e
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    if len(faces) == 0:
        raise MeshError(f"{path}: the mesh has no triangles")
    if len(faces) > MAX_FACES:
        raise MeshError(f"{path}: {len(faces)} triangles; at most {MAX_FACES} can be inserted")
    if not np.isfinite(vertices).all():
        raise MeshError(f"{path}: a vertex is not finite (NaN or inf)")
    mesh.merge_vertices()  # a format that repeats a vertex per face (STL-like PLY, glTF seams) joined again
    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    vertices = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3)
    if not (vertices.max(0) - vertices.min(0)).max() > 0:
        raise MeshError(f"{path}: the mesh has no extent (every vertex at one point)")
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    if (counts > 2).any():
        raise MeshError(f"{path}: non-manifold ({int((counts > 2).sum())} edges shared by more than two triangles)")
    return vertices, faces
