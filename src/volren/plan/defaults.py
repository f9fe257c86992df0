"""The defaults every front end gives a loaded file and a built-in scene (`volren.load`, ``volren render
--volume``, ``volren serve``, batch jobs): a file's opacity from its own box, its fire's kelvin reading and emission
scale, and the instances of a scene of several."""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from volren.data.loaders import LoadedVolume
    from volren.scene import Volume

SCENE_COUNT = 16
"""instances in a scene of several (`volren.data.COUNTED_SCENES`) that ``volren render --scene`` and `render` of its
name build without ``--count``"""


BOX_OPTICAL_DEPTH = 20.0
"""K: a loaded volume's default optical depth at density 1 (the top of its value mapping) across its box's longest
side, whatever its units (`box_density_scale`). 20 keeps the density_scale of 10 /m that files had before on the
2 m box of a file that stores no placement (so those render as before), shows a sparse specimen (a ball filling a
fifth of the box's side at density 1: optical depth 4), and makes a dense block opaque but not a solid wall of
one voxel (a 64-voxel side: 0.3 a voxel)."""


def box_density_scale(to_world: Any) -> float:
    """[1/m] a loaded volume's default density_scale: `BOX_OPTICAL_DEPTH` / its box's longest side, so density 1
    has the same optical depth across the box in micrometres as in metres (ParaView's scalar opacity unit distance
    relative to the data's bounds; the rule the channels of a multi-channel file follow with their own constant)."""
    from volren.scene import box_longest_side

    return BOX_OPTICAL_DEPTH / box_longest_side(to_world)


def volume_from_file(loaded: LoadedVolume, name: str, **material: Any) -> Volume:
    """A loaded file as a Volume (`volren load`, ``volren render --volume``): its placement, its emission grid, and
    its value range when that is Hounsfield units (CT transfer functions classify by HU; a constant file, lo = hi,
    has no HU scale). Without a ``density_scale`` in ``material`` it is `box_density_scale` (its box sets its
    opacity, whatever the file's units); given, it is per metre as everywhere. An emission grid whose values look like
    kelvin (`volren.blackbody.kelvin_span`) is read as kelvin, temperature range (0, its hottest): T = v; else its
    values are relative, 0+ to max at 1000-3000 K."""
    from volren.blackbody import kelvin_span
    from volren.scene import Volume

    hu = loaded.hounsfield and loaded.value_range[1] > loaded.value_range[0]
    if material.get("density_scale") is None:
        material["density_scale"] = box_density_scale(loaded.to_world)
    if loaded.emission_source is not None and "temperature_range" not in material:
        span = kelvin_span(loaded.emission_source)
        if span is not None:
            material = {**material, "temperature_range": (0.0, span[1])}
    return Volume(loaded.density, loaded.to_world, name=name, value_range=loaded.value_range if hu else None,
                  emission_grid=loaded.emission_source, **material)


def flame_defaults(volumes: tuple, lights, environment) -> tuple:
    """A file's volumes with the default emission scale of their emission grids (`flame_emission_scale`, relative
    to the white W = sum(Y(directional irradiance)) / pi + Y(mean environment radiance) of these lights; W = 3 / pi,
    the default light's, where there is no light)."""
    import numpy as np

    from volren.blackbody import flame_emission_scale, luminance
    from volren.scene import DirectionalLight

    white = sum(float(luminance(lt.irradiance)) for lt in lights if isinstance(lt, DirectionalLight)) / math.pi
    white += float(luminance(environment.mean_radiance()))
    white = white if white > 0 else float(luminance(DirectionalLight().irradiance)) / math.pi
    out = []
    for v in volumes:
        if v.emission_grid is not None:
            voxel = abs(float(np.linalg.det(v.to_world[:3, :3]))) * 8.0 / v.density.size
            scale = flame_emission_scale(v.emission_u, v.density, v.density_scale, *v.temperature_range, voxel, white)
            v = dataclasses.replace(v, emission_scale=scale)
        out.append(v)
    return tuple(out)
