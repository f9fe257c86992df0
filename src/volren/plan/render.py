"""What a render is (`RenderPlan`, made by `plan_render` after every check) and how its frames are rendered and
written (`render_plan`): ``volren render`` and ``animate``, batch jobs and the Ray workers all go through it."""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

from volren.plan.options import (
    ANIMATE_FRAMES,
    ANIMATION_FPS,
    FOG_SCENE_NAMES,
    FROXEL_BYTES,
    HOST_BYTES_PER_PIXEL,
    MAX_EXPOSURE,
    MAX_IMAGE_SIDE,
    MAX_VIEW_PIXELS,
    CliError,
    _warned,
    check_method,
    check_scene_name,
    warn,
)
from volren.plan.renderer import iso_value_from_data, renderer_from_args, sequence_from_args
from volren.plan.scene import (
    EMPTY_ALPHA,
    THIN_BOX_DEPTH,
    _with_material,
    emission_reading,
    flame_defaults,
    scene_from_args,
)
from volren.plan.views import depth_images_from_args, views_from_args
from volren.plan.volume import _file_scene, _value_mapping, volume_sequence


def estimate_memory(args: argparse.Namespace, scene, views, method: str) -> int:
    """[bytes] the render's large buffers, all at once: every view's device image buffers (as the renderer counts
    them), every frame's host copies, cmsrm/cacrm cube maps of every view and volume, fog's three froxel grids."""
    from volren.render.marching.cmsrm import CUBE_TEXEL_BYTES

    pixels = sum(v.width * v.height for v in views)
    total = pixels * (40 + HOST_BYTES_PER_PIXEL * args.frames)
    if method in ("cmsrm", "cacrm"):
        from volren.render.marching.cubemap import face_size_cap

        sizes = [args.cube_size or face_size_cap(max(vol.density.shape)) for vol in scene.volumes]
        total += len(views) * sum(6 * size**2 for size in sizes) * CUBE_TEXEL_BYTES
    if method == "fog":
        tile, slices = args.froxel_size or 8, args.slices or 128
        froxels = sum(-(-v.width // tile) * -(-v.height // tile) for v in views) * (slices + 1)
        total += 3 * froxels * FROXEL_BYTES
    return total


def check_run_time(args: argparse.Namespace, scene, views, method: str) -> None:
    """Refuse, before any output, a render estimated to run longer than --max-minutes (`volren.estimates`)."""
    from volren.estimates import estimate_seconds, needs_estimate

    if not (math.isfinite(args.max_minutes) and args.max_minutes >= 0):
        raise CliError(f"--max-minutes must be >= 0 (0: no limit), got {args.max_minutes}")
    if args.max_minutes == 0 or not needs_estimate(views, args.frames):
        return
    probe = renderer_from_args(args, method)
    est = estimate_seconds(views, args.frames, lambda cam: probe.render(scene, [cam]))
    what = f"{len(views)} view(s) of {views[0].width}x{views[0].height} for {args.frames} frame(s) with {method}"
    if est.seconds > 60 * args.max_minutes:
        raise CliError(f"{what} would take about {est.seconds / 60:.0f} min on {probe.device} (a "
                       f"{est.probe[0]}x{est.probe[1]} probe took {est.probe_ms:.0f} ms), over --max-minutes "
                       f"{args.max_minutes:g}: render fewer or smaller views or frames, or raise --max-minutes")
    print(f"{what}: about {est.seconds / 60:.1f} min estimated on {probe.device}", file=sys.stderr)


def check_idle_flags(args: argparse.Namespace) -> None:
    """Refuse the flags that would do nothing in this run, and values outside the ranges --help gives (issue 22.7)."""
    given = lambda *names: [f"--{n.replace('_', '-')}" for n in names if getattr(args, n, None) is not None]  # noqa: E731
    if getattr(args, "volume", None) is None and (unused := given("shape", "dtype", "spacing", "units")):
        raise CliError(f"built-in scenes ignore {', '.join(unused)}: they say how to read a --volume file")
    scale = getattr(args, "mesh_scale", 1.0)
    if not (math.isfinite(scale) and scale > 0):
        raise CliError(f"--mesh-scale must be a positive number, got {scale:g}")
    mesh_flags = [flag for flag, value, default in (
        ("--mesh-alpha", getattr(args, "mesh_alpha", []), []), ("--mesh-scale", scale, 1.0),
        ("--mesh-translate", getattr(args, "mesh_translate", (0.0, 0.0, 0.0)), (0.0, 0.0, 0.0))) if value != default]
    if mesh_flags and not getattr(args, "mesh", None):
        raise CliError(f"{', '.join(mesh_flags)}: there is no --mesh to place")
    ipd = getattr(args, "ipd", None)
    if ipd is not None:
        if not (math.isfinite(ipd) and 0 <= ipd < 10):
            raise CliError(f"--ipd must lie in [0, 10) m, got {ipd:g}")
        if getattr(args, "views", "stereo") != "stereo":
            raise CliError(f"--ipd separates the eyes of --views stereo; --views {args.views} has none")
    background = getattr(args, "background", None)
    if background is not None and not all(math.isfinite(c) and c >= 0 for c in background):
        raise CliError(f"--background must be >= 0 in every channel, got {','.join(f'{c:g}' for c in background)}")
    if getattr(args, "seed", 0) < 0:
        raise CliError(f"--seed must be an integer >= 0, got {args.seed}")
    if args.width * args.height > MAX_VIEW_PIXELS:
        raise CliError(f"--width x --height is {args.width * args.height:,} pixels, over the {MAX_VIEW_PIXELS:,} "
                       "pixels a view may have")
    if getattr(args, "scene", None) in FOG_SCENE_NAMES and (unused := given("density_scale", "albedo")):
        raise CliError(f"fog scene '{args.scene}' has its own fog: {', '.join(unused)} would do nothing")


@dataclasses.dataclass
class RenderPlan:
    """What `plan_render` built for a render or animate run, and `frame`: frame i's scene and views (and the
    renderer's config). The in-process loop of `render_plan` and the batch engine's workers
    (`volren.distributed.engine`) both go through it, so a distributed run renders the same frames by construction."""

    args: argparse.Namespace
    method: str
    scene: object
    views: list
    renderer: object
    sequence: object
    played: object
    occluder_depth: list | None
    value_mapping: dict
    """stats.json's entries beside the scene and the command: ``value_mapping`` (`_value_mapping`), and the
    ``iso_value`` chosen from the data (`iso_value_from_data`)"""
    animated: bool
    walking: bool

    def __post_init__(self) -> None:
        self.base_config = self.renderer.config

    def frame(self, i: int) -> tuple:
        """Frame i's (scene, views), with the renderer's config set for it: an animated fog scene at i / fps, a
        volume sequence's frame i (the lights, geometry and environment the same objects), wandering viewers at
        i / fps, then animate's orbit, light orbit and transfer-function switch. Frame 0 is the planned scene."""
        args, scene, views = self.args, self.scene, self.views
        if self.animated and i:
            scene = scene_from_args(args, i / ANIMATION_FPS)
        if self.played is not None and i:  # the lights, geometry and environment stay the same objects
            volumes = _with_material(args, _file_scene(args, i).volumes)
            if getattr(args, "emission_scale", None) is None:  # each frame's flame by its own grids, as frame 0's
                volumes = flame_defaults(volumes, scene.lights, scene.environment)
            scene = dataclasses.replace(self.scene, volumes=volumes)
        if self.walking and i:
            views = views_from_args(args, i / ANIMATION_FPS, self.scene)
        if self.sequence is not None:
            from volren.animate import frame_config, frame_scene, frame_views

            scene = frame_scene(self.sequence, scene, i)
            views = frame_views(self.sequence, self.views, i)
            self.renderer.config = frame_config(self.sequence, self.base_config, i)
        return scene, views

    def render(self, i: int):
        """Frame i rendered (`frame`), as `Frame` with ``index`` i (its per-frame seeds)."""
        scene, views = self.frame(i)
        return self.renderer.render(scene, views, frame=i, occluder_depth=self.occluder_depth)


def check_render_args(args: argparse.Namespace, method: str) -> None:
    """`plan_render`'s checks that need no data (``volren render`` makes them first): the imports after them take
    seconds."""
    check_method(method)
    check_scene_name(getattr(args, "scene", None))
    if args.frames is not None and args.frames < 1:  # None: animate's default, set by plan_render
        raise CliError(f"--frames must be >= 1, got {args.frames}")
    for flag, side in (("--width", args.width), ("--height", args.height)):
        if not 1 <= side <= MAX_IMAGE_SIDE:
            raise CliError(f"{flag} must lie in [1, {MAX_IMAGE_SIDE}] pixels, got {side}")
    if not (math.isfinite(args.exposure) and abs(args.exposure) <= MAX_EXPOSURE):
        raise CliError(f"--exposure must be a number of stops in [-{MAX_EXPOSURE:g}, {MAX_EXPOSURE:g}]")
    check_idle_flags(args)
    workers = getattr(args, "workers", None)
    if workers is not None and workers < 1:
        raise CliError(f"--workers must be >= 1, got {workers}")
    if getattr(args, "gpus_per_worker", None) is not None and workers is None and args.ray_address is None:
        raise CliError("--gpus-per-worker shares a GPU among the workers of --workers or --ray-address: there are none")


def plan_render(args: argparse.Namespace, method: str) -> RenderPlan:
    """Every check of a render before any output (`check_render_args` first), then its scene, views and renderer;
    sets animate's default --frames. The run-time estimate (a probe render) is the last check."""
    check_render_args(args, method)
    from volren.animate import frame_config
    from volren.data.fog_scenes import ANIMATED_FOG_SCENES

    played = volume_sequence(args)
    if args.frames is None:
        args.frames = ANIMATE_FRAMES if played is None else len(played)
    if played is not None:
        if args.frames > len(played):
            raise CliError(f"--frames {args.frames}: the sequence {args.volume} has {len(played)} frames")
        played.check_start()  # the first two frames read and matched before any output
    scene = scene_from_args(args)
    value_mapping = _value_mapping(args)
    animated = getattr(args, "scene", None) in ANIMATED_FOG_SCENES
    walking = args.rig == "wander" and args.views not in ("mono", "stereo")
    views = views_from_args(args, scene=scene)
    occluder_depth = depth_images_from_args(args, len(views))
    renderer = renderer_from_args(args, method)
    value_mapping |= iso_value_from_data(args, scene, renderer)
    value_mapping |= emission_reading(args, scene)
    from volren.device import check_allocation

    check_allocation(estimate_memory(args, scene, views, method), renderer.device,
                     f"{len(views)} view(s) of {args.width}x{args.height} for {args.frames} frame(s) with {method}")
    sequence = sequence_from_args(args)
    if sequence is not None:
        frame_config(sequence, renderer.config, sequence.frames - 1)  # refuse a switch the method cannot take
    check_run_time(args, scene, views, method)  # the last check: it renders a probe
    return RenderPlan(args, method, scene, views, renderer, sequence, played, occluder_depth, value_mapping,
                      animated, walking)


def frame_prefix(args: argparse.Namespace, i: int) -> str:
    """What tells frame i's files apart in a run of several frames (none in a run of one)."""
    return f"frame{i:04d}_" if args.frames > 1 else ""


def write_plan_frame(plan: RenderPlan, frame, out: Path) -> list[Path]:
    """`write_frame` with the run's output flags: frame ``frame.index``'s files into ``out``."""
    from volren.output import write_frame

    args = plan.args
    return write_frame(frame, out, frame.background, exposure=args.exposure, tonemap=args.tonemap,
                       linear=args.save_linear, prefix=frame_prefix(args, frame.index))


def warn_empty_render(plan, frame) -> None:
    """One line when a --volume's render shows nothing (alpha under `EMPTY_ALPHA` in every view) though its box's
    optical depth is not under `THIN_BOX_DEPTH` (`warn_density` said why then; a density_scale of 0 asks for
    nothing; or a line was said already) and no transfer function chose what shows: the camera misses its box or the
    volume is too thin, and what to set for each."""
    import numpy as np

    from volren.scene import box_longest_side

    volumes = plan.scene.volumes
    if getattr(plan.args, "volume", None) is None or len(volumes) != 1 or _warned:
        return  # a line said already (an --iso-value outside the data, ...) says it best: one line
    if getattr(plan.renderer.config, "mode", "dvr") not in ("dvr", "mida"):
        return  # iso and mip show what their value and maximum make of it, not the density's opacity
    if getattr(plan.renderer.config, "transfer", None) is not None:
        return  # the transfer function chose what shows (ct-bone on a CT without bone is rightly empty)
    v = volumes[0]
    depth = float(v.density.max()) * v.density_scale * box_longest_side(v.to_world)
    if depth < THIN_BOX_DEPTH or max(float(np.max(im[..., 3])) for im in frame.images) >= EMPTY_ALPHA:
        return  # warn_density said why (all zero, too thin) or a density_scale of 0 asked for nothing
    warn(f"the render of volume '{v.name}' is empty (alpha under {EMPTY_ALPHA:g} in every view): the camera misses "
         "its box (check --camera-pos, --look-at, --fov) or it is too thin (raise --density-scale [1/m], now "
         f"{v.density_scale:.3g})")


@dataclasses.dataclass(frozen=True)
class Rendered:
    """What `render_plan` wrote into ``--out``."""

    frames: list
    """every frame, as rendered (`Frame`)"""
    files: list[Path]
    """the images and animate's MP4, as named in ``--out``"""
    stats: Path
    """stats.json in ``--out``"""
    wall: float
    """[s] rendering and writing the frames"""


def render_plan(plan: RenderPlan, command: str) -> Rendered:
    """The plan's frames rendered in this process and written, with stats.json (``command`` in it) and animate's MP4,
    into ``--out`` (written beside it and moved in when complete, `run_output`)."""
    from volren.animate import write_mp4
    from volren.imageio import composite, to_srgb8
    from volren.output import contact_sheet, run_output, write_stats
    from volren.progress import progress, reporter

    args, method = plan.args, plan.method
    frames, files, movie = [], [], []
    start = time.perf_counter()
    with run_output(args.out) as out:  # written beside --out, moved in when complete
        rows = args.frames * sum(v.height for v in plan.views)  # each view's image pass reports its rows
        with progress(f"{method} {plan.scene.name}", rows, always=args.frames > 1) as advance:
            plan.renderer.on_rows = advance
            plan.renderer.on_bricks = reporter(f"{plan.scene.name}: streaming bricks", "bricks")
            for i in range(args.frames):
                frame = plan.render(i)
                if i == 0:
                    warn_empty_render(plan, frame)
                if plan.sequence is not None:
                    shown = frame.images[0] if len(frame.images) == 1 else contact_sheet(frame.images)
                    movie.append(to_srgb8(composite(shown, frame.background), args.exposure, args.tonemap))
                files += write_plan_frame(plan, frame, out)
                frames.append(frame)
        wall = time.perf_counter() - start
        if plan.sequence is not None:
            files.append(write_mp4(out / "animation.mp4", movie, plan.sequence.fps))
        stats = write_stats(out, frames, {"scene": plan.scene.name, "command": command, **plan.value_mapping})
    return Rendered(frames, [args.out / f.name for f in files], args.out / stats.name, wall)
