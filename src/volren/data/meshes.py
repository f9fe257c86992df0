"""Triangle meshes from files (OBJ, PLY, STL, glTF/GLB, OFF, ... through trimesh) as opaque scene geometry."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from volren.errors import VolrenError
from volren.scene import TriangleMesh


def load_mesh_file(
    path: str | Path,
    *,
    scale: float = 1.0,
    translate: Sequence[float] = (0.0, 0.0, 0.0),
    albedo: float | Sequence[float] = 0.7,
) -> TriangleMesh:
    """Read every triangle of a mesh file (a multi-object scene is flattened into one mesh in world coordinates),
    then scale about the origin and translate: world = scale * v + translate. Errors name the file."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise VolrenError(f"{path}: mesh file not found")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # any parser failure on user data means an unreadable or corrupt file
        raise VolrenError(f"{path}: cannot read the mesh ({type(exc).__name__}: {exc})") from None
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))))
    if faces.size == 0:
        raise VolrenError(f"{path}: holds no triangles")
    vertices = np.asarray(mesh.vertices, dtype=np.float64) * float(scale) + np.asarray(translate, dtype=np.float64)
    return TriangleMesh(vertices, faces.astype(np.int64), albedo=albedo, name=path.name)
