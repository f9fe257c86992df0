"""A render's options in the command line's words: the argument types and the parser of ``volren demo | render |
animate``. The CLI adds its other commands to the same parser (its `build_parser`); batch jobs and Ray workers
parse a job's command line with `render_parser` (until they receive the plan as data)."""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Sequence
from pathlib import Path

from volren.plan.options import (
    ANIMATE_FRAMES,
    DEFAULT_RESOLUTION,
    DEFAULT_SCENE,
    GI_METHOD_NAMES,
    MAX_EXPOSURE,
    MAX_IMAGE_SIDE,
    MAX_VIEW_PIXELS,
    METHOD_NAMES,
    TF_PRESET_NAMES,
    TONEMAPS,
    CliError,
)
from volren.store import volume_path

NEGATIVE_NUMBERS = re.compile(r"^-\.?\d")
"""A value, not an option: what starts as a negative number does (``-1,-1,0``, ``-1e-3``, ``-.5``); the option's
type then says whether the rest is right, naming the flag."""


class HelpFormatter(argparse.HelpFormatter):
    """Every option's help ends with its default, unless the text gives it already or a flag is simply off."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        value = action.default
        # identity, not ==: a default of 0 is shown, though 0 == False
        if not action.option_strings or "default" in text or any(value is v for v in (None, False, argparse.SUPPRESS)):
            return text
        shown = ",".join(f"{v:g}" for v in value) if isinstance(value, tuple) else str(value)
        return f"{text} (default: {shown.replace('%', '%%')})"


class VersionAction(argparse.Action):
    """``--version``: looks the version up only when asked (importlib.metadata alone takes 0.1 s to import)."""

    def __init__(self, option_strings: Sequence[str], dest: str, **kwargs) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, namespace, values, option_string=None) -> None:
        from volren._version import __version__

        print(f"volren {__version__}")
        parser.exit()


class Parser(argparse.ArgumentParser):
    """argparse that raises instead of printing usage and exiting, so every error is one line."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)
        # argparse's own matcher knows only "-1" and "-.5", so "--light-dir -1,-1,0" read "-1,-1,0" as an option.
        # No option of ours starts with a digit, so anything this matches can only be a value.
        self._negative_number_matcher = NEGATIVE_NUMBERS

    def error(self, message: str) -> None:  # type: ignore[override]
        raise CliError(message)


def floats(text: str, count: int | tuple[int, ...] = 3) -> tuple[float, ...]:
    """Parse ``"x,y,z"`` (or one number where ``count`` allows 1) into floats."""
    counts = (count,) if isinstance(count, int) else count
    try:
        values = tuple(float(t) for t in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a list of numbers") from None
    if len(values) not in counts:
        raise argparse.ArgumentTypeError(f"'{text}' needs {' or '.join(map(str, counts))} comma-separated numbers")
    return values


def out_folder(text: str) -> Path:
    """``--out``: a folder name; an empty one would write into the current folder unasked (``.`` says so)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("is empty: give a folder name ('.' for the current folder)")
    return Path(text)


def vec3(text: str) -> tuple[float, ...]:
    return floats(text, 3)


def floats4(text: str) -> tuple[float, ...]:
    return floats(text, 4)


def floats6(text: str) -> tuple[float, ...]:
    return floats(text, 6)


def rgb(text: str) -> tuple[float, ...]:
    v = floats(text, (1, 3))
    return v * 3 if len(v) == 1 else v


def channel_colors(text: str) -> tuple[tuple[float, float, float], ...]:
    from volren.render.compositing.channels import parse_channel_colors

    return parse_channel_colors(text)


def ints3(text: str) -> tuple[int, int, int]:
    try:
        values = tuple(int(t) for t in text.lower().replace("x", ",").split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' must be three integers X,Y,Z") from None
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"'{text}' must be three integers X,Y,Z")
    return values  # type: ignore[return-value]


def kelvin_range(text: str) -> tuple[float, float]:
    """``--temperature-range K0,K1``: two finite kelvin values 0 < K0 < K1."""
    k = floats(text, 2)
    if not (math.isfinite(k[0]) and math.isfinite(k[1]) and 0 < k[0] < k[1]):
        raise argparse.ArgumentTypeError(f"needs two finite kelvin values 0 < K0 < K1, got {text!r}")
    return (k[0], k[1])


def add_device(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="auto", help="auto (CUDA when present), cpu, cuda or cuda:N")


def add_volume_args(src: argparse._ArgumentGroup | argparse.ArgumentParser) -> None:
    """``--volume`` and every flag saying how to read it: render, animate and serve take them all (`_file_scene`
    reads them)."""
    src.add_argument("--volume", type=volume_path, help="density file (default: none, a --scene): .npy .npz .nrrd "
                     ".nhdr .nii(.gz) .tif(f) .nvdb .vdb .zarr or raw, a folder of DICOM slices or one of its .dcm "
                     "files (the series is read), or an OME-Zarr store's URL (https://..., s3://...: streamed); "
                     "placed where the file says (mm unless it states metres). A sequence, one "
                     "file per frame: 'sim_####.vdb' (# = the zero-padded frame number), 'sim_%%04d.npy', a glob "
                     "'sim_*.npy' (numeric order) or a folder of numbered files; render --frames, animate and serve "
                     "play it")
    src.add_argument("--shape", type=ints3, help="raw files: voxels X,Y,Z, each >= 2 (x varies fastest in the "
                     "file; default: none, required for raw)")
    src.add_argument("--dtype", help="raw files: uint8, uint16, int16, float32, ... (default: none, required for "
                     "raw)")
    src.add_argument("--spacing", type=vec3, help="voxel size x,y,z in --units for .npy .npz raw files, or to "
                     "replace a .tif's, .nvdb's or .vdb's own (default: what the file stores, else cubic voxels, "
                     "longest side 2 m)")
    src.add_argument("--units", choices=("m", "cm", "mm", "um"), help="unit of the file's coordinates and "
                     "--spacing (default: what the file states, e.g. a TIFF's microns, else mm; .vdb: m, "
                     "OpenVDB states no unit)")
    src.add_argument("--grid", help=".vdb files: the density grid's name (default: 'density', else the file's "
                     "only float or double grid)")
    src.add_argument("--level", type=int, help=".zarr (OME-Zarr) pyramids: the level to read, 0 = finest "
                     "(default: the finest within --memory-budget)")
    src.add_argument("--memory-budget", type=float, help=".zarr pyramids: [GiB] of float32 voxels (all "
                     "channels) the chosen level may take, else it streams; .vdb: [GiB] its bricks may take; at most "
                     "the machine's memory; not with --level (default: 1 for .zarr, none for .vdb)")
    src.add_argument("--channel-colors", type=channel_colors, help="multi-channel volumes: a colour per "
                     "channel, names (green,magenta) or r,g,b triples separated by ';' (default: green, magenta, "
                     "cyan, yellow, red, blue, ...)")
    src.add_argument("--channel-opacity", type=lambda t: floats(t, len(t.split(","))), help="multi-channel "
                     "volumes: optical depth at density 1 across the volume's longest side, one for all or one "
                     "per channel (default: 4)")


def add_render_args(p: argparse.ArgumentParser, *, demo: bool = False) -> None:
    animate = p.prog.endswith("animate")
    from volren.presets import QUALITIES

    src = p.add_argument_group("data")
    if not demo:
        src.add_argument("--scene", default=None, help=f"built-in scene (default {DEFAULT_SCENE}; see `volren scenes`)")
        add_volume_args(src)
    # None unless given, so --volume and the fog scenes (which take no voxel count) can refuse it
    src.add_argument("--resolution", type=int, default=128 if demo else None, help="built-in volume scenes: voxels "
                     f"per axis, 64-512{'' if demo else f' (default: {DEFAULT_RESOLUTION})'}")
    src.add_argument("--count", type=int, help="scenes multi, instances, instances-overlap: 4, 16 or 36 "
                     "instances (default 16)")
    mat = p.add_argument_group("material and light (override the scene's)")
    mat.add_argument("--density-scale", type=float, help="sigma_t per unit density [1/m], >= 0 (default: the scene's; "
                     "a --volume's: 20 / its box's longest side [m], optical depth 20 at density 1 across the box "
                     "whatever the file's units)")
    mat.add_argument("--albedo", type=rgb, help="single-scattering albedo: a or r,g,b, each in [0, 1] (default: the "
                     "scene's)")
    mat.add_argument("--g", type=float, help="Henyey-Greenstein asymmetry in (-1, 1) (default: the scene's)")
    mat.add_argument("--emission", type=rgb, help="emitted radiance per unit density per metre: e or r,g,b, >= 0 "
                     "(default: the scene's)")
    mat.add_argument("--emission-grid", help=".vdb files: a second grid (e.g. temperature, heat, flame) that emits "
                     "blackbody radiance where the density is > 0; read as kelvin when its positive values run from "
                     ">= 200 to a hottest in 500..10000, else as relative (default: none)")
    mat.add_argument("--temperature-range", type=kelvin_range, help="K0,K1: kelvin of the emission grid's values "
                     "0+ and max (linear between; values <= 0 emit nothing), 0 < K0 < K1; given, the grid is read as "
                     "relative (default: the scene's; a file's grid read as kelvin: its values; else 1000,3000)")
    mat.add_argument("--emission-scale", type=float, help="luminance Y [W/(m^3 sr)] of the blackbody radiance "
                     "emitted per metre at the hottest value, >= 0 (default: the scene's; a file's: 4 W sigma / "
                     "(1 - exp(-sigma d)), W = sum(Y(light irradiance)) / pi + Y(ambient), d and sigma the thickness "
                     "and extinction of the flame's hot region: its core 4x as bright as a white surface facing the "
                     "light)")
    mat.add_argument("--light-dir", type=vec3, help="direction the light travels: x,y,z, not zero (default: the "
                     "scene's)")
    mat.add_argument("--light-irradiance", type=rgb, help="directional light irradiance [W/m^2]: e or r,g,b, >= 0 "
                     "(default: the scene's)")
    mat.add_argument("--rect-light", type=floats6, action="append", default=[], help="x,y,z,width,height,radiance: "
                     "a rectangular area light at x,y,z facing the origin (repeatable)")
    mat.add_argument("--ambient", type=rgb, help="constant environment radiance: l or r,g,b, >= 0 (default: the "
                     "scene's)")
    mat.add_argument("--environment", type=Path,
                     help="equirectangular environment (.npy linear, or PNG/JPEG sRGB), or 'sky' (built-in); its mean "
                     "is the ambient without --gi (default: the scene's)")
    mat.add_argument("--background", type=rgb, help="background colour (linear): c or r,g,b, >= 0 (default: the "
                     "scene's)")
    opq = p.add_argument_group("opaque geometry (clips the volumes)")
    opq.add_argument("--sphere", type=floats4, action="append", default=[],
                     help="opaque diffuse sphere x,y,z,radius, radius > 0 (repeatable; default: none)")
    opq.add_argument("--ground", type=float, help="opaque ground plane at height y [m] (default: none)")
    opq.add_argument("--mesh", type=Path, action="append", default=[],
                     help="opaque triangle mesh file: OBJ, PLY, STL, glTF/GLB, OFF, or USD (.usd "
                     ".usda .usdc .usdz) (repeatable; default: none)")
    opq.add_argument("--mesh-scale", type=float, default=1.0, help="scale applied to every --mesh (about the origin), "
                     "> 0")
    opq.add_argument("--mesh-translate", type=vec3, default=(0.0, 0.0, 0.0), help="then translation x,y,z [m]")
    opq.add_argument("--mesh-alpha", type=float, action="append", default=[],
                     help="opacity A in [0, 1] of the --mesh at the same position (repeatable; one value applies to "
                     "every --mesh; default 1 = opaque); A < 1: translucent layers blended among the volumes (paper "
                     "000 §3.3; reference, dssrm, cmsrm, cacrm)")
    opq.add_argument("--depth-image", type=Path,
                     help=".npy linear depth (H, W), or (views, H, W), of geometry drawn elsewhere; inf = none "
                                              "(default: none)")
    cam = p.add_argument_group("views")
    cam.add_argument("--camera-pos", type=vec3, help="eye position x,y,z [m] (default: built-in volume scenes and "
                     "--volume framed, the eye in the direction of 0,0.4,3.2 from the centre of their medium or box, "
                     "far enough that it fills the view; fog scenes: their own viewpoint; with --look-at: 0,0.4,3.2)")
    cam.add_argument("--look-at", type=vec3, help="x,y,z (default: the framed centre; fog scenes: their own; with "
                     "--camera-pos: 0,0,0)")
    cam.add_argument("--up", type=vec3, default=(0.0, 1.0, 0.0), help="x,y,z")
    cam.add_argument("--fov", type=float, default=45.0, help="vertical field of view [degrees], in (0, 180)")
    cam.add_argument("--width", type=int, default=640, help=f"[px] in [1, {MAX_IMAGE_SIDE}],"
                     f" width x height at most {MAX_VIEW_PIXELS:,} pixels")
    cam.add_argument("--height", type=int, default=360, help=f"[px] in [1, {MAX_IMAGE_SIDE}]")
    cam.add_argument("--near", type=float, help="[m], > 0 (default: 0.01, or a thousandth of the distance to a "
                     "framed --volume where that is less: micrometre microscopy)")
    cam.add_argument("--far", type=float, help="[m], > --near (default: 1000, or twice the framed volume's farthest "
                     "corner where more)")
    cam.add_argument("--views", default="stereo", help="mono, stereo, or N viewers (placed by --rig), N in [1, 1024]")
    cam.add_argument("--rig", choices=("arc", "wander", "overlap"), help="N viewers (default arc): on an arc "
                     "around --look-at, wandering the scene's area (moving with --frames), or yawed copies of one "
                     "camera whose neighbours share --overlap of the field of view")
    cam.add_argument("--overlap", type=float, help="--rig overlap: shared fraction in [0, 1] (default 0.5)")
    cam.add_argument("--ipd", type=float, help="stereo eye distance [m], in [0, 10) (default: 0.063, or the longest "
                     "side of a framed --volume where that is less: micrometre microscopy)")
    r = p.add_argument_group("method")
    if not demo:
        r.add_argument("--method", default="dssrm", help=f"one of: {', '.join(METHOD_NAMES)}")
    r.add_argument("--quality", default="default", choices=QUALITIES, help="preset of V, L, light grid, early "
                   "termination (light-map methods), froxels (fog), paths (vpt); the flags below override it")
    r.add_argument("--samples", type=int, help="V: view samples across the box diagonal, in [1, 65536] "
                   "(default: the method's)")
    r.add_argument("--light-samples", type=int, help="L: samples towards the light, in [1, 65536] (default: the "
                   "method's)")
    r.add_argument("--light-grid", type=int, help="light-map voxels on the longest axis, in [2, 1024] (default: half "
                   "the density)")
    r.add_argument("--jitter", action="store_true", help="seeded random ray start offsets")
    r.add_argument("--cube-faces", choices=("interior", "exterior"), help="cmsrm/cacrm: march to interior (default) or "
                   "exterior cube faces (exterior only to show its aliasing)")
    r.add_argument("--cube-size", type=int, help="cmsrm: level-0 cube face size S0, fixed, in [2, 4096] (default: "
                   "the density's axis, raised with the LOD to what the screen needs, up to max(axis, 64))")
    r.add_argument("--no-lod", action="store_true", help="cmsrm: no adaptive LOD (level 0, N = --samples)")
    r.add_argument("--no-hybrid", action="store_true", help="cmsrm: always march the cube map, never directly")
    r.add_argument("--no-skip", action="store_true", help="dssrm/cmsrm/cacrm/reference: sample every step, no "
                   "empty-space skipping (the same image, more density samples)")
    r.add_argument("--no-cull", action="store_true", help="cmsrm/cacrm: march empty tiles too (no culling)")
    r.add_argument("--tile-lod", action="store_true", help="cmsrm/cacrm: per-tile LOD 0-2 (fewer samples for distant "
                   "faces, lower PSNR)")
    r.add_argument("--k-z", type=float, help="cmsrm: bilateral edge-stopping coefficient [1/m], >= 0 (0 = "
                   "bilinear; default: the method's)")
    r.add_argument("--no-coupling", action="store_true", help="cacrm: march each eye alone (same steps)")
    r.add_argument("--no-share", action="store_true", help="cacrm: couple the eyes but fetch voxels per ray")
    r.add_argument("--no-vsa", action="store_true", help="cacrm: uniform steps (no variable step amplification)")
    r.add_argument("--k-a", type=float, help="cacrm: Eq. 4's ramp k_a t / t_max, >= 0 (default 1.5, fitted; the "
                   "paper's 3 takes about half the samples at the default N = 360 for 0.3-0.7 dB less PSNR)")
    r.add_argument("--no-interleave", action="store_true", help="cacrm: no interleaved spatial reuse of 2x2 quads "
                   "(it runs where a base step reaches a voxel: N up to the grid's diagonal in voxels, 221 at 128^3)")
    r.add_argument("--mode", choices=("dvr", "mip", "mida", "iso"), help="dssrm/cmsrm/cacrm: dvr (volume rendering, "
                   "default), mip (maximum intensity projection), mida (maximum intensity difference accumulation) "
                   "or iso (shaded isosurface at --iso-value); a multi-channel --volume: dvr, mip (each channel's "
                   "maximum in its colour, added) or mida")
    r.add_argument("--iso-value", type=float, help="--mode iso: the surface's density V > 0, in the grid's units (a CT "
                   "with a Hounsfield range lo..hi holds (HU - lo) / (hi - lo)); outside the densities: a warning "
                   "(default: Otsu's threshold of the densities, said on stderr and in stats.json)")
    r.add_argument("--oit", choices=("tiled", "pixel-rt", "pixel-sort"), help="dssrm/cmsrm/cacrm: how each pixel "
                   "finds the boxes its ray meets, in ray order: tiled (paper 000 §3.4 tiled k-buffer, default), "
                   "pixel-rt (per-pixel BVH ray queries) or pixel-sort (every box tested per pixel)")
    r.add_argument("--oit-k", type=int, help="dssrm/cmsrm/cacrm: K, boxes kept per pixel (the nearest), in [1, 16] "
                   "(default 16)")
    r.add_argument("--gi", choices=GI_METHOD_NAMES, help="dssrm/cmsrm/cacrm: ambient global illumination (paper 000 "
                   "§3.2): sresir (ours), restir (strict ReSTIR), prt, major (major direction), brute (ground truth), "
                   "none (default: constant ambient)")
    r.add_argument("--gi-order", type=int, help="SH order n of the GI (n^2 coefficients, 1-4, default 3)")
    r.add_argument("--gi-rays", type=int, help="--gi prt/brute: rays per voxel, >= 1 (default 256)")
    r.add_argument("--gi-volumes", type=int, help="--gi: volumes whose lighting is updated per frame, >= 1 (default 1)")
    r.add_argument("--spp", type=int, help="vpt: paths per pixel and frame, in [1, 4096] (default 8)")
    r.add_argument("--max-bounces", type=int, help="vpt: scattering events per path, in [1, 64] (default 2; 1 = "
                   "single)")
    r.add_argument("--shading", choices=("coexist", "er"), help="vpt: surface-medium coexistence (default) or "
                   "Exposure Render's two particle types")
    r.add_argument("--tf", help=f"vpt: transfer function, a preset ({', '.join(TF_PRESET_NAMES)}) or a JSON "
                   "file {\"points\": [{\"position\": u, \"extinction\": mu_t, \"albedo\": [r, g, b], \"p_brdf\": p}, "
                   "...]}: u in [0, 1] (the scalar over the volume's largest) not decreasing, mu_t >= 0 [1/m], albedo "
                   "(default 0.8 each) and p_brdf (surface-like share, default 0) in [0, 1], optional \"emission\": "
                   "[r, g, b] >= 0 (radiance emitted per metre, default 0; needs mu_t > 0 there), linear in between; "
                   "optional \"hu_points\" (same fields, position in Hounsfield units) classify a CT (signed "
                   "integers, DICOM) by HU instead, as the ct-* presets do (default: extinction proportional to "
                   "density)")
    r.add_argument("--vpt-ambient", action="store_true", help="vpt: also add the environment's mean radiance as a "
                   "uniform, unshadowed ambient at every collision (paper 002 §6.1; the environment is already "
                   "sampled as a light, so this counts it twice)")
    r.add_argument("--denoise", choices=("none", "ours", "svgf", "wrls"), help="vpt: the spatiotemporal denoiser of "
                   "paper 002 §5 (ours), or the baselines SVGF and WRLS; all keep history across --frames (default: "
                   "none)")
    r.add_argument("--clip", type=floats6, help="vpt: x0,x1,y0,y1,z0,z1 clipping box in the volume's [-1, 1] "
                   "coordinates, each pair increasing (default: none)")
    r.add_argument("--fog-sharing", choices=("none", "grid"), help="fog: per-viewer shadow rays (none) or the "
                   "shared shadow grid (grid, default)")
    r.add_argument("--voxel-size", type=float, help="fog: shadow-grid voxel edge [m], > 0 (default 0.5)")
    r.add_argument("--slices", type=int, help="fog: depth slices per froxel grid, in [3, 1024] (default 128)")
    r.add_argument("--froxel-size", type=int, help="fog: froxel width [px], in [1, 256] (default 8)")
    r.add_argument("--fog-far", type=float, help="fog: end of the fog range [m], > 0 (default 64)")
    r.add_argument("--trilinear", action="store_true", help="fog: interpolate 8 shadow-grid voxels, not the nearest")
    r.add_argument("--no-temporal", action="store_true", help="fog: no jitter and temporal blending")
    r.add_argument("--frames", type=int, default=None if animate else 1, help="render N >= 1 frames (temporal "
                   "methods), keep every frame; a --volume sequence plays its frames 0..N-1, N at most its length "
                   f"(default: {f'{ANIMATE_FRAMES}, or the length of a --volume sequence' if animate else 1})")
    r.add_argument("--seed", type=int, default=0, help="random seed (jitter, scenes, viewers): an integer >= 0")
    r.add_argument("--max-minutes", type=float, default=60.0, help="refuse a render estimated to run longer "
                   "(estimated by a quarter-size probe when views x pixels x frames exceeds 20 M; 0: no limit)")
    add_device(p)
    o = p.add_argument_group("output")
    o.add_argument("--out", type=out_folder, default=Path("out"), help="output folder")
    o.add_argument("--save-linear", action="store_true", help="also write linear (H, W, 4) float32 .npy images")
    o.add_argument("--exposure", type=float, default=0.0, help=f"PNG exposure in stops, in "
                   f"[-{MAX_EXPOSURE:g}, {MAX_EXPOSURE:g}]")
    o.add_argument("--tonemap", default="none", choices=TONEMAPS, help="PNG tone map")
    if not demo:
        b = p.add_argument_group("beyond one process (Ray: pip install 'volren[ray]')")
        b.add_argument("--workers", type=int, help="render the frames (and views) in work units on N >= 1 Ray "
                       "workers, each holding one renderer; a local Ray is started (default: none, in process)")
        b.add_argument("--ray-address", help="run the workers on the Ray cluster at ADDR (host:port, or 'auto'); "
                       "with no --workers, one per CPU (GPU on CUDA) the cluster has (default: none)")
        b.add_argument("--gpus-per-worker", type=float, help="CUDA: the GPU share each worker asks, in (0, 1] "
                       "(default 1)")
        b.add_argument("--data-parallel", type=int, metavar="N", help="split the volume into N >= 1 regions, each "
                       "loaded, held and rendered by its own Ray actor, and composite their images (dssrm: dvr, mip, "
                       "iso); with --ray-address on that cluster (default: none, one process holds it all)")



DESCRIPTION = "Multi-view volumetric density rendering (NVIDIA Warp, CPU or CUDA)."
"""``volren --help``'s first line"""


def command_parser() -> tuple[argparse.ArgumentParser, argparse._SubParsersAction]:
    """``volren`` with --version and the commands demo, render and animate; returns the parser and its sub-parsers,
    to which the CLI adds its other commands."""
    p = Parser(prog="volren", description=DESCRIPTION)
    p.add_argument("--version", action=VersionAction, help="print the version and exit")
    sub = p.add_subparsers(dest="command", required=True, parser_class=Parser)
    add_render_args(sub.add_parser("demo", help="render the default scene as a stereo pair into out/"), demo=True)
    add_render_args(sub.add_parser("render", help="render a built-in scene or a volume file"))
    a = sub.add_parser("animate", help="render an interaction sequence (orbit, light rotation, transfer-function "
                       "switch) to PNG frames and an MP4")
    add_render_args(a)
    a.add_argument("--orbit", type=float, default=360.0, help="camera turn over the sequence [deg]")
    a.add_argument("--light-orbit", type=float, default=0.0, help="light turn over the sequence [deg]")
    a.add_argument("--switch-tf", help="vpt: FRAME:TF, switch to transfer function TF (as --tf) at frame FRAME "
                   "(default: no switch)")
    a.add_argument("--fps", type=float, default=30.0, help="MP4 frame rate")
    return p, sub


def render_parser() -> argparse.ArgumentParser:
    """The parser of ``volren demo | render | animate`` command lines: the CLI's own for those commands."""
    return command_parser()[0]


def command_options(command: str) -> list[argparse.Action]:
    """The actions (options) of ``volren <command>``'s sub-parser (demo, render or animate), --help aside: what a
    batch file's keys and a `volren.plan.spec.RenderSpec` are checked and typed by."""
    sub = next(a for a in render_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return [a for a in sub.choices[command]._actions if a.dest != "help"]
