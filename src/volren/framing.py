"""Automatic framing, shared by every front end (``volren render --volume``, ``volren serve --volume``, `volren.render`
without views): the eye looks at a box's centre from the default direction, far enough that the whole box is in view;
a built-in volume scene is framed by where its density is (`framed_content`), not by its boxes.
Imports nothing heavy at the top (the command-line parser imports this module)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

DEFAULT_EYE = (0.0, 0.4, 3.2)
"""[m] the default camera position; a framed box is seen from its direction"""


def framing_distance(corners, look_at, direction, up, fov_y: float, aspect: float, eye_offset: float = 0.0) -> float:
    """Distance from ``look_at`` along the unit ``direction`` (towards the eye) at which every corner lies inside the
    view: a corner at (x, y) across and z towards the eye needs D >= z + |x| / tan(fov_x / 2) and likewise in y;
    ``eye_offset`` widens x for eyes shifted sideways (stereo: ipd / 2). Ten percent of margin."""
    import numpy as np

    d = np.asarray(direction, dtype=float)
    right = np.cross(-d, up)
    if np.linalg.norm(right) < 1e-9:  # --up along the view: Camera refuses it next; any frame will do here
        right = np.cross(-d, np.eye(3)[np.argmin(np.abs(d))])
    right /= np.linalg.norm(right)
    true_up = np.cross(right, -d)
    rel = np.asarray(corners, dtype=float) - np.asarray(look_at, dtype=float)
    tan_y = math.tan(math.radians(fov_y) / 2)
    across = np.abs(rel @ right) + eye_offset
    need = rel @ d + np.maximum(across / (tan_y * aspect), np.abs(rel @ true_up) / tan_y)
    return 1.1 * float(need.max())


DEFAULT_FAR = 1000.0
"""[m] the far plane of a framed eye, unless its volume reaches beyond (`framed_eye`)"""


def framed_eye(corners, up, fov_y: float, aspect: float, look_at=None, eye_offset: float = 0.0) -> tuple:
    """(position, look_at, near, far) of an eye that sees the box ``corners`` (an (N, 3) array [m]) whole: it looks
    at ``look_at`` (default: the box's centre) from the direction of `DEFAULT_EYE`, at `framing_distance`; ``near`` is
    0.01 m or a thousandth of that distance where less (a 100 um stack framed from 0.4 mm: 1 cm would clip it all);
    ``far`` `DEFAULT_FAR`, or twice the farthest corner where more (a 1.6 km OpenVDB box in metres, framed from 4 km,
    lay wholly beyond 1000 m: a black picture)."""
    import numpy as np

    look_at = tuple(look_at or (corners.min(axis=0) + corners.max(axis=0)) / 2)
    direction = np.array(DEFAULT_EYE) / np.linalg.norm(DEFAULT_EYE)
    distance = framing_distance(corners, look_at, direction, up, fov_y, aspect, eye_offset)
    eye = np.array(look_at) + distance * direction
    farthest = float(np.linalg.norm(np.asarray(corners, dtype=float) - eye, axis=1).max())
    return tuple(eye), look_at, min(0.01, distance / 1000), max(DEFAULT_FAR, 2.0 * farthest)


CONTENT_SHARE = 0.05
"""a voxel denser than this share of its volume's densest is content that `framed_content` keeps in view. Measured on
the built-in scenes at 64^3 (192x108, dssrm): the pixels of alpha > 0.05 span the same box at 0.01 and 0.05 within
3% (the plume's cap and edges are faint: a lower share frames no more of what shows)"""
CONTENT_BLOCKS = 48
"""blocks per axis at most in which `content_points` looks for content: each block's centre stands for it (a 512^3
grid is tested once, the framing's points stay few; a block is 2% of the box, within the framing's 10% margin)"""


def content_points(volumes) -> np.ndarray:
    """World positions [m] of the centres of the blocks of each volume's grid (at most `CONTENT_BLOCKS` per axis)
    that hold a voxel denser than `CONTENT_SHARE` of the volume's densest: where its medium is. A volume of all
    zeros gives its box's corners."""
    import numpy as np

    from volren.sparse import SparseGrid

    points = []
    for v in volumes:
        top = float(v.density.max())
        if top <= 0:
            points.append(v.corners_world)
            continue
        shape = v.density.shape  # (z, y, x)
        starts = [np.arange(0, n, -(-n // CONTENT_BLOCKS)) for n in shape]
        if isinstance(v.density, SparseGrid):  # a block holds content if a brick of it holds a dense enough voxel
            mask = v.density.cell_ranges()[1] > CONTENT_SHARE * top  # cells of B voxels
            first = [np.minimum(s // v.density.brick, m - 1) for s, m in zip(starts, mask.shape, strict=True)]
            for axis, s in enumerate(first):
                mask = np.logical_or.reduceat(mask, s, axis=axis)
        else:
            mask = np.asarray(v.density) > CONTENT_SHARE * top
            for axis, s in enumerate(starts):
                mask = np.logical_or.reduceat(mask, s, axis=axis)
        z, y, x = np.nonzero(mask)
        # a block's centre in local [-1, 1]: (start + end) / 2 voxels
        local = [-1.0 + (s[i] + np.append(s[1:], n)[i]) / n for s, n, i in zip(starts[::-1], shape[::-1], (x, y, z),
                                                                                 strict=True)]
        homogeneous = np.stack([*local, np.ones_like(local[0])], axis=1)
        points.append((homogeneous @ np.asarray(v.to_world).T)[:, :3])
    return np.concatenate(points)


def framed_content(volumes, up, fov_y: float, aspect: float, eye_offset: float = 0.0) -> tuple:
    """(position, look_at, near, far) of the eye that frames a built-in volume scene when no camera is given (``volren
    render --scene``, `volren.render` of a name): `framed_eye` on `content_points`, so the medium, not its box, fills
    the view. Framing the boxes' corners left the plume a sixth of the width and the phantom's ellipsoid two thirds
    of the height (its box's near corners set the distance)."""
    return framed_eye(content_points(volumes), up, fov_y, aspect, eye_offset=eye_offset)
