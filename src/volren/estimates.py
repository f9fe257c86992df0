"""Up-front run-time estimate for a large render (issue 13 item 8): refuse before any output when it would run longer
than the user allows.

A probe renders the first view at a quarter of its size per side with a fresh renderer of the same method and
settings (so the real renderer's temporal state is untouched; kernels compile once for both), then extrapolates its
pass times: per-pixel passes with the pixel count, per-view passes (cube maps, tile passes, shadow frustum) with the
view count, per-frame passes (light map, GI, majorants, shared shadow grid) with the frame count. Small renders skip
the probe: below ``PROBE_ABOVE`` pixel-frames a render takes seconds to minutes on two CPU cores.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

from volren.camera import Camera
from volren.render.frame import Frame

PROBE_ABOVE = 20_000_000
"""pixel-frames (width x height x views x frames) above which the run time is estimated: 1080p stereo for 5 frames"""
PROBE_DIVISOR = 4
"""the probe renders the first view at 1 / 4 of its width and height (at least 16 pixels a side)"""
PER_FRAME_PASSES = frozenset({"light_map", "lighting", "accumulation", "majorants", "shadow_grid",
                              "fog_bake"})
"""passes computed once per frame for all views"""
PER_VIEW_PASSES = frozenset({"cube_march", "tile_cull", "tile_lod", "shadow_frustum"})
"""passes whose work follows a per-view structure (cube-map faces, the shadow frustum), not the pixel count"""


@dataclasses.dataclass(frozen=True)
class TimeEstimate:
    seconds: float
    probe: tuple[int, int]
    """the probe view's width and height"""
    probe_ms: float
    """the probe frame's total pass time"""


def estimate_seconds(views: Sequence[Camera], frames: int, render_probe: Callable[[Camera], Frame]) -> TimeEstimate:
    """Seconds the render of ``frames`` frames of ``views`` would take, extrapolated from one probe frame that
    ``render_probe`` renders for the given (smaller) camera."""
    first = views[0]
    probe = dataclasses.replace(first, width=max(16, first.width // PROBE_DIVISOR),
                                height=max(16, first.height // PROBE_DIVISOR))
    times = render_probe(probe).stats.times_ms
    pixel_ratio = sum(v.width * v.height for v in views) / (probe.width * probe.height)
    ms = 0.0
    for name, t in times.items():
        if name == "upload":
            ms += t / frames  # once per run
        elif name in PER_FRAME_PASSES:
            ms += t
        elif name in PER_VIEW_PASSES:
            ms += t * len(views)
        else:
            ms += t * pixel_ratio
    return TimeEstimate(ms * frames / 1e3, (probe.width, probe.height), sum(times.values()))


def needs_estimate(views: Sequence[Camera], frames: int) -> bool:
    return sum(v.width * v.height for v in views) * frames > PROBE_ABOVE
