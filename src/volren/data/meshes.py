"""Triangle meshes from files (OBJ, PLY, STL, glTF/GLB, OFF, ... through trimesh; USD through usd-core) as opaque or
translucent scene geometry."""

from __future__ import annotations

import re
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
    alpha: float = 1.0,
) -> TriangleMesh:
    """Read every triangle of a mesh file (a multi-object scene is flattened into one mesh in world coordinates),
    then scale about the origin and translate: world = scale * v + translate. ``alpha`` < 1 makes it translucent
    (`TriangleMesh.alpha`). Errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise VolrenError(f"{path}: mesh file not found")
    if path.suffix.lower() in TEXT_SUFFIXES:
        try:
            path.read_bytes().decode("utf-8")
        except UnicodeDecodeError as exc:  # trimesh would go on to guess an encoding and fail obscurely
            raise VolrenError(f"{path}: not a text {path.suffix} mesh (byte {exc.start} is not UTF-8 text)") from None
    try:
        vertices, faces = read_usd(path) if path.suffix.lower() in USD_SUFFIXES else read_trimesh(path)
    except VolrenError:
        raise
    except Exception as exc:  # any parser failure on user data means an unreadable or corrupt file
        raise VolrenError(f"{path}: cannot read the mesh ({type(exc).__name__}: {_cause(exc)})") from None
    if faces.size == 0:
        raise VolrenError(f"{path}: holds no triangles")
    check_manifold(faces, path)
    vertices = vertices * float(scale) + np.asarray(translate, dtype=np.float64)
    return TriangleMesh(vertices, faces.astype(np.int64), albedo=albedo, name=path.name, alpha=alpha)


def _cause(exc: Exception) -> str:
    """A parser's error in one line. USD's lists its C++ frames, a line each: "Error in 'f' at line N in file F :
    'what'"; the first what is the cause (its namespace names shortened)."""
    text = re.sub(r"pxrInternal_\w+?__pxrReserved__::", "", str(exc))
    what = re.search(r" : '(.+)", text)
    return what.group(1).rstrip("'") if what else " ".join(text.split())


USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
TEXT_SUFFIXES = (".obj", ".off")
"""Mesh formats that are text only (PLY and STL have binary forms, glTF is JSON)."""


def read_trimesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    mesh = trimesh.load(path, force="mesh", process=False)
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))))
    return np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64), faces.reshape(-1, 3)


def read_usd(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Every UsdGeom.Mesh of the stage at the default time, in world coordinates (its local-to-world transform
    applied), polygons fan-triangulated."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise VolrenError(f"{path}: cannot open the USD stage")
    cache = UsdGeom.XformCache()
    vertices, faces, base = [], [], 0
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Mesh):
            continue
        mesh = UsdGeom.Mesh(prim)
        points = np.asarray(mesh.GetPointsAttr().Get() or [], dtype=np.float64).reshape(-1, 3)
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
        indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
        if not len(points) or not len(counts):
            continue
        if counts.sum() != len(indices) or counts.min() < 3:
            raise VolrenError(f"{path}: mesh {prim.GetPath()} has inconsistent face vertex counts")
        world = np.asarray(cache.GetLocalToWorldTransform(prim), dtype=np.float64)  # row-vector convention
        vertices.append(np.c_[points, np.ones(len(points))] @ world[:, :3])
        starts = np.r_[0, np.cumsum(counts)[:-1]]
        for k in range(1, counts.max() - 1):  # fan triangle k of every polygon with more than k + 1 sides
            sel = counts > k + 1
            faces.append(base + np.stack([indices[starts[sel]], indices[starts[sel] + k],
                                          indices[starts[sel] + k + 1]], 1))
        base += len(points)
    if not vertices:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    return np.concatenate(vertices), np.concatenate(faces)


def check_manifold(faces: np.ndarray, path: Path) -> None:
    """Refuse edges shared by more than two triangles: shadow and primary rays would see self-intersecting sheets
    (open borders, as of a single quad, are fine)."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, uses = np.unique(edges, axis=0, return_counts=True)
    bad = int((uses > 2).sum())
    if bad:
        raise VolrenError(f"{path}: non-manifold mesh ({bad} edges shared by more than two triangles)")
