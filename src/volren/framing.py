"""Automatic framing, shared by every front end (``volren render --volume``, ``volren serve --volume``, `volren.render`
without views): the eye looks at a box's centre from the default direction, far enough that the whole box is in view.
Imports nothing heavy at the top (the command-line parser imports this module)."""

from __future__ import annotations

import math

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


def framed_eye(corners, up, fov_y: float, aspect: float, look_at=None, eye_offset: float = 0.0) -> tuple:
    """(position, look_at, near) of an eye that sees the box ``corners`` (an (N, 3) array [m]) whole: it looks at
    ``look_at`` (default: the box's centre) from the direction of `DEFAULT_EYE`, at `framing_distance`; ``near`` is
    0.01 m or a thousandth of that distance where less (a 100 um stack framed from 0.4 mm: 1 cm would clip it all)."""
    import numpy as np

    look_at = tuple(look_at or (corners.min(axis=0) + corners.max(axis=0)) / 2)
    direction = np.array(DEFAULT_EYE) / np.linalg.norm(DEFAULT_EYE)
    distance = framing_distance(corners, look_at, direction, up, fov_y, aspect, eye_offset)
    return tuple(np.array(look_at) + distance * direction), look_at, min(0.01, distance / 1000)
