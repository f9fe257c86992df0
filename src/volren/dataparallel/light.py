"""The regions' light-map exchange (issue 43 item 3): each region's light map holds, per node, the optical depth of
its own samples of the node's path to each light (`volren.render.base.LightMapRenderer.region_light_map`); the sum
over the regions is the one-process map. What travels is less than N maps and back:

- a region sends its map's sigma_bar planes (one per light; the tau_in planes carry other volumes' depth, which a
  data-parallel scene, one volume and no GI, has none of) over the box of nodes where they are not zero: the nodes
  whose path to a light crosses the region (a 512^3 volume's 256^3-node map is 128 MiB a region, mostly zeros);
- the sum comes back to each region only over the nodes its own samples read (its cells' box in light-map nodes,
  one node to spare): about 1/N of the map.

The values are the sums of the full maps' node for node, so the picture is the same.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from volren.errors import VolrenError
from volren.scene import Volume
from volren.upload import light_grid_resolution

Nodes = tuple[int, int, int]
"""light-map nodes (z, y, x)"""


@dataclass(frozen=True)
class LightPart:
    """One region's light map where it is not zero, and the nodes it reads (module docstring)."""

    size: int
    """floats of the region's whole light-map array"""
    res: Nodes
    """the map's nodes per axis (z, y, x)"""
    lights: int
    lo: Nodes
    """the first node of the box where the sigma_bar planes are not zero"""
    hi: Nodes
    """its last node + 1 (lo == hi: the region adds nothing)"""
    values: np.ndarray
    """float32 (lights, z, y, x): the sigma_bar planes over [lo, hi)"""
    needs: tuple[Nodes, Nodes]
    """the nodes [first, last + 1) a sample in the region's cells interpolates"""

    @property
    def nbytes(self) -> int:
        return int(self.values.nbytes)


def _planes(light_map: np.ndarray, res: Nodes, lights: int) -> np.ndarray:
    """The sigma_bar planes (lights, z, y, x) of a packed light map (per light sigma_bar, then tau_in)."""
    return light_map.reshape(lights, 2, *res)[:, 0]


def light_part(light_map: np.ndarray, volume: Volume, light_grid: int | None) -> LightPart:
    """The `LightPart` of a region's ``light_map`` (`region_light_map`'s) for its ``volume`` (a region's: its
    ``owned_cells`` set, bricked) and the renderer's ``light_grid``."""
    res: Nodes = light_grid_resolution(volume.resolution, light_grid, sparse=True)[::-1]  # as the upload sizes it
    nodes = int(np.prod(res))
    lights = light_map.size // (2 * nodes)
    if lights * 2 * nodes != light_map.size or volume.owned_cells is None:
        raise VolrenError(f"a light map of {light_map.size} floats is not a region's of {list(res)} nodes")
    planes = _planes(light_map, res, lights)
    used = np.any(planes != 0, axis=0)
    spans = [np.flatnonzero(used.any(axis=tuple(b for b in range(3) if b != a))) for a in range(3)]
    lo: Nodes = tuple(int(s[0]) if len(s) else 0 for s in spans)  # type: ignore[assignment]
    hi: Nodes = tuple(int(s[-1]) + 1 if len(s) else 0 for s in spans)  # type: ignore[assignment]
    values = np.ascontiguousarray(planes[:, lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]])
    return LightPart(light_map.size, res, lights, lo, hi, values, needed_nodes(volume, res))


def needed_nodes(volume: Volume, res: Nodes) -> tuple[Nodes, Nodes]:
    """The light-map nodes (z, y, x) [first, last + 1) that the samples in ``volume``'s owned cells interpolate: the
    cells' span from voxel centre to voxel centre, a voxel to spare (the border's clamp included), in node units
    (node i of n at -1 + 2 i / (n - 1)), a node to spare."""
    first, last = volume.owned_cells  # type: ignore[misc]
    lo, hi = [], []
    for a, n_voxels in enumerate(volume.density.shape):
        p_lo = max(-1.0 + (first[a] - 0.5) * 2.0 / n_voxels, -1.0)
        p_hi = min(-1.0 + (last[a] + 1.5) * 2.0 / n_voxels, 1.0)
        u_lo, u_hi = (p_lo + 1.0) * 0.5 * (res[a] - 1), (p_hi + 1.0) * 0.5 * (res[a] - 1)
        lo.append(max(int(np.floor(u_lo)) - 1, 0))
        hi.append(min(int(np.ceil(u_hi)) + 2, res[a]))
    return tuple(lo), tuple(hi)  # type: ignore[return-value]


def light_sum(parts: Sequence[LightPart]) -> np.ndarray:
    """The regions' sigma_bar planes summed over the whole map: float32 (lights, z, y, x)."""
    first = parts[0]
    total = np.zeros((first.lights, *first.res), np.float32)
    for p in parts:
        if p.res != first.res or p.lights != first.lights:
            raise VolrenError(f"the regions' light maps differ: {list(p.res)} and {list(first.res)} nodes")
        total[:, p.lo[0]:p.hi[0], p.lo[1]:p.hi[1], p.lo[2]:p.hi[2]] += p.values
    return total


def light_patch(total: np.ndarray, part: LightPart) -> np.ndarray:
    """The summed planes over the nodes ``part``'s region reads."""
    (z0, y0, x0), (z1, y1, x1) = part.needs
    return np.ascontiguousarray(total[:, z0:z1, y0:y1, x0:x1])


def light_map_of(patch: np.ndarray, part: LightPart) -> np.ndarray:
    """The region's whole light-map array (``part``'s layout) holding the sum's ``patch`` over the nodes it reads,
    0 elsewhere (nodes no sample of the region reads; tau_in: no other volume)."""
    out = np.zeros(part.size, np.float32)
    (z0, y0, x0), (z1, y1, x1) = part.needs
    _planes(out, part.res, part.lights)[:, z0:z1, y0:y1, x0:x1] = patch
    return out
