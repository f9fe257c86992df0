"""What a renderer returns: per-view images and depth, plus stats (device-synchronised pass times, work counters)."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import warp as wp

from volren.device import counter_rows_for, synchronize

COUNTERS = ("density_samples", "light_samples", "lightmap_lookups", "rays", "shared_samples", "interleaved_samples",
            "shadow_rays", "shadow_voxels", "box_tests", "tile_box_tests", "bvh_queries", "ao_bvh_queries",
            "joint_rays", "skipped_steps", "light_skipped", "jumped_steps", "idle_runs")
"""Work counters gathered by the kernels (wp.atomic_add into one int64 array, indexed by position here):
density_samples: trilinear density fetches on view rays; light_samples: density fetches on rays towards lights
(light-map pass or the reference's per-sample shadow rays); lightmap_lookups: light-map fetches while shading;
rays: view rays that hit at least one volume box (CMSRM: texel rays marched, plus pixels marched directly);
shared_samples: density samples that reused the 8 voxels another ray fetched (CACRM's coupled eyes), so the voxel
gathers are density_samples - shared_samples; interleaved_samples: supplementary samples a CACRM ray took from the
voxels its 2x2 quad neighbours fetched (interleaved spatial reuse), on top of its density_samples; shadow_rays:
ray-traced light-visibility queries of the fog method (one per light and froxel, grid voxel or frustum froxel);
shadow_voxels: shadow-grid voxels re-traced this frame; box_tests: exact ray/box tests of pixel rays finding their
layers (multi-volume OIT, `volren.render.compositing.oit`: instances per pixel for pixel-sort, boxes the BVH reported
for pixel-rt, the tile's instances for tiled); tile_box_tests: the tiled k-buffer's phase-1 tests of tile rays against
the boxes its BVH reported; bvh_queries: the OIT's BVH ray queries (pixel-rt: one per pixel, tiled: one per tile;
Warp's query does not report the nodes it visits); ao_bvh_queries: the surfaces' AO rays, one BVH query each
(`volren.render.compositing.surface_light`); joint_rays: pixel rays that marched overlapping boxes jointly;
skipped_steps: view-ray steps of the light-map march left unsampled by empty-space skipping (with it off they would
be density_samples); light_skipped: steps of the light-map pass's rays towards lights left unsampled by empty-space
skipping (with it off they would be light_samples); jumped_steps: those of the skipped_steps that CACRM's idle runs
took in closed form under VSA (`volren.render.marching.cacrm.ramp_jump`) instead of one by one; idle_runs: the
runs of steps CACRM's coupled pair took with every live eye in empty space (`volren.render.marching.cacrm.idle_run`),
each a return to its full loop."""
(DENSITY_SAMPLES, LIGHT_SAMPLES, LIGHTMAP_LOOKUPS, RAYS, SHARED_SAMPLES, INTERLEAVED_SAMPLES, SHADOW_RAYS,
 SHADOW_VOXELS, BOX_TESTS, TILE_BOX_TESTS, BVH_QUERIES, AO_BVH_QUERIES, JOINT_RAYS, SKIPPED_STEPS,
 LIGHT_SKIPPED, JUMPED_STEPS, IDLE_RUNS) = range(len(COUNTERS))


@dataclass
class Stats:
    device: str
    method: str
    settings: dict[str, Any]
    times_ms: dict[str, float] = field(default_factory=dict)
    """wall time per pass, measured after a device synchronise"""
    counters: dict[str, int] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)
    """method-specific reports (e.g. CMSRM's per-volume scheme, LOD and cube-map memory)"""

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["times_ms"]["total"] = sum(self.times_ms.values())
        return d


@dataclass
class Frame:
    """One rendered frame: ``images[v]`` is float32 (H, W, 4) premultiplied linear RGBA, ``depths[v]`` the linear
    view depth [m] where the transmittance reached 1/2 (+inf where it never did)."""

    images: list[np.ndarray]
    depths: list[np.ndarray]
    stats: Stats
    index: int = 0
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """the scene's background (linear RGB), composited under the images when they are saved or shown"""
    scene_name: str = "scene"
    """the scene's name, stats.json's ``scene``"""

    def __repr__(self) -> str:
        """A summary, not the pixels: views and their size, method, device, time, scene."""
        sizes = sorted({f"{im.shape[1]}x{im.shape[0]}" for im in self.images})
        total = sum(self.stats.times_ms.values())
        return (f"Frame({len(self.images)} view(s) {', '.join(sizes)}, {self.stats.method} on {self.stats.device}, "
                f"{total:.1f} ms, frame {self.index}, scene {self.scene_name!r})")

    def save(self, out: str | Path, *, exposure: float = 0.0, tonemap: str = "none",
             linear: bool = False) -> list[Path]:
        """Write into folder ``out`` what ``volren render --out OUT`` writes for one frame (`volren.output`, the same
        writers): ``view{v}.png`` (sRGB after ``exposure`` [stops] and ``tonemap``), ``stereo.png`` for a pair,
        ``contact.png`` for more views, ``view{v}.npy`` linear images with ``linear``, and ``stats.json``; the
        files' paths, stats.json last."""
        from volren.output import run_output, write_frame, write_stats

        out = Path(out)
        with run_output(out) as staging:  # moved into ``out`` when complete, as the CLI does
            files = write_frame(self, staging, self.background, exposure=exposure, tonemap=tonemap, linear=linear)
            files.append(write_stats(staging, [self], {"scene": self.scene_name}))
        return [out / f.name for f in files]

    def srgb(self, *, exposure: float = 0.0, tonemap: str = "none") -> np.ndarray:
        """The frame as one display image, uint8 sRGB (H, W, 3): the view, or the views on a contact sheet (a stereo
        pair side by side, as stereo.png), as ``volren animate`` puts frames in its movie."""
        from volren.imageio import composite, to_srgb8
        from volren.output import contact_sheet

        shown = self.images[0] if len(self.images) == 1 else contact_sheet(self.images)
        return to_srgb8(composite(shown, self.background), exposure, tonemap)

    def show(self, *, exposure: float = 0.0, tonemap: str = "none") -> None:
        """Display `srgb`: inline in a Jupyter notebook, else in the system's image viewer (Pillow's ``show``:
        Pillow is installed with imageio, matplotlib would cost a second to import)."""
        from PIL import Image

        image = Image.fromarray(self.srgb(exposure=exposure, tonemap=tonemap))
        if _in_notebook():
            from IPython.display import display

            display(image)
        else:
            image.show()


def _in_notebook() -> bool:
    """Running in a Jupyter kernel (not a terminal IPython, whose shell has no kernel app)."""
    ipython = sys.modules.get("IPython")
    shell = ipython.get_ipython() if ipython is not None else None
    return shell is not None and "IPKernelApp" in shell.config


class PassClock:
    """Times named passes with a device synchronise on both ends and owns the frame's counters array."""

    def __init__(self, device: str) -> None:
        self.device = device
        self.times_ms: dict[str, float] = {}
        self.counters = wp.zeros((counter_rows_for(device), len(COUNTERS)), dtype=wp.int64, device=device)

    @contextmanager
    def measure(self, name: str) -> Iterator[None]:
        synchronize(self.device)
        start = time.perf_counter()
        yield
        synchronize(self.device)
        self.times_ms[name] = self.times_ms.get(name, 0.0) + (time.perf_counter() - start) * 1e3

    def counter_values(self) -> dict[str, int]:
        return {name: int(v) for name, v in zip(COUNTERS, self.counters.numpy().sum(axis=0), strict=True)}
