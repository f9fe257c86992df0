"""Quality presets: ``interactive | default | high``, a frozen mapping from (quality, method) to config fields.

``default`` is each method's own config defaults (the papers' settings, e.g. DSSRM:360:96). ``interactive`` is what
`volren serve` starts with: sized so one 480x270 view of the default scene (smoke 64^3, DSSRM) renders at >= 10 frames
per second on two CPU cores (measured in docs/BENCHMARKS.md, "interactive"). ``high`` is for stills. Flags given on
the command line (``--samples`` ...) override the preset's fields.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

from volren.errors import VolrenError

QUALITIES = ("interactive", "default", "high")
DEFAULT_QUALITY = "default"


def _frozen(table: dict[str, dict[str, dict[str, Any]]]) -> Mapping[str, Mapping[str, Mapping[str, Any]]]:
    return MappingProxyType({q: MappingProxyType({m: MappingProxyType(f) for m, f in by.items()})
                             for q, by in table.items()})


_LIGHT_MAP_INTERACTIVE = {"samples": 160, "light_samples": 48, "light_grid": 32, "min_transmittance": 0.01}
"""V:L = 160:48, a 32^3 light grid, early termination at T < 1% (the light map kept while scene and light stand
still, as in every preset: `LightMapMarchConfig.reuse_light_map`).
Measured on the smoke 64^3 at 480x270 against the reference (docs/BENCHMARKS.md, "interactive"): 52.2 dB (default
360:96: 52.3 dB) for 0.66x its CPU time per frame (47.5 against 72.5 ms, both with empty-space skipping)."""
_LIGHT_MAP_HIGH = {"samples": 720, "light_samples": 192, "light_grid": 128, "min_transmittance": 1e-4}
"""The light grid is what limits the light-map methods against the reference: on the smoke 64^3 at 480x270 a 64^3
grid gave 63.5 dB where the default (half the density, 32^3) gave 52.3 dB; this preset 75.3 dB (1.9 s a frame on the
CPU). 128 is the papers' grid for 256^3 densities."""

QUALITY_PRESETS = _frozen({
    "interactive": {
        "dssrm": _LIGHT_MAP_INTERACTIVE,
        "cmsrm": _LIGHT_MAP_INTERACTIVE,
        "cacrm": _LIGHT_MAP_INTERACTIVE,
        "fog": {"tile": 16, "slices": 64},
        "vpt": {"spp": 1, "max_bounces": 1},
        "reference": {},
    },
    "default": {m: {} for m in ("dssrm", "cmsrm", "cacrm", "fog", "vpt", "reference")},
    "high": {
        "dssrm": _LIGHT_MAP_HIGH,
        "cmsrm": _LIGHT_MAP_HIGH,
        "cacrm": _LIGHT_MAP_HIGH,
        "fog": {"tile": 4, "slices": 256},
        "vpt": {"spp": 32, "max_bounces": 4},
        "reference": {},
    },
})
"""quality -> method -> config fields that differ from the method's defaults (the reference is the ground truth at
every quality). Interactive fog (16 px froxels, 64 slices) on ``hall`` at 480x270: 17.8 fps against 11.0, 44.2 dB
against the default's image (the ray-cast surfaces take most of its frame); interactive VPT (1 path per pixel, one
bounce): 35.2 fps against 6.0 (docs/BENCHMARKS.md, "interactive")."""


def quality_options(method: str, quality: str) -> dict[str, Any]:
    """The config fields ``quality`` sets for ``method`` (a copy; empty for ``default`` and unlisted methods)."""
    from volren.render import METHODS

    if quality not in QUALITY_PRESETS:
        raise VolrenError(f"unknown quality '{quality}': choose from {', '.join(QUALITIES)}")
    if method not in METHODS:
        raise VolrenError(f"unknown method '{method}': choose from {', '.join(METHODS)}")
    return dict(QUALITY_PRESETS[quality].get(method, {}))


def quality_config(method: str, quality: str = DEFAULT_QUALITY, **overrides: Any) -> Any:
    """``method``'s config at ``quality``, with ``overrides`` (config fields) on top."""
    from volren.render import METHODS

    options = quality_options(method, quality)
    config_cls = METHODS[method][1]
    unknown = sorted(set(overrides) - {f.name for f in dataclasses.fields(config_cls)})
    if unknown:
        raise VolrenError(f"method '{method}' has no setting {', '.join(unknown)}")
    return config_cls(**{**options, **overrides})
