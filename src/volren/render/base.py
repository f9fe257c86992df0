"""The renderer interface: ``render(scene, views, frame) -> Frame``; subclasses supply the per-view pass."""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any, ClassVar

import numpy as np

from volren.camera import Camera
from volren.device import check_allocation, resolve_device
from volren.errors import VolrenError, VolrenWarning
from volren.kernels.common import INF, ViewBuffers
from volren.render.compositing.surface_light import (
    AO_COARSE,
    AO_CONE_RAYS,
    AO_RAYS,
    SH_AO_METHODS,
    SURFACE_LIGHT_MAP,
    SurfaceLight,
    surface_light,
)
from volren.render.compositing.surfaces import check_user_depth, trace_surfaces, view_buffers
from volren.render.frame import Frame, PassClock, Stats
from volren.render.gi.ambient import AmbientGI, GIConfig
from volren.render.lightmap import LightMapCache
from volren.render.marching.modes import check_mode, iso_range_message, mode_index
from volren.render.streaming import update_streams
from volren.scene import Scene
from volren.upload import DeviceScene, camera_struct, only_lights_differ, upload_lights, upload_scene


def frame_seed(seed: int, frame: int) -> int:
    """A 31-bit RNG seed per (seed, frame), so jittered frames differ and the same inputs repeat bit for bit."""
    return (seed * 1_000_003 + frame * 7_919 + 12_345) % (2**31 - 1)


OIT_SCHEMES = ("tiled", "pixel-rt", "pixel-sort")
MAX_OIT_K = 16
"""layers a pixel keeps in registers (`volren.render.compositing.oit.LayerIds`)"""

MAX_MESH_LAYERS = 64
"""Cap on K of the mesh k-buffer: K x 20 bytes per pixel; paper 000 §3.3 keeps a few layers."""
MAX_SAMPLES = 65536
"""Cap on V and L: kernels count steps in 32-bit ints, and more samples than this per diagonal buys nothing."""


def check_transmittance_threshold(value: float) -> None:
    if not 0 <= value < 1:
        raise VolrenError(f"min_transmittance (early termination) must lie in [0, 1), got {value}")


def check_sample_count(name: str, value: int) -> None:
    if int(value) != value or not 1 <= value <= MAX_SAMPLES:
        raise VolrenError(f"{name} must be an integer in [1, {MAX_SAMPLES}], got {value}")


def check_scene_mode(scene: Scene, mode: str) -> None:
    """Refuse what the sci-vis modes do not composite: translucent mesh layers (blended by "over" between march
    pieces) and boxes overlapping along a ray (marched jointly as DVR, `oit.march_joint`)."""
    if mode == "dvr":
        return
    if any(getattr(o, "alpha", 1.0) < 1.0 for o in scene.opaque):
        raise VolrenError(f"mode {mode} draws no translucent meshes (mesh alpha < 1): use mode dvr")
    boxes = [(v.corners_world.min(axis=0), v.corners_world.max(axis=0)) for v in scene.volumes]
    for i, (lo_a, hi_a) in enumerate(boxes):
        for lo_b, hi_b in boxes[i + 1:]:
            if np.all(lo_a < hi_b) and np.all(lo_b < hi_a):
                raise VolrenError(f"mode {mode} marches one box at a time and two volumes' bounding boxes overlap: "
                                  "use mode dvr")


@dataclass(frozen=True)
class LightMapMarchConfig:
    """Settings every light-map-lit ray marcher shares (DSSRM, CMSRM, CACRM): the papers' METHOD:V:L."""

    samples: int = 360
    """V (N_max for the cube methods): at most this many view samples across a box diagonal"""
    light_samples: int = 96
    """L: at most this many samples across the box diagonal on each light-map ray"""
    light_grid: int | None = None
    """light-map voxels on the longest axis; None = half the density resolution"""
    seed: int = 0
    min_transmittance: float = 1e-3
    """early ray termination threshold"""
    gi: GIConfig = GIConfig()  # noqa: RUF009 (frozen, so one shared default is safe)
    """ambient global illumination (paper 000 §3.2); off by default (constant ambient)"""
    reuse_light_map: bool = True
    """skip the light-map pass while what the map depends on (lights, volumes, L, GI on) is what it was last
    computed with (`volren.render.lightmap.LightMapCache`); False recomputes it every frame (benchmarks that time
    the pass per frame, as the papers' tables do)"""
    oit: str = "tiled"
    """how each pixel finds the boxes its ray meets (`volren.render.compositing.oit`): tiled (paper 000 §3.4's tiled
    k-buffer), pixel-rt (per-pixel BVH ray queries, paper 001 §3.4) or pixel-sort (every box tested per pixel)"""
    oit_k: int = 16
    """K: at most this many boxes per pixel (and per tile), the nearest; farther boxes on the ray are dropped. 16:
    on `instances-overlap --count 36` (rays cross up to 12 boxes) K = 8 scores 20-23 dB under K = 12 and 16, which
    cost the same (work grows with the boxes a ray meets, not with K; issue 19)"""
    mesh_layers: int = 4
    """K of the mesh k-buffer (paper 000 §3.3): translucent mesh layers kept per pixel, the nearest"""
    skip_empty: bool = True
    """empty-space skipping: the march leaves out steps in empty cells of the max-density grid (same image)"""
    ao_rays: int = AO_RAYS
    """surfaces' AO rays per point that samples the whole hemisphere (in or beside a volume's occupied box)"""
    ao_cone_rays: int = AO_CONE_RAYS
    """surfaces' AO rays per point that sees the volumes' occupied boxes in a cone (`surface_light.box_cone`)"""
    mode: str = "dvr"
    """dvr (volume rendering), mip (maximum intensity projection), mida (maximum intensity difference accumulation)
    or iso (shaded isosurface at ``iso_value``): `volren.render.marching.modes`"""
    iso_value: float = 0.5
    """[density, the grid's units] V of mode iso: the first crossing of this density along the ray (a CT loaded
    with a Hounsfield ``value_range`` (lo, hi) holds (HU - lo) / (hi - lo))"""

    def __post_init__(self) -> None:
        if (isinstance(self.mesh_layers, bool) or int(self.mesh_layers) != self.mesh_layers
                or not 1 <= self.mesh_layers <= MAX_MESH_LAYERS):
            raise VolrenError(f"mesh_layers (K of the mesh k-buffer) must be an integer in [1, {MAX_MESH_LAYERS}], "
                              f"got {self.mesh_layers}")
        if self.oit not in OIT_SCHEMES:
            raise VolrenError(f"oit must be one of {', '.join(OIT_SCHEMES)}, got '{self.oit}'")
        if isinstance(self.oit_k, bool) or int(self.oit_k) != self.oit_k or not 1 <= self.oit_k <= MAX_OIT_K:
            raise VolrenError(f"oit_k (K) must be an integer in [1, {MAX_OIT_K}], got {self.oit_k}")
        if not isinstance(self.gi, GIConfig):
            raise VolrenError(f"gi must be a GIConfig, got {type(self.gi).__name__}")
        check_sample_count("samples (V)", self.samples)
        check_sample_count("light samples (L)", self.light_samples)
        check_transmittance_threshold(self.min_transmittance)
        check_sample_count("ao_rays", self.ao_rays)
        check_sample_count("ao_cone_rays", self.ao_cone_rays)
        check_mode(self.mode, self.iso_value)
        if self.mode in ("mip", "iso") and self.gi.on:
            raise VolrenError(f"mode {self.mode} reads no ambient GI: --gi would do nothing")


class Renderer:
    """Base class. A subclass has a frozen config dataclass and implements ``_render_view``."""

    name: ClassVar[str] = ""
    needs_volumes: ClassVar[bool] = True
    translucent_meshes: ClassVar[bool] = False
    """whether the method blends meshes with alpha < 1 (paper 000 §3.3); the others refuse such scenes"""

    def __init__(self, config: Any, device: str = "auto") -> None:
        self.config = config
        self.device = resolve_device(device)
        self._device_scene: DeviceScene | None = None
        self._upload_key: tuple[int | None, bool, bool] | None = None
        self.bricked = True
        """densities uploaded as bricks (issue 41 item 1); False uploads them dense, the same image: only the
        equality tests and benchmarks set it, to compare the two"""
        self.stream_wait = True
        """a streamed volume's frame waits for the bricks it needs (``render``, ``animate``); False draws what is
        resident and lets the rest come over the next frames (``serve``, the notebook viewer: a tick never waits)"""
        self._views: list[Camera] = []
        self.on_bricks: Callable[[int, int], None] | None = None
        """Progress hook of a streamed volume's wait: (bricks come, bricks asked for)."""
        self.on_rows: Callable[[int], None] | None = None
        """Progress hook: called with the number of image rows the view pass just finished."""
        self._targets: list[ViewBuffers] = []
        self._target_sizes: list[tuple[int, int]] = []
        self._settings_of: tuple[Any, dict[str, Any]] | None = None

    def _view_targets(self, views: list[Camera]) -> list[ViewBuffers]:
        """Each view's render targets, kept from the last frame while the view sizes stay and cleared as
        `view_buffers` makes them: a fresh 480x270 set cost 1.5 ms of CPU per view and frame, clearing one 0.08 ms."""
        sizes = [(c.width, c.height) for c in views]
        if sizes != self._target_sizes:
            self._targets, self._target_sizes = [view_buffers(c, self.device) for c in views], sizes
            return self._targets
        for b in self._targets:
            b.image.zero_()
            b.depth.zero_()
            b.occluder_color.zero_()
            b.occluder_depth.fill_(INF)
        return self._targets

    def release_views(self) -> None:
        """Drop what is sized by the last frame's views (render targets, a subclass's per-view history), keeping what
        belongs to the scene (its upload, light map, majorants): the next frame allocates them afresh. `volren serve`
        calls this once its last viewer has left (issue 44 item 6: 16 full-HD viewers' buffers stayed held)."""
        self._targets, self._target_sizes = [], []

    def _settings(self) -> dict[str, Any]:
        """The config as a dict, converted once per config (``asdict`` of the nested GI config took ~1 ms a frame)."""
        if self._settings_of is None or self._settings_of[0] is not self.config:
            self._settings_of = (self.config, asdict(self.config))
        return dict(self._settings_of[1])

    def _upload(
        self, scene: Scene, clock: PassClock, light_grid: int | None = None, mip_levels: bool = False
    ) -> DeviceScene:
        """The scene on the device, uploaded once per scene object (the cache holds the scene, so ids stay valid); a
        scene that differs from the last only in its lights (`volren serve`'s light drag) uploads only the lights."""
        ds = self._device_scene
        key = (light_grid, mip_levels, self.bricked)
        if ds is not None and ds.scene is not scene and self._upload_key == key and only_lights_differ(ds.scene, scene):
            with clock.measure("upload_lights"):
                self._device_scene = upload_lights(ds, scene)
            return self._device_scene
        if ds is None or ds.scene is not scene or self._upload_key != key:
            with clock.measure("upload"):
                ds = upload_scene(scene, self.device, light_grid, mip_levels, bricked=self.bricked)
            self._device_scene, self._upload_key = ds, key
        if ds.streams:  # this frame's bricks of the streamed volumes, before anything samples them
            with clock.measure("stream"):
                marched, ancestors = self._stream_levels(ds)
                self._frame_info["stream"] = update_streams(ds, self._views, self.stream_wait, self.on_bricks,
                                                            marched, ancestors)
        return ds

    def _stream_levels(self, ds: DeviceScene) -> tuple[list[int] | None, bool]:
        """Which bricks of a streamed volume this method reads besides the footprint's level
        (`volren.stream.lod.frame_needs`): per volume a level it marches (None: none), and whether it reads a
        brick's ancestors too. Each sample here reads level 0, drawing what is not resident from coarser bricks."""
        return None, False

    def _prepare(self, scene: Scene, clock: PassClock, frame: int) -> DeviceScene:
        """Per-frame passes shared by all views (upload, light map, ...)."""
        return self._upload(scene, clock)

    def _render_view(
        self, ds: DeviceScene, cam: Camera, view: int, frame: int, buffers: ViewBuffers, clock: PassClock
    ) -> None:
        raise NotImplementedError

    def _surface_light(self, ds: DeviceScene) -> SurfaceLight | None:
        """How this frame's volumes shade the opaque surfaces (`surface_light`); None: they do not."""
        return None

    def _render_views(
        self, ds: DeviceScene, views: list[Camera], frame: int, targets: list[ViewBuffers], clock: PassClock
    ) -> None:
        """Render every view into its buffers; methods that share work between views override this."""
        for v, (cam, buffers) in enumerate(zip(views, targets, strict=True)):
            self._render_view(ds, cam, v, frame, buffers, clock)

    def render(
        self,
        scene: Scene,
        views: Sequence[Camera],
        frame: int = 0,
        *,
        occluder_depth: Sequence[np.ndarray | None] | None = None,
    ) -> Frame:
        """Render ``frame`` of ``scene`` for every view. ``occluder_depth`` optionally gives per view a linear depth
        image (H, W) of opaque geometry drawn elsewhere (+inf where none): volumes are clipped there."""
        views = list(views)
        if not views:
            raise VolrenError("render needs at least one view")
        if self.needs_volumes and not scene.volumes:
            raise VolrenError(f"method '{self.name}' renders volumes and scene '{scene.name}' has none")
        if not self.translucent_meshes and any(getattr(o, "alpha", 1.0) < 1.0 for o in scene.opaque):
            raise VolrenError(f"method '{self.name}' draws no translucent meshes (mesh alpha < 1): use reference, "
                              "dssrm, cmsrm or cacrm")
        user_depth = list(occluder_depth) if occluder_depth is not None else [None] * len(views)
        if len(user_depth) != len(views):
            raise VolrenError(f"got {len(user_depth)} depth image(s) for {len(views)} view(s)")
        user_depth = [None if z is None else check_user_depth(z, c, v)
                      for v, (z, c) in enumerate(zip(user_depth, views, strict=True))]
        # RGBA + depth and the surface colour + depth on the device, and host copies of the first two.
        pixels = sum(c.width * c.height for c in views)
        check_allocation(pixels * (40 if self.device == "cpu" else 60), self.device, f"{len(views)} view image(s)")
        clock = PassClock(self.device)
        self._frame_info: dict[str, Any] = {}
        self._views = views
        ds = self._prepare(scene, clock, frame)
        # what the density costs on the device (issue 41 items 1 and 4): memory goes with the resident bricks
        self._frame_info["bricks"] = {"active": ds.active_bricks, "pool_bytes": ds.pool_bytes}
        targets = self._view_targets(views)
        surface = self._surface_light(ds) if scene.opaque else None
        for v, (cam, buffers) in enumerate(zip(views, targets, strict=True)):
            if scene.opaque or user_depth[v] is not None:
                with clock.measure("surfaces"):
                    trace_surfaces(ds, camera_struct(cam), cam, user_depth[v], buffers, clock.counters, surface)
        self._render_views(ds, views, frame, targets, clock)
        with clock.measure("readback"):
            # copies: the targets are this renderer's, overwritten by its next frame
            images = [b.image.numpy().copy() for b in targets]
            depths = [b.depth.numpy().copy() for b in targets]
        for d in depths:
            d[d >= 1e29] = np.inf
        settings = {"views": len(views), "resolution": [[c.width, c.height] for c in views], **self._settings()}
        stats = Stats(self.device, self.name, settings, clock.times_ms, clock.counter_values(), self._frame_info)
        return Frame(images, depths, stats, frame, background=scene.background, scene_name=scene.name)


class LightMapRenderer(Renderer):
    """A ray marcher shaded from the light map (DSSRM, CMSRM, CACRM): its lighting passes are the light map and,
    with ``config.gi`` on, the ambient GI passes, whose state persists across frames (and animated densities)."""

    def __init__(self, config: LightMapMarchConfig, device: str = "auto") -> None:
        super().__init__(config, device)
        self._gi: AmbientGI | None = None
        self._light_map = LightMapCache()
        self._peak_of: tuple[DeviceScene, float] | None = None
        """(uploaded scene, 1 / its largest density) for MIP's and MIDA's intensity (`_mode_params`)"""
        self.region_light_stats: tuple[dict[str, float], dict[str, int]] = ({}, {})
        """the last `region_light_map`'s pass times and work counters"""
        self.light_map_total: np.ndarray | None = None
        """data-parallel rendering (issue 43): the light map of the whole volume, the sum of every region's
        `region_light_map` (optical depth adds), which this region's marches read; None: its own"""

    def _reads_light_map(self, scene: Scene) -> bool:
        return not (self.config.mode in ("mip", "iso") and not self.config.gi.on and not scene.opaque)

    def region_light_map(self, scene: Scene, frame: int = 0) -> np.ndarray | None:
        """Data-parallel rendering (issue 43): the light-map pass of ``scene``, whose volume is a region
        (`volren.scene.Volume.owned_cells`), and its map, each node's sigma_bar = tau / s summed over this region's
        samples only. Summed over the regions (optical depth adds along each node's path: every sample of the
        one-process march is one region's), it is the whole volume's map: give the sum as ``light_map_total`` before
        `render`.
        None where nothing reads a light map, or where the pass's inputs are those of the last call (the sum given
        since still holds)."""
        if not self._reads_light_map(scene) or not scene.lights:  # no lights (channels glow): nothing to sum
            return None
        clock = PassClock(self.device)
        self._frame_info, self._views = {}, []
        ds = self._upload(scene, clock, self.config.light_grid)
        ds.skip_empty = self.config.skip_empty
        ran = self._light_map.update(ds, self.config.light_samples, clock, self.config.gi.on,
                                     self.config.reuse_light_map)
        self.region_light_stats = (clock.times_ms, clock.counter_values())
        return ds.lightmap.numpy().copy() if ran else None

    def _lighting(self, ds: DeviceScene, clock: PassClock) -> None:
        ds.skip_empty = self.config.skip_empty  # read by this frame's marches (`DeviceScene.medium`)
        check_scene_mode(ds.scene, self.config.mode)
        gi = self.config.gi
        if not self._reads_light_map(ds.scene):
            return  # nothing reads the light map: MIP is unlit, iso shades unshadowed (13 s of a 640^3 MIP frame)
        if self.light_map_total is None:
            self._light_map.update(ds, self.config.light_samples, clock, gi.on, self.config.reuse_light_map)
        else:  # a data-parallel region: its pass ran in `region_light_map`; the regions' sum replaces its map
            with clock.measure("light_map_total"):
                ds.lightmap.assign(self.light_map_total)
        if not gi.on:
            return
        if self._gi is None or not self._gi.fits(ds, gi):
            self._gi = AmbientGI(gi, ds, self.config.seed)
        self._frame_info["gi"] = self._gi.update(ds, self.config.light_samples, clock)

    def _mode_params(self, params: Any, ds: DeviceScene) -> Any:
        """Fill the mode fields of a `MarchParams`: the mode, V and 1 / the scene's largest density (cached per
        uploaded scene; 1 for an all-zero scene)."""
        if self._peak_of is None or self._peak_of[0] is not ds:
            peak = max(float(np.max(v.density)) for v in ds.scene.volumes)
            self._peak_of = (ds, 1.0 / peak if peak > 0 else 1.0)
            if self.config.mode == "iso":
                floor = min(float(np.min(v.density)) for v in ds.scene.volumes)
                message = iso_range_message(self.config.iso_value, floor, peak)
                if message:
                    warnings.warn(message, VolrenWarning, stacklevel=2)
        params.mode = mode_index(self.config.mode)
        params.iso_value = self.config.iso_value
        params.inv_max = self._peak_of[1]
        return params

    def _surface_light(self, ds: DeviceScene) -> SurfaceLight:
        """Shadows from this frame's light map (cross-volume with GI on); AO from the GI grid's SH coefficients near
        the volumes where they are converged per voxel (`SH_AO_METHODS`), else from coarse transmittance rays."""
        c = self.config
        sh = self._gi if c.gi.method in SH_AO_METHODS else None
        return surface_light(ds, SURFACE_LIGHT_MAP, c.light_samples, c.ao_rays, max(1, c.light_samples // AO_COARSE),
                             cross_volume=c.gi.on, sh=None if sh is None else sh.buffers.sh,
                             order2=0 if sh is None else c.gi.order**2, cone_rays=c.ao_cone_rays)

    @property
    def gi_state(self) -> AmbientGI | None:
        """The GI lighting grids of the last frame (None with GI off)."""
        return self._gi
