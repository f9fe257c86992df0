"""The order in which a view's rays meet the regions of a k-d split (issue 43 item 2): front to back, the order
sort-last compositing needs (`volren.dataparallel.composite`).

A split plane cuts space in two half-spaces, and a ray (a straight segment) crosses it at most once, from the side it
starts on to the other: everything it meets on its start side comes before everything on the other side. So at each
node the child on the eye's side goes first, recursively, and one order serves every ray of a pinhole view (an eye
inside the volume or outside it), for every pixel; an orthographic view's rays all travel along one direction and
enter first the child that direction leaves. A region a ray misses sits anywhere in the order without harm: its
partial image is empty there.

**Units.** The eye is a point in the volume's local coordinates (x, y, z) (DESIGN.md: [-1, 1]^3 is the volume's
box; the camera's position through the inverse of ``to_world``). The tree's planes are brick indices; each is placed
in local coordinates by `volren.dataparallel.regions.plane_local` (the centre of voxel B p), the very value at which
the two regions' clip boxes meet, and compared there. An eye on a plane belongs to the high side, as the plane does
under the regions' half-open rule, and that side goes first (rays from the plane enter only one side: either order is
right, this one is deterministic). A direction parallel to a plane crosses it nowhere: the low side goes first.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from volren.dataparallel.regions import RegionTree, Split, plane_local

AXIS_XYZ = (2, 1, 0)
"""local coordinate (x, y, z) index of brick axes z, y, x"""


def visibility_order(tree: RegionTree, eye_local: np.ndarray) -> list[int]:
    """The region indices front to back for a pinhole eye at ``eye_local`` (x, y, z, the volume's local
    coordinates; module docstring)."""
    eye = np.asarray(eye_local, dtype=np.float64).reshape(3)

    def low_first(node: Split) -> bool:
        return bool(eye[AXIS_XYZ[node.axis]] < _plane(tree, node))

    return _walk(tree.root, low_first)


def visibility_order_direction(tree: RegionTree, direction_local: np.ndarray) -> list[int]:
    """The region indices front to back for parallel rays travelling along ``direction_local`` (x, y, z, local
    coordinates; an orthographic view): at each split the child the rays enter first."""
    d = np.asarray(direction_local, dtype=np.float64).reshape(3)
    return _walk(tree.root, lambda node: bool(d[AXIS_XYZ[node.axis]] >= 0.0))


def _plane(tree: RegionTree, node: Split) -> float:
    return plane_local(node.plane, tree.grid[node.axis], tree.brick, tree.shape[node.axis])


def _walk(node: Split | int, low_first: Callable[[Split], bool]) -> list[int]:
    if isinstance(node, int):
        return [node]
    first, second = (node.low, node.high) if low_first(node) else (node.high, node.low)
    return _walk(first, low_first) + _walk(second, low_first)
