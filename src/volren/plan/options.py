"""The names, defaults and limits of a render's options (spelled out so that building the command-line parser
imports no renderer, Warp or numpy), the error a bad one raises and the one warning line every part of a run says."""

from __future__ import annotations

import sys

from volren.errors import VolrenError
from volren.framing import DEFAULT_EYE  # noqa: F401  (the default camera position; a volume file is framed from it)

# Building the parser imports no renderer, Warp or numpy (`volren --help` and refusals answer at once), so the names
# its choices and help list are spelled out here; tests/test_api.py checks they equal their sources'.
METHOD_NAMES = ("dssrm", "cmsrm", "cacrm", "reference", "fog", "vpt")
"""`volren.render.METHODS`"""
GI_METHOD_NAMES = ("none", "major", "prt", "restir", "sresir", "brute")
"""`volren.render.gi.ambient.GI_METHODS`"""
TF_PRESET_NAMES = ("ct-bone", "ct-muscle", "ct-vessels", "smoke")
"""`volren.transfer.PRESETS`"""
TONEMAPS = ("none", "reinhard", "aces")
"""`volren.imageio.TONEMAPS`"""
SCENE_NAMES = ("smoke", "cloud", "phantom", "multi", "instances", "instances-overlap", "smoke-floor", "fire",
               "hall", "courtyard", "dynamic")
"""`volren.data.BUILTIN_SCENES`, then `volren.data.fog_scenes.FOG_SCENES`"""
FOG_SCENE_NAMES = SCENE_NAMES[-3:]
"""`volren.data.fog_scenes.FOG_SCENES`"""

MAX_EXPOSURE = 64.0
"""[stops] beyond this every pixel is black or white, and 2**exposure overflows soon after."""

MAX_IMAGE_SIDE = 16384
"""[px] --width and --height: beyond any display, and a typo for a smaller number far more often than meant."""
MAX_VIEW_PIXELS = 8192 * 8192
"""[px] --width x --height: `volren.camera.MAX_PIXELS`"""
HOST_BYTES_PER_PIXEL = 20
"""Each finished frame's host copies, kept until stats.json is written: float32 RGBA and depth."""
FROXEL_BYTES = 16
"""fog froxel: one vec4 in each of the lighting, history and integrated grids."""

DEFAULT_SCENE = "smoke"
DEFAULT_RESOLUTION = 64
"""voxels per axis of a built-in volume scene (render, animate; demo: 128)"""
SCENE_COUNT = 16
"""instances in a scene of several (`volren.data.COUNTED_SCENES`) that ``volren render --scene`` and `render` of its
name build without ``--count``"""
ANIMATION_FPS = 30.0
"""frames per second of scene time for animated scenes rendered with --frames"""
ANIMATE_FRAMES = 60
"""``volren animate``'s --frames unless a --volume sequence gives its length"""


class CliError(VolrenError):
    """A bad command-line value."""


_warned: set[str] = set()
"""the warnings printed by this command (`main` empties it): each is said once"""


def warn(message: str) -> None:
    """One ``volren: warning: ...`` line on stderr, once per command however often the cause recurs."""
    if message not in _warned:
        _warned.add(message)
        print(f"volren: warning: {message}", file=sys.stderr)


def check_method(method: str) -> None:
    if method not in METHOD_NAMES:
        raise CliError(f"unknown method '{method}': choose from {', '.join(METHOD_NAMES)}")


def check_scene_name(name: str | None) -> None:
    if name is not None and name not in SCENE_NAMES:
        raise CliError(f"--scene: unknown scene '{name}': choose from {', '.join(SCENE_NAMES)}")
