"""OME-Zarr (NGFF) metadata: attributes, axes, coordinate transformations, fill values, and the box of a chunk on
the next coarser level, shared by the reader of one level (`volren.data.omezarr`) and the brick streamer
(`volren.stream.source`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

CHUNK_MARGIN = 2
"""[voxels of the coarser level] left out at each side of a chunk's box when `_missing_chunks` looks there for data
(fewer where the box is narrower, keeping its middle): a smoothing downsampler (a Gaussian pyramid) spreads a
neighbouring chunk's values about this far"""


def _attributes(group: Any) -> dict[str, Any]:
    """NGFF 0.5 nests the metadata under ``ome``; 0.4 keeps it at the top of the group's attributes."""
    attrs = dict(group.attrs)
    return dict(attrs["ome"]) if "ome" in attrs else attrs


def _axes(multiscale: dict[str, Any], ndim: int) -> list[tuple[str, str, str | None]]:
    """(name, type, unit) per array axis; NGFF 0.3 gave names only, <= 0.2 none (then t, c, z, y, x)."""
    axes = multiscale.get("axes", ["t", "c", "z", "y", "x"][-ndim:])
    out = []
    for a in axes:
        name = str(a["name"] if isinstance(a, dict) else a).lower()
        kind = str(a.get("type", "")) if isinstance(a, dict) else ""
        kind = kind or {"c": "channel", "t": "time"}.get(name, "space")
        out.append((name, kind, a.get("unit") if isinstance(a, dict) else None))
    if len(out) != ndim:
        raise ValueError(f"{len(out)} axes for an array of {ndim} dimensions")
    return out


def _scale_translation(transforms: list[dict[str, Any]], ndim: int) -> tuple[np.ndarray, np.ndarray]:
    """Compose a list of NGFF ``scale`` / ``translation`` transformations into one per-axis scale and offset."""
    scale, offset = np.ones(ndim), np.zeros(ndim)
    for t in transforms:
        kind = t["type"]
        if kind == "identity":
            continue
        if kind not in ("scale", "translation"):
            raise ValueError(f"coordinate transformation {kind!r} is not supported (scale and translation are)")
        if kind not in t:
            raise ValueError(f"a {kind} transformation without values (a 'path' to them is not supported)")
        v = np.asarray(t[kind], dtype=np.float64)
        if v.shape != (ndim,) or not np.all(np.isfinite(v)):
            raise ValueError(f"{kind} {t[kind]!r} is not {ndim} finite numbers")
        if kind == "scale":
            scale, offset = scale * v, offset * v
        else:
            offset = offset + v
    return scale, offset


def _fill(array: Any) -> float:
    """The value zarr gives the voxels of a chunk that is not on disk."""
    return 0.0 if array.fill_value is None else float(array.fill_value)


def coarser_inner_box(box: list[tuple[int, int]], ratio: list[float]) -> list[slice]:
    """A chunk's ``box`` ([start, stop) per axis in a level's voxels) in the next coarser level's voxels (``ratio``:
    coarser voxels per finer voxel, per axis), less the margins (`CHUNK_MARGIN`): where a hole's data would show."""
    inner = []
    for (a, b), r in zip(box, ratio, strict=True):
        lo, hi = math.ceil(a * r), math.floor(b * r)
        m = 0 if r == 1 else max(0, min(CHUNK_MARGIN, (hi - lo - 1) // 2))
        inner.append(slice(lo + m, hi - m))
    return inner
