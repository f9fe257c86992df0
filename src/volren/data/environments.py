"""Built-in environment maps: a procedural sky (equirectangular, `volren.scene.Environment`'s convention) whose
directional variation makes ambient GI visible: a blue zenith, a bright horizon, a dark ground and a warm glow
around the sun (towards the built-in scenes' light)."""

from __future__ import annotations

import numpy as np

from volren.scene import Environment
from volren.sh import equirect_directions

SUN = np.array([0.5, 1.0, 0.35]) / np.linalg.norm([0.5, 1.0, 0.35])
"""towards the sun: the built-in scenes' light travels along -SUN"""
ZENITH, HORIZON, GROUND, GLOW = (0.10, 0.16, 0.32), (0.35, 0.38, 0.42), (0.06, 0.05, 0.04), (1.6, 1.1, 0.6)


def sky_environment(height: int = 64, width: int = 128) -> Environment:
    """The procedural sky as an ``height x width`` equirect map (linear radiance)."""
    d, _ = equirect_directions(height, width)
    y = d[..., 1:2]
    up = np.clip(y, 0, 1) ** 0.5
    sky = (1 - up) * np.asarray(HORIZON) + up * np.asarray(ZENITH)
    ground = np.asarray(GROUND) + (np.asarray(HORIZON) - np.asarray(GROUND)) * np.exp(8 * np.minimum(y, 0))
    image = np.where(y >= 0, sky, ground)
    image = image + np.asarray(GLOW) * np.exp(12 * (d @ SUN - 1))[..., None]
    return Environment(image=image.astype(np.float32))


ENVIRONMENTS = {"sky": sky_environment}
