"""``volren`` command line: demo, render, scenes, compare, bench. Thin over the Python API.

Every user error (bad file, bad number, no GPU, ...) is printed as one line on stderr with exit status 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import os
import re
import signal
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from volren.errors import VolrenError, VolrenWarning

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
DEFAULT_EYE = (0.0, 0.4, 3.2)
"""[m] the default camera position; a volume file is seen from its direction, framed"""
DEFAULT_RESOLUTION = 64
"""voxels per axis of a built-in volume scene (render, animate; demo: 128)"""
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


def _show_warning(show, message, category, filename, lineno, file=None, line=None) -> None:
    """`warnings.showwarning` while a command runs: a `VolrenWarning` (a renderer's or a loader's) as `warn`'s one
    line, anything else as Python shows it."""
    if issubclass(category, VolrenWarning):
        warn(str(message))
    else:
        show(message, category, filename, lineno, file, line)


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
        from volren import __version__

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


def add_device(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="auto", help="auto (CUDA when present), cpu, cuda or cuda:N")


def add_volume_args(src: argparse._ArgumentGroup | argparse.ArgumentParser) -> None:
    """``--volume`` and every flag saying how to read it: render, animate and serve take them all (`_file_scene`
    reads them)."""
    src.add_argument("--volume", type=Path, help="density file (default: none, a --scene): .npy .npz .nrrd .nhdr "
                     ".nii(.gz) .tif(f) .nvdb .vdb or raw, a folder of DICOM slices or one of its .dcm files (the "
                     "series is read); placed where the file says (mm unless it states metres). A sequence, one "
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
                     "channels) the chosen level may take, at most the machine's memory; not with --level "
                     "(default: 1)")
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
    cam.add_argument("--camera-pos", type=vec3, help="eye position x,y,z [m] (default 0,0.4,3.2; fog scenes: their "
                     "own viewpoint)")
    cam.add_argument("--look-at", type=vec3, help="x,y,z (default 0,0,0; fog scenes: their own)")
    cam.add_argument("--up", type=vec3, default=(0.0, 1.0, 0.0), help="x,y,z")
    cam.add_argument("--fov", type=float, default=45.0, help="vertical field of view [degrees], in (0, 180)")
    cam.add_argument("--width", type=int, default=640, help=f"[px] in [1, {MAX_IMAGE_SIDE}],"
                     f" width x height at most {MAX_VIEW_PIXELS:,} pixels")
    cam.add_argument("--height", type=int, default=360, help=f"[px] in [1, {MAX_IMAGE_SIDE}]")
    cam.add_argument("--near", type=float, help="[m], > 0 (default: 0.01, or a thousandth of the distance to a "
                     "framed --volume where that is less: micrometre microscopy)")
    cam.add_argument("--far", type=float, default=1000.0, help="[m], > --near")
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
    o.add_argument("--exposure", type=float, default=1.0 if demo else 0.0, help=f"PNG exposure in stops, in "
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


def add_serve_args(p: argparse.ArgumentParser) -> None:
    from volren.presets import QUALITIES
    from volren.serve.rates import TICK_MS

    p.add_argument("--scene", help=f"built-in scene (default {DEFAULT_SCENE}; see `volren scenes`)")
    add_volume_args(p)
    p.add_argument("--resolution", type=int, help=f"built-in volume scenes: voxels per axis, 64-512 (default: "
                   f"{DEFAULT_RESOLUTION})")
    p.add_argument("--method", help="dssrm, cmsrm, cacrm, vpt or fog (default: dssrm, fog for fog scenes)")
    p.add_argument("--quality", default="interactive", choices=QUALITIES, help="starting preset (viewers may switch)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on; any but loopback needs a token "
                   "(--token-file, VOLREN_TOKEN or --token)")
    p.add_argument("--port", type=int, default=8000, help="TCP port, in [1, 65535]")
    p.add_argument("--token-file", metavar="PATH", help="a file holding the secret every request must carry (as "
                   "?token=T, or the cookie the page gets with it), 16-256 URL-safe characters (default: none; "
                   "without --token-file and --token, the environment variable VOLREN_TOKEN if set)")
    p.add_argument("--token", help="the secret itself, as --token-file's content (visible to every local user in "
                   "the process list: prefer --token-file or VOLREN_TOKEN; default: none)")
    p.add_argument("--allow-host", action="append", default=[], metavar="NAME", help="a further name the Host "
                   "header may give (repeatable; default: the bound address, and localhost on loopback)")
    p.add_argument("--allow-origin", action="append", default=[], metavar="ORIGIN", help="a further page origin, "
                   "http://host:port, allowed to open /ws (repeatable; default: the server's own only)")
    p.add_argument("--lock-settings", action="store_true", help="viewers may not change the shared method, "
                   "quality, transfer function, light or playback")
    p.add_argument("--max-viewers", type=int, default=16, help="viewers connected at once, in [1, 1024]")
    p.add_argument("--max-viewers-per-client", type=int, help="viewers connected at once from one address, so one "
                   "neighbour cannot take every slot (on loopback each 127.x.y.z counts apart; default: 4, at most "
                   "--max-viewers)")
    p.add_argument("--max-width", type=int, default=1920, help="[px] largest viewer image (stereo: both eyes)")
    p.add_argument("--max-height", type=int, default=1080, help="[px] largest viewer image")
    p.add_argument("--pixel-budget", type=int, default=1920 * 1080, help="[px] rendered per tick for all viewers "
                   "at most")
    p.add_argument("--tick-ms", type=float, default=TICK_MS, help="[ms] with several viewers, the tick time aimed "
                   "at: each gets an equal share of it, a viewer whose frame costs more gets a smaller one (0: share "
                   f"the pixel budget only; default {TICK_MS:g})")
    s = p.add_argument_group("beyond one process (Ray: pip install 'volren[ray]')")
    s.add_argument("--shards", type=int, help="render on N >= 1 Ray actors, each a render loop for the viewers "
                   "placed on it (a stereo pair whole, viewers of one part of the scene together); a local Ray is "
                   "started (default: none, one render loop in process)")
    s.add_argument("--ray-address", help="with --shards: run the shards on the Ray cluster at ADDR (host:port, or "
                   "'auto') (default: a local Ray)")
    add_device(p)


def run_serve(args: argparse.Namespace) -> int:
    # the checks that need no data first: the imports below take seconds
    if not 1 <= args.port <= 65535:
        raise CliError(f"--port must lie in [1, 65535], got {args.port}")
    if args.ray_address is not None and args.shards is None:
        raise CliError("--ray-address needs --shards N (the server renders in process without it)")
    if args.shards is not None and args.shards < 1:
        raise CliError(f"--shards must be at least 1, got {args.shards}")
    check_scene_name(args.scene)
    from volren.serve.heap import one_arena

    one_arena()  # before the imports below start threads
    from volren.serve.app import TOKEN_ENV, build_loop, check_bind, make_app, read_token, serve
    from volren.serve.viewers import Limits

    token, source = read_token(args.token, args.token_file)
    check_bind(args.host, token, tuple(args.allow_origin), source or "--token")
    if source == "--token":
        warn(f"--token is visible to every local user in the process list (ps, /proc/PID/cmdline): prefer --token-file "
             f"PATH or {TOKEN_ENV}")
    per_client = args.max_viewers_per_client
    if per_client is not None and per_client > args.max_viewers:
        raise CliError(f"--max-viewers-per-client {per_client} exceeds --max-viewers {args.max_viewers}: it would "
                       "limit nothing")
    limits = Limits(args.max_viewers, args.max_width, args.max_height, args.pixel_budget,
                    max_per_client=per_client or min(Limits.max_per_client, args.max_viewers),
                    tick_ms=args.tick_ms or None)
    name = args.scene or DEFAULT_SCENE
    loop = build_loop(name, args.method, args.quality, args.resolution or DEFAULT_RESOLUTION, args.device, limits,
                      args.lock_settings, **served_volume(args), shards=args.shards, ray_address=args.ray_address)
    name = args.volume.name if args.volume is not None else name
    serve(make_app(loop, name, token, hosts=(args.host, *args.allow_host), origins=tuple(args.allow_origin)),
          args.host, args.port, token, source)
    return 0


def served_volume(args: argparse.Namespace) -> dict:
    """`build_loop`'s scene, camera and play step for ``serve --volume`` (none without): the file's scene, framed as
    `views_from_args` frames it for a --max-width x --max-height view; a sequence plays its frames in a loop."""
    check_channel_flags(args)
    if args.volume is None:
        return {}
    import numpy as np

    from volren.camera import Camera
    from volren.serve.loop import sequence_player

    if args.scene is not None or args.resolution is not None:
        raise CliError("serve --volume shows the file: --scene and --resolution apply to built-in scenes")
    loaded = _volume_from_args(args)
    if loaded.channels:  # `channel_scene` renders each channel by a renderer of its own; the loop has one
        raise CliError(f"serve --volume {args.volume}: a multi-channel volume renders with render and animate only")
    scene = _file_scene(args)
    corners = loaded.corners_world
    look_at = (corners.min(axis=0) + corners.max(axis=0)) / 2
    direction = np.array(DEFAULT_EYE) / np.linalg.norm(DEFAULT_EYE)
    distance = framing_distance(corners, look_at, direction, (0.0, 1.0, 0.0), Camera.fov_y,
                                args.max_width / args.max_height)
    played = volume_sequence(args)
    animate = None if played is None or len(played) == 1 else sequence_player(
        len(played), lambda i: dataclasses.replace(scene, volumes=_file_scene(args, i).volumes))
    camera = Camera(position=tuple(look_at + distance * direction), look_at=tuple(look_at),
                    near=min(Camera.near, distance / 1000))  # as `views_from_args`: 1 cm would clip a 30 um stack
    return {"scene": scene, "camera": camera, "animate": animate}


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="volren", description="Multi-view volumetric density rendering (NVIDIA Warp, CPU or CUDA).")
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
    sub.add_parser("scenes", help="list the built-in scenes")
    c = sub.add_parser("compare", help="PSNR, SSIM, FLIP of TEST against REF, and an error heat map")
    c.add_argument("ref", type=Path, help="reference image: .npy linear, or PNG/JPEG; its peak must be > 0")
    c.add_argument("test", type=Path, help="image to measure, same size and kind as REF")
    c.add_argument("--heatmap", type=Path, help="heat map PNG (default: next to TEST, *_error.png)")
    add_serve_args(sub.add_parser("serve", help="serve a scene live to browsers: each viewer steers its own "
                                  "camera; one render call per tick serves them all"))
    b = sub.add_parser("bench", help="run a benchmark suite; writes JSON and a Markdown table")
    b.add_argument("suite", help="suite name (see `volren bench list`)")
    b.add_argument("--quick", action="store_true", help="small sizes for a CPU")
    b.add_argument("--out", type=Path, default=None,
                   help="folder for the JSON and Markdown (default out/bench; --out docs/bench updates the committed "
                        "tables)")
    b.add_argument("--repeats", type=int, help="timed frames per case instead of the suite's own (at least 1; the "
                   "frame-timed suites: a full-size run on a CPU cuts repeats, not sizes) (default: the suite's)")
    b.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="settings",
                   help="replace an entry of the suite's configuration (repeatable; VALUE as JSON, e.g. frames=12: "
                   "a full-size run on a CPU cuts a camera path's frames, not its sizes) (default: none)")
    b.add_argument("--shards", help="bench serve: COUNTS, comma-separated (e.g. 1,2): the sharded server on a local "
                   "Ray with each count of shards, against the loop in process (default: no shards)")
    add_device(b)
    j = sub.add_parser("batch", help="run a sweep of renders a TOML job file describes: in process, or on Ray with "
                       "--workers or --ray-address")
    j.add_argument("job", type=Path, help="job file: render/animate options and a [sweep] of what varies (see "
                   "examples/turntable-sweep.toml)")
    j.add_argument("--workers", type=int, help="run on a local Ray with N >= 1 workers (default: none, in process)")
    j.add_argument("--ray-address", help="run on the Ray cluster at ADDR (host:port, or 'auto') (default: none)")
    j.add_argument("--gpus-per-worker", type=float, help="CUDA: the GPU share each worker asks, in (0, 1] "
                   "(default 1)")
    j.add_argument("--dry-run", action="store_true", help="check the job file, print its jobs and render nothing")
    return p


def scene_from_args(args: argparse.Namespace, time: float = 0.0):
    """The scene the arguments ask for: a built-in (a fog scene at ``time`` [s]) or a volume file, with material and
    light overrides."""
    from volren.data import COUNTED_SCENES, builtin_scene, load_mesh_file
    from volren.data.fog_scenes import FOG_SCENES, fog_scene
    from volren.scene import DirectionalLight, Environment, Plane, Sphere

    check_channel_flags(args)
    if getattr(args, "grid", None) is not None and getattr(args, "volume", None) is None:
        raise CliError("--grid names a grid of a .vdb --volume; there is no --volume")
    if getattr(args, "volume", None) is not None:
        if args.scene is not None:
            raise CliError("give either --scene or --volume, not both")
        if args.resolution is not None:
            raise CliError("--resolution applies to built-in volume scenes only; --volume's file sets its own voxels")
        scene = _file_scene(args)
    elif getattr(args, "scene", None) in FOG_SCENES:
        if args.resolution is not None:
            raise CliError(f"--resolution applies to built-in volume scenes only, not to fog scene '{args.scene}'")
        scene = fog_scene(args.scene, time)
    else:
        name = getattr(args, "scene", None)
        check_scene_name(name)
        name = DEFAULT_SCENE if name is None else name
        if args.count is not None and name not in COUNTED_SCENES:
            raise CliError(f"--count applies to --scene {', '.join(COUNTED_SCENES)} only, not to scene '{name}'")
        resolution = DEFAULT_RESOLUTION if args.resolution is None else args.resolution
        scene = builtin_scene(name, resolution, count=16 if args.count is None else args.count, seed=args.seed)
    check_fire_flags(args, scene)
    volumes = _with_material(args, scene.volumes)
    warn_density(volumes, transfer=args.tf is not None)
    lights = list(scene.lights)
    if args.light_dir is not None or args.light_irradiance is not None:
        idx = next((i for i, lt in enumerate(lights) if isinstance(lt, DirectionalLight)), None)
        base = lights[idx] if idx is not None else DirectionalLight()
        new = dataclasses.replace(
            base,
            **({"direction": args.light_dir} if args.light_dir is not None else {}),
            **({"irradiance": args.light_irradiance} if args.light_irradiance is not None else {}),
        )
        if idx is None:
            lights.append(new)
        else:
            lights[idx] = new
    lights += [rect_light(*r) for r in args.rect_light]
    if args.ambient is not None and args.environment is not None:
        raise CliError("give either --ambient or --environment, not both")
    opaque = list(scene.opaque) + [Sphere(tuple(s[:3]), s[3]) for s in args.sphere]
    alphas = mesh_alphas(args.mesh_alpha, len(args.mesh))
    opaque += [load_mesh_file(m, scale=args.mesh_scale, translate=args.mesh_translate, alpha=a)
               for m, a in zip(args.mesh, alphas, strict=True)]
    if args.ground is not None:
        opaque.append(Plane((0.0, args.ground, 0.0), (0.0, 1.0, 0.0)))
    environment = scene.environment
    if args.ambient is not None:
        environment = Environment(args.ambient)
    elif args.environment is not None:
        from volren.data.environments import ENVIRONMENTS
        from volren.imageio import load_image

        if str(args.environment) in ENVIRONMENTS:
            environment = ENVIRONMENTS[str(args.environment)]()
        else:
            environment = Environment(image=load_image(args.environment)[..., :3])
    background = args.background if args.background is not None else scene.background
    if getattr(args, "volume", None) is not None and getattr(args, "emission_scale", None) is None:
        volumes = flame_defaults(volumes, lights, environment)
    return dataclasses.replace(scene, volumes=volumes, lights=tuple(lights), environment=environment,
                               background=background, opaque=tuple(opaque))


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


def emission_reading(args: argparse.Namespace, scene) -> dict:
    """stats.json's ``emission_grid`` for a file's emission grid, and one line on stdout: how its values became
    temperatures (kelvin, relative, or relative by --temperature-range) and the emission scale; nothing without."""
    from volren.blackbody import FLAME_CONTRAST

    volume = next((v for v in scene.volumes if v.emission_grid is not None), None)
    if getattr(args, "volume", None) is None or volume is None:
        return {}
    grid = volume.emission_grid
    positive = grid[grid > 0]
    values = [float(positive.min()), float(positive.max())] if positive.size else [0.0, 0.0]
    k0, k1 = volume.temperature_range
    if args.temperature_range is not None:
        reading, said = "relative", f"as relative (--temperature-range), mapped to {k0:g}..{k1:g} K"
        kelvin = [k0, k1]
    elif k0 == 0:
        reading, said = "kelvin", f"as kelvin ({values[0]:.4g}..{values[1]:.4g} K)"
        kelvin = values
    else:
        reading, said = "relative", f"as relative (values {values[0]:.4g}..{values[1]:.4g}), mapped to {k0:g}..{k1:g} K"
        kelvin = [k0, k1]
    given = args.emission_scale is not None
    rule = "--emission-scale" if given else f"default: the flame {FLAME_CONTRAST:g}x a lit white surface"
    print(f"volren: emission grid '{args.emission_grid}' read {said}; emission scale {volume.emission_scale:.4g} "
          f"W/(m^3 sr) ({rule})")
    return {"emission_grid": {"name": args.emission_grid, "reading": reading, "values": values, "kelvin": kelvin,
                              "temperature_range_given": args.temperature_range is not None,
                              "emission_scale": volume.emission_scale,
                              "emission_scale_rule": "--emission-scale" if given else "flame"}}


OPAQUE_VOXEL_DEPTH = 100.0
"""optical depth of one voxel beyond which a volume renders as an opaque box (transmittance e^-100 per voxel)"""
THIN_BOX_DEPTH = 0.05
"""optical depth at the densest value across the box's longest side below which a volume renders all but empty
(alpha under 5% in every pixel)"""
EMPTY_ALPHA = 0.01
"""a render whose alpha stays below this in every pixel of every view shows nothing of its --volume"""


def warn_density(volumes: tuple, transfer: bool) -> None:
    """Warn of a density that renders nothing (all zero), all but nothing (the densest value's optical depth across
    the box's longest side under `THIN_BOX_DEPTH`: a float file of tiny values, or a --density-scale [1/m] meant for
    a box in metres on one in micrometres) or an opaque box (the densest voxel's optical depth over
    `OPAQUE_VOXEL_DEPTH`, sigma_t = density_scale * density); a --tf reads density / its maximum, so only the first.
    A density_scale of 0 asks for nothing and gets no warning."""
    import numpy as np

    from volren._api import BOX_OPTICAL_DEPTH, box_longest_side

    for v in volumes:
        hi = float(v.density.max())
        voxel = float(np.min(np.linalg.norm(v.to_world[:3, :3], axis=0) * 2 / np.array(v.density.shape[::-1])))
        side = box_longest_side(v.to_world)
        if hi == 0:
            warn(f"volume '{v.name}' has an all-zero density: it renders nothing")
        elif not transfer and hi * v.density_scale * voxel > OPAQUE_VOXEL_DEPTH:
            warn(f"volume '{v.name}' is opaque (optical depth {hi * v.density_scale * voxel:.3g} in its densest "
                 "voxel): check --density-scale")
        elif not transfer and 0 < hi * v.density_scale * side < THIN_BOX_DEPTH:
            warn(f"volume '{v.name}' renders all but empty (optical depth {hi * v.density_scale * side:.3g} at its "
                 f"densest across its {side:.3g} m box): set --density-scale [1/m] to about "
                 f"{BOX_OPTICAL_DEPTH / (hi * side):.3g}")


def warn_empty_render(plan, frame) -> None:
    """One line when a --volume's render shows nothing (alpha under `EMPTY_ALPHA` in every view) though its box's
    optical depth is not under `THIN_BOX_DEPTH` (`warn_density` said why then; a density_scale of 0 asks for
    nothing; or a line was said already) and no transfer function chose what shows: the camera misses its box or the
    volume is too thin, and what to set for each."""
    import numpy as np

    from volren._api import box_longest_side

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


def rect_light(x: float, y: float, z: float, width: float, height: float, radiance: float):
    """``--rect-light``: a width x height rectangle at (x, y, z) facing the origin (its height along the world's up,
    projected)."""
    import numpy as np

    from volren.scene import RectLight

    if not (width > 0 and height > 0):
        raise CliError(f"--rect-light needs a positive width and height, got {width} and {height}")
    position = np.array([x, y, z])
    if np.linalg.norm(position) < 1e-9:
        raise CliError("--rect-light cannot sit at the origin it faces")
    normal = -position / np.linalg.norm(position)
    up = np.array([0.0, 1.0, 0.0]) if abs(normal[1]) < 0.99 else np.array([1.0, 0.0, 0.0])
    u = np.cross(up, normal)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    # Emission faces edge_u x edge_v = normal.
    return RectLight(tuple(position), tuple(0.5 * width * u), tuple(0.5 * height * v), (radiance,) * 3)


def kelvin_range(text: str) -> tuple[float, float]:
    """``--temperature-range K0,K1``: two finite kelvin values 0 < K0 < K1."""
    k = floats(text, 2)
    if not (math.isfinite(k[0]) and math.isfinite(k[1]) and 0 < k[0] < k[1]):
        raise argparse.ArgumentTypeError(f"needs two finite kelvin values 0 < K0 < K1, got {text!r}")
    return (k[0], k[1])


def check_fire_flags(args: argparse.Namespace, scene) -> None:
    """--emission-grid names a grid of a .vdb --volume; --temperature-range and --emission-scale need a volume with
    an emission grid (--emission-grid or the fire scene): elsewhere they would do nothing."""
    if getattr(args, "emission_grid", None) is not None and getattr(args, "volume", None) is None:
        raise CliError("--emission-grid names a second grid of a .vdb --volume; there is no --volume (the fire scene "
                       "has its own)")
    flags = [f for f, k in (("--temperature-range", "temperature_range"), ("--emission-scale", "emission_scale"))
             if getattr(args, k, None) is not None]
    if flags and not any(v.emission_grid is not None for v in scene.volumes):
        raise CliError(f"{', '.join(flags)} set the blackbody emission of an emission grid: give --emission-grid "
                       "NAME with a .vdb --volume, or --scene fire")
    scale = getattr(args, "emission_scale", None)
    if scale is not None and not (math.isfinite(scale) and scale >= 0):
        raise CliError(f"--emission-scale must be a finite number >= 0, got {scale:g}")


def channel_scene(args: argparse.Namespace, loaded):
    """A multi-channel ``--volume``: one volume per channel glowing in its colour, unlit
    (`volren.render.compositing.channels`); material and light flags would do nothing and are refused."""
    from volren.render.compositing.channels import channel_volumes
    from volren.scene import Environment, Scene

    unused = [flag for flag, value in (
        ("--density-scale", args.density_scale), ("--albedo", args.albedo), ("--g", args.g),
        ("--emission", args.emission), ("--light-dir", args.light_dir), ("--light-irradiance", args.light_irradiance),
        ("--rect-light", args.rect_light or None), ("--ambient", args.ambient), ("--environment", args.environment),
        ("--tf", args.tf), ("--gi", None if args.gi in (None, "none") else args.gi)) if value is not None]
    if unused:
        raise CliError(f"a multi-channel volume glows in its channel colours, unlit: {', '.join(unused)} would do "
                       "nothing (use --channel-colors, --channel-opacity)")
    mode = getattr(args, "mode", None)
    if mode == "iso":
        raise CliError(f"--mode iso draws a lit, opaque surface; the multi-channel --volume {args.volume} glows unlit "
                       "in its channel colours, so its surfaces would be black: use --mode dvr, mip or mida")
    if mode == "mip" and args.channel_opacity is not None:
        raise CliError("--channel-opacity would do nothing with --mode mip: each channel shows its maximum in its "
                       "colour, whatever its opacity")
    colors = args.channel_colors or loaded.channel_colors or None  # the flag, else the file's (OME-Zarr omero)
    volumes = channel_volumes(loaded.channels, loaded.to_world, colors=colors, opacity=args.channel_opacity,
                              name=args.volume.name)
    return Scene(volumes, lights=(), environment=Environment((0.0, 0.0, 0.0)), name=args.volume.stem)


def check_channel_flags(args: argparse.Namespace) -> None:
    """--level / --memory-budget need a --volume (the loader refuses them for anything but .zarr) and not each other
    (`check_memory_budget`), checked before the file is read; --channel-colors / --channel-opacity a multi-channel
    --volume."""
    volume = getattr(args, "volume", None)
    zarr_flags = [f for f, k in (("--level", "level"), ("--memory-budget", "memory_budget"))
                  if getattr(args, k, None) is not None]
    if zarr_flags and volume is None:
        raise CliError(f"{', '.join(zarr_flags)} choose the level of a .zarr --volume; there is no --volume")
    check_memory_budget(getattr(args, "memory_budget", None), getattr(args, "level", None))
    channel_flags = [f for f, k in (("--channel-colors", "channel_colors"), ("--channel-opacity", "channel_opacity"))
                     if getattr(args, k, None) is not None]
    if channel_flags and (volume is None or not _volume_from_args(args).channels):
        raise CliError(f"{', '.join(channel_flags)} apply to a multi-channel --volume only (a (C, Z, Y, X) array, a "
                       "TIFF or OME-Zarr with a channel axis)")


def host_memory() -> int | None:
    """[bytes] of this machine's physical memory; None where the system does not say (no ``os.sysconf``)."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None


def check_memory_budget(budget: float | None, level: int | None) -> None:
    """--memory-budget [GiB]: a positive number no larger than the machine's memory (a level it would admit could
    not be held), and not beside --level, which names the level the budget would choose."""
    if budget is None:
        return
    if level is not None:
        raise CliError(f"--memory-budget chooses a level by its size; --level {level} names the level, so the budget "
                       "would do nothing: give one of them")
    if not (math.isfinite(budget) and budget > 0):
        raise CliError(f"--memory-budget must be a positive number of GiB, got {budget:g}")
    memory = host_memory()
    if memory is not None and budget * 2**30 > memory:
        raise CliError(f"--memory-budget {budget:g} GiB exceeds this machine's memory ({memory / 2**30:.1f} GiB): a "
                       "level that large could not be read")


def _with_material(args: argparse.Namespace, volumes: tuple) -> tuple:
    """``volumes`` with the material flags' values in place of their own."""
    names = ("density_scale", "albedo", "g", "emission", "temperature_range", "emission_scale")
    material = {k: getattr(args, k) for k in names if getattr(args, k) is not None}
    return tuple(dataclasses.replace(v, **material) for v in volumes) if material else volumes


def _file_scene(args: argparse.Namespace, frame: int = 0):
    """``--volume``'s scene (of frame ``frame`` of a sequence), before the material and light overrides."""
    from volren._api import volume_from_file
    from volren.scene import Scene

    loaded = _volume_from_args(args, frame)
    return channel_scene(args, loaded) if loaded.channels else Scene(
        (volume_from_file(loaded, args.volume.name),), name=args.volume.stem)


def _value_mapping(args: argparse.Namespace) -> dict:
    """stats.json's ``value_mapping``: how ``--volume``'s file values became densities (a sequence's frames share
    frame 0's), and ``opacity``: how densities became extinction (`opacity_entry`); nothing for built-in scenes and
    multi-channel files."""
    mapping = _volume_from_args(args).value_mapping if getattr(args, "volume", None) is not None else None
    return {} if mapping is None else {"value_mapping": mapping.to_dict(), "opacity": opacity_entry(args)}


def opacity_entry(args: argparse.Namespace) -> dict:
    """stats.json's ``opacity`` of a one-channel ``--volume``: its ``density_scale`` [1/m] and the ``rule`` that
    set it: "--density-scale" (given, per metre) or "box" (`volren._api.box_density_scale`: ``optical_depth`` at
    density 1 across the box's ``longest_side`` [m])."""
    from volren._api import BOX_OPTICAL_DEPTH, box_density_scale, box_longest_side

    if args.density_scale is not None:
        return {"rule": "--density-scale", "density_scale": args.density_scale}
    to_world = _volume_from_args(args).to_world
    return {"rule": "box", "optical_depth": BOX_OPTICAL_DEPTH, "longest_side": box_longest_side(to_world),
            "density_scale": box_density_scale(to_world)}


def _volume_options(args: argparse.Namespace) -> tuple:
    """How to read ``--volume`` (`_read_volume`'s arguments after the path)."""
    return (args.shape, args.dtype, args.spacing, args.units, args.grid, args.level, args.memory_budget,
            getattr(args, "emission_grid", None))


def _volume_from_args(args: argparse.Namespace, frame: int = 0):
    """``--volume`` (frame ``frame`` of a sequence) with the options that say how to read it (`_load_volume`)."""
    sequence = volume_sequence(args)
    if sequence is not None:
        return sequence.frame(frame)
    return _load_volume(args.volume, *_volume_options(args))


def volume_sequence(args: argparse.Namespace):
    """The `VolumeSequence` a ``--volume`` pattern or 4-D NIfTI names (serve's reads ahead across the end: it plays
    in a loop), opened once (keyed on the folder's mtime too, so added or removed frames are found, and a file's);
    None for one volume."""
    if getattr(args, "volume", None) is None:
        return None
    folder = args.volume if args.volume.is_dir() else args.volume.parent
    stamp = folder.stat().st_mtime_ns if folder.exists() else None
    if args.volume.is_file():  # a 4-D NIfTI's time points: the file rewritten in place
        stamp = (stamp, args.volume.stat().st_mtime_ns)
    return _open_sequence(args.volume, stamp, args.command == "serve", *_volume_options(args))


@functools.lru_cache(maxsize=1)
def _open_sequence(path: Path, _stamp, loop: bool, *options):
    from volren.data.sequence import SequenceConfig, VolumeSequence, frame_files

    files = frame_files(path)
    if files is None:
        return None
    return VolumeSequence(SequenceConfig(files, loop=loop), lambda frame: _read_volume(frame, *options))


def _load_volume(path: Path, shape, dtype, spacing, units, grid=None, level=None, memory_budget=None,
                 emission_grid=None):
    """``--volume`` read once: the scene and the default camera framing both need it (keyed on the file's mtime too,
    so a rewritten file is read again). One DICOM file (``.dcm``, or DICOM content without another extension) stands
    for its series: the files of its folder with its SeriesInstanceUID (other series beside it are skipped)."""
    from volren.data.loaders import dicom_member

    dicom_file = dicom_member(path, shape)
    source = path.parent if dicom_file else path
    stamp = source.stat().st_mtime_ns if source.exists() else None
    try:
        return _load_volume_cached(path, stamp, shape, dtype, spacing, units, grid, level, memory_budget,
                                   emission_grid)
    except VolrenError as exc:
        if not dicom_file or str(exc).startswith(str(path)):  # the message names the file already
            raise
        # the loader names the folder; the user named a file (e.g. the folder holds two series: say which file)
        raise CliError(f"--volume {path}: reading the DICOM series in its folder: {exc}") from None


@functools.lru_cache(maxsize=1)
def _load_volume_cached(path: Path, _stamp, *options):
    return _read_volume(path, *options)


def _read_volume(path: Path, shape, dtype, spacing, units, grid, level, memory_budget, emission_grid):
    from volren.data.loaders import load_volume

    budget = None if memory_budget is None else memory_budget * 2**30  # --memory-budget is in GiB
    return load_volume(path, shape=shape, dtype=dtype, spacing=spacing, units=units, grid=grid, level=level,
                       memory_budget=budget, emission_grid=emission_grid)


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


def views_from_args(args: argparse.Namespace, time: float = 0.0):
    """The viewers: one camera from the arguments (a fog scene's own viewpoint by default), made into mono, stereo
    or N views by ``--rig``; in a fog scene the arc and the wandering viewers keep to its walkable space (the arc
    only when the camera stands in it), elsewhere viewers wander 3 m around the look-at point; wandering viewers are
    placed for ``time`` [s]. A volume file is framed: the camera looks at its world box's centre from the default
    direction (0, 0.4, 3.2), far enough that the whole box is in view."""
    from volren.camera import Camera, make_views
    from volren.data.fog_scenes import FOG_SCENES, fog_scene_camera, fog_scene_walk_area
    from volren.viewers import WalkArea, arc_viewers, overlap_viewers, wandering_viewers

    position, look_at, near, ipd = DEFAULT_EYE, (0.0, 0.0, 0.0), 0.01, 0.063
    fog_scene = getattr(args, "scene", None) in FOG_SCENES
    if fog_scene:
        default = fog_scene_camera(args.scene)
        position, look_at = default["position"], default["look_at"]
    elif getattr(args, "volume", None) is not None and args.camera_pos is None:
        import numpy as np

        corners = _volume_from_args(args).corners_world
        look_at = tuple(args.look_at or (corners.min(axis=0) + corners.max(axis=0)) / 2)
        # eyes 63 mm apart would each see a 30 um stack as a speck off to the side
        ipd = min(ipd, float(np.ptp(corners, axis=0).max())) if args.ipd is None else args.ipd
        direction = np.array(position) / np.linalg.norm(position)
        distance = framing_distance(corners, look_at, direction, args.up, args.fov, args.width / max(args.height, 1),
                                    ipd / 2 if args.views == "stereo" else 0.0)
        position = tuple(np.array(look_at) + distance * direction)
        near = min(near, distance / 1000)  # a 100 um stack framed from 0.4 mm: the default 1 cm would clip it all
    cam = Camera(position=args.camera_pos or position, look_at=args.look_at or look_at, up=args.up, fov_y=args.fov,
                 width=args.width, height=args.height, near=near if args.near is None else args.near, far=args.far)
    if args.overlap is not None and args.rig != "overlap":
        raise CliError("--overlap needs --rig overlap and --views N")
    if args.views in ("mono", "stereo"):
        if args.rig is not None:
            raise CliError(f"--rig {args.rig} places N viewers, not --views {args.views}: give --views N")
        return make_views(cam, args.views, ipd if args.ipd is None else args.ipd)
    count = len(make_views(cam, args.views))  # validates N
    rig = args.rig or "arc"
    if rig == "overlap":
        return overlap_viewers(cam, count, 0.5 if args.overlap is None else args.overlap)
    area = fog_scene_walk_area(args.scene) if fog_scene else None
    if rig == "arc":
        return arc_viewers(cam, count, area)
    if area is None:
        x, y, z = cam.look_at
        area = WalkArea((x - 3.0, z - 3.0), (x + 3.0, z + 3.0), floor=y - 3.0)
    return wandering_viewers(cam, count, area, time=time, seed=args.seed)


def depth_images_from_args(args: argparse.Namespace, view_count: int) -> list | None:
    """``--depth-image``: one (H, W) image for every view, or a (views, H, W) stack."""
    if args.depth_image is None:
        return None
    import numpy as np

    try:
        depth = np.load(args.depth_image, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise CliError(f"cannot read depth image '{args.depth_image}': {exc}") from None
    if depth.ndim == 2:
        return [depth] * view_count
    if depth.ndim == 3 and depth.shape[0] == view_count:
        return list(depth)
    raise CliError(f"depth image must be (H, W) or ({view_count}, H, W), got shape {depth.shape}")


def renderer_from_args(args: argparse.Namespace, method: str):
    from volren.presets import quality_options
    from volren.render import METHODS
    from volren.render.gi.ambient import GIConfig

    check_method(method)
    cls, config_cls = METHODS[method]
    fields = {f.name for f in dataclasses.fields(config_cls)}
    # config field -> (value given on the command line or None, the flag that gives it)
    given = {
        "samples": (args.samples, "--samples"),
        "light_samples": (args.light_samples, "--light-samples"),
        "light_grid": (args.light_grid, "--light-grid"),
        "jitter": (args.jitter or None, "--jitter"),
        "cube_faces": (args.cube_faces, "--cube-faces"),
        "cube_size": (args.cube_size, "--cube-size"),
        "adaptive_lod": (False if args.no_lod else None, "--no-lod"),
        "hybrid": (False if args.no_hybrid else None, "--no-hybrid"),
        "cull_tiles": (False if args.no_cull else None, "--no-cull"),
        "skip_empty": (False if args.no_skip else None, "--no-skip"),
        "tile_lod": (args.tile_lod or None, "--tile-lod"),
        "k_z": (args.k_z, "--k-z"),
        "coupling": (False if args.no_coupling else None, "--no-coupling"),
        "share_voxels": (False if args.no_share else None, "--no-share"),
        "vsa": (False if args.no_vsa else None, "--no-vsa"),
        "k_a": (args.k_a, "--k-a"),
        "interleave": (False if args.no_interleave else None, "--no-interleave"),
        "mode": (None if args.mode in (None, "dvr") else args.mode, "--mode"),
        "iso_value": (args.iso_value, "--iso-value"),
        "oit": (args.oit, "--oit"),
        "oit_k": (args.oit_k, "--oit-k"),
        "spp": (args.spp, "--spp"),
        "max_bounces": (args.max_bounces, "--max-bounces"),
        "shading": (args.shading, "--shading"),
        "transfer": (args.tf, "--tf"),
        "ambient": (args.vpt_ambient or None, "--vpt-ambient"),
        "clip": (args.clip, "--clip"),
        "denoise": (args.denoise, "--denoise"),
        "sharing": (args.fog_sharing, "--fog-sharing"),
        "voxel_size": (args.voxel_size, "--voxel-size"),
        "slices": (args.slices, "--slices"),
        "tile": (args.froxel_size, "--froxel-size"),
        "far": (args.fog_far, "--fog-far"),
        "trilinear": (args.trilinear or None, "--trilinear"),
        "temporal": (False if args.no_temporal else None, "--no-temporal"),
    }
    if args.iso_value is not None and args.mode != "iso":
        raise CliError("--iso-value needs --mode iso")
    if args.k_a is not None and (args.no_vsa or args.mode not in (None, "dvr")):
        raise CliError("--k-a sets VSA's ramp, which marches in --mode dvr only and not with --no-vsa")
    gi = {"method": (args.gi, "--gi"), "order": (args.gi_order, "--gi-order"), "rays": (args.gi_rays, "--gi-rays"),
          "volumes_per_frame": (args.gi_volumes, "--gi-volumes")}
    gi_options = {k: v for k, (v, _) in gi.items() if v is not None}
    if gi_options:
        if gi_options.get("method", "none") == "none" and len(gi_options) > (1 if "method" in gi_options else 0):
            raise CliError("--gi-order, --gi-rays and --gi-volumes need --gi with a method other than none")
        given["gi"] = (GIConfig(**gi_options), ", ".join(flag for k, (v, flag) in gi.items() if v is not None))
    # the preset first: a flag given on the command line overrides the field it sets
    options = quality_options(method, args.quality)
    options |= {k: v for k, (v, _) in given.items() if v is not None and k in fields}
    ignored = [flag for k, (v, flag) in given.items() if v is not None and k not in fields]
    if ignored:
        raise CliError(f"method '{method}' does not take {', '.join(ignored)}")
    if args.tf is not None:
        replaced = [flag for k, flag in (("density_scale", "--density-scale"), ("albedo", "--albedo"),
                                         ("emission", "--emission")) if getattr(args, k, None) is not None]
        if replaced:
            raise CliError(f"--tf gives the extinction, albedo and emission: {', '.join(replaced)} would do nothing")
    if "seed" in fields:
        options["seed"] = args.seed
    channels = len(_volume_from_args(args).channels) if getattr(args, "volume", None) is not None else 0
    if channels:  # each channel its own renderer, the images added
        from volren.render.compositing.channels import AdditiveChannels

        return AdditiveChannels(lambda: cls(config_cls(**options), device=args.device), channels)
    return cls(config_cls(**options), device=args.device)


def sequence_from_args(args: argparse.Namespace):
    """``volren animate``'s sequence; None for ``render``."""
    if args.command != "animate":
        return None
    from volren.animate import Sequence

    switch_frame = switch_tf = None
    if args.switch_tf is not None:
        frame, sep, tf = args.switch_tf.partition(":")
        if not sep or not frame.strip().isdecimal():
            raise CliError(f"--switch-tf must be FRAME:TF, got '{args.switch_tf}'")
        switch_frame, switch_tf = int(frame), tf
    return Sequence(frames=args.frames, orbit=args.orbit, light_orbit=args.light_orbit, switch_frame=switch_frame,
                    switch_transfer=switch_tf, fps=args.fps)


def mesh_alphas(values: list[float], meshes: int) -> list[float]:
    """One opacity per --mesh from --mesh-alpha: none (all opaque), one for all, or one each."""
    if len(values) not in (0, 1, meshes):
        raise CliError(f"--mesh-alpha given {len(values)} times for {meshes} --mesh: give it once or once per --mesh")
    bad = [a for a in values if not 0.0 <= a <= 1.0]
    if bad:
        raise CliError(f"--mesh-alpha must lie in [0, 1], got {bad[0]:g}")
    return values * meshes if len(values) == 1 else values or [1.0] * meshes


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


def check_method(method: str) -> None:
    if method not in METHOD_NAMES:
        raise CliError(f"unknown method '{method}': choose from {', '.join(METHOD_NAMES)}")


def check_scene_name(name: str | None) -> None:
    if name is not None and name not in SCENE_NAMES:
        raise CliError(f"--scene: unknown scene '{name}': choose from {', '.join(SCENE_NAMES)}")


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
    renderer's config). The in-process loop of `run_render` and the batch engine's workers
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
            views = views_from_args(args, i / ANIMATION_FPS)
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
    """`run_render`'s checks that need no data: the imports after them take seconds."""
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
    views = views_from_args(args)
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


def iso_value_from_data(args: argparse.Namespace, scene, renderer) -> dict:
    """``--mode iso``: without --iso-value, V is Otsu's threshold of the scene's densities (`otsu_iso_value`), set in
    the renderer's config and ``args`` and said in one line; a given V outside the densities is warned of in one line
    (`iso_range_message`) before any rendering. Returns stats.json's ``iso_value`` entry when V was chosen here."""
    if getattr(renderer.config, "mode", "dvr") != "iso":
        return {}
    from volren.render.marching.modes import iso_range_message, otsu_iso_value

    densities = [v.density for v in scene.volumes]
    lo, hi = min(float(d.min()) for d in densities), max(float(d.max()) for d in densities)
    if args.iso_value is not None:
        message = iso_range_message(args.iso_value, lo, hi)
        if message:
            warn(message)
        return {}
    value = otsu_iso_value(densities)
    args.iso_value = value  # for the renderers made from args later (the run-time probe)
    renderer.config = dataclasses.replace(renderer.config, iso_value=value)
    print(f"volren: --mode iso without --iso-value: the isosurface is at density {value:.4g}, Otsu's threshold of "
          f"the densities {lo:.4g} to {hi:.4g} (give --iso-value to choose)", file=sys.stderr)
    return {"iso_value": {"value": value, "rule": "otsu", "densities": [lo, hi]}}


def frame_prefix(args: argparse.Namespace, i: int) -> str:
    """What tells frame i's files apart in a run of several frames (none in a run of one)."""
    return f"frame{i:04d}_" if args.frames > 1 else ""


def write_plan_frame(plan: RenderPlan, frame, out: Path) -> list[Path]:
    """`write_frame` with the run's output flags: frame ``frame.index``'s files into ``out``."""
    from volren.output import write_frame

    args = plan.args
    return write_frame(frame, out, frame.background, exposure=args.exposure, tonemap=args.tonemap,
                       linear=args.save_linear, prefix=frame_prefix(args, frame.index))


def run_render(args: argparse.Namespace, method: str, command: str, plan: RenderPlan | None = None) -> int:
    """``volren render``/``animate`` (``plan``: already made from ``args``, by `volren batch`'s checks)."""
    check_render_args(args, method)  # before the imports of either path
    if getattr(args, "workers", None) is not None or getattr(args, "ray_address", None) is not None:
        from volren.distributed.engine import run_command_on_ray

        return run_command_on_ray(args)
    plan = plan or plan_render(args, method)
    from volren.animate import write_mp4
    from volren.imageio import composite, to_srgb8
    from volren.output import contact_sheet, run_output, write_stats
    from volren.progress import progress

    frames, files, movie = [], [], []
    start = time.perf_counter()
    with run_output(args.out) as out:  # written beside --out, moved in when complete
        rows = args.frames * sum(v.height for v in plan.views)  # each view's image pass reports its rows
        with progress(f"{method} {plan.scene.name}", rows, always=args.frames > 1) as advance:
            plan.renderer.on_rows = advance
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
    files, stats = [args.out / f.name for f in files], args.out / stats.name
    print_summary(method, plan.scene.name, len(plan.views), args.frames, wall, frames[-1].stats, files, stats)
    return 0


def print_summary(method: str, scene: str, views: int, frames: int, wall: float, last, files: list,
                  stats: Path) -> None:
    """The lines a render ends with: what ran, the last frame's pass times and work, the files written."""
    print(f"{method} on {last.device}: {views} view(s) of '{scene}', {frames} frame(s) in {wall:.2f} s")
    print("  last frame, ms per pass: " + ", ".join(f"{k} {v:.1f}" for k, v in last.times_ms.items()))
    print("  work: " + ", ".join(f"{k} {v:,}" for k, v in last.counters.items()))
    shown = files if len(files) <= 8 else [*files[:6], f"... ({len(files) - 6} more)"]
    print("  wrote " + ", ".join(str(f) for f in [*shown, stats]))


def run_scenes() -> int:
    from volren.data import BUILTIN_SCENES
    from volren.data.fog_scenes import FOG_SCENES

    width = max(len(n) for n in [*BUILTIN_SCENES, *FOG_SCENES])
    for name, spec in BUILTIN_SCENES.items():
        print(f"{name:<{width}}  {spec.description}")
    for name, description in FOG_SCENES.items():
        print(f"{name:<{width}}  {description} (meshes and fog: --method fog)")
    return 0


def run_compare(args: argparse.Namespace) -> int:
    from volren.metrics import compare_files

    heatmap = args.heatmap or args.test.with_name(args.test.stem + "_error.png")
    result = compare_files(args.ref, args.test, heatmap)
    print(f"PSNR {result['psnr']:.2f} dB  SSIM {result['ssim']:.5f}  FLIP {result['flip']:.5f}  "
          f"max |error| {result['max_abs_error']:.4g}")
    print(f"  heat map (per-pixel L1 of normalised RGB, 0..25%): {heatmap}")
    return 0


def bench_overrides(settings: list[str]) -> dict[str, Any]:
    """``--set KEY=VALUE`` entries: VALUE read as JSON (numbers, lists), else as a string."""
    out: dict[str, Any] = {}
    for item in settings:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise CliError(f"--set takes KEY=VALUE, got '{item}'")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def run_bench(args: argparse.Namespace) -> int:
    from volren.bench.runner import all_suites, run_suite

    if args.suite == "list":
        for name, suite in all_suites().items():
            print(f"{name}: {suite.description}")
        return 0
    suite = None
    if args.shards is not None:
        if args.suite != "serve":
            raise CliError(f"--shards: bench serve only (the sharded server), not bench {args.suite}")
        from volren.bench.serve import shard_suite

        try:
            suite = shard_suite([int(n) for n in args.shards.split(",")])
        except ValueError:
            raise CliError(f"--shards must be comma-separated shard counts like 1,2, got {args.shards}") from None
    json_path, md_path, table = run_suite(suite.name if suite else args.suite, quick=args.quick, device=args.device,
                                          out=args.out, suite=suite, repeats=args.repeats,
                                          overrides=bench_overrides(args.settings))
    print(table)
    print(f"wrote {json_path} and {md_path}")
    return 0


def run_command(args: argparse.Namespace, command: str) -> int:
    if args.command == "demo":
        return run_render(args, "dssrm", command)
    if args.command in ("render", "animate"):
        return run_render(args, args.method, command)
    if args.command == "scenes":
        return run_scenes()
    if args.command == "compare":
        return run_compare(args)
    if args.command == "serve":
        return run_serve(args)
    if args.command == "batch":
        from volren.distributed.job import run_batch

        return run_batch(args)
    return run_bench(args)


def main(argv: Sequence[str] | None = None) -> int:
    from volren.errors import Terminated

    console = argv is None  # the volren command, not a caller in Python
    argv = list(sys.argv[1:] if argv is None else argv)
    command = " ".join(["volren", *argv])
    try:
        args = build_parser().parse_args(argv)
        args.argv = tuple(argv)  # what the batch engine's workers parse again (--workers)
        _warned.clear()
        with warnings.catch_warnings():
            warnings.simplefilter("always", VolrenWarning)  # `warn` says each once
            warnings.showwarning = functools.partial(_show_warning, warnings.showwarning)
            code = run_command(args, command)
        sys.stdout.flush()  # a reader that left shows here, not in Python's exit-time flush
        if console and "warp" in sys.modules:
            # every output is closed by now; the interpreter's teardown with Warp loaded waits 2-4 s in native code
            sys.stderr.flush()
            os._exit(code)
        return code
    except BrokenPipeError:
        # `volren scenes | head -1`: the reader has all it wanted. Stop quietly with the status SIGPIPE would give,
        # and point stdout at /dev/null so the exit-time flush has nowhere to fail.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except VolrenError as exc:
        print(f"volren: error: {exc}", file=sys.stderr)
        return 2
    except MemoryError:
        print("volren: error: out of memory (try a smaller image, resolution or view count)", file=sys.stderr)
        return 2
    except OSError as exc:  # what no loader or writer turned into a VolrenError: stdout on a full disk, mostly
        print(f"volren: error: cannot write {exc.filename or 'stdout'}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except Terminated:  # SIGTERM during a run on Ray: stopped as Ctrl-C stops it (below), 128 + SIGTERM
        print("volren: terminated", file=sys.stderr)
        if console:
            sys.stderr.flush()
            os._exit(128 + signal.SIGTERM)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print("volren: interrupted", file=sys.stderr)
        if console:  # run_output has removed any partial run; the interpreter's exit would wait seconds on Warp
            sys.stderr.flush()
            os._exit(130)
        return 130


if __name__ == "__main__":
    sys.exit(main())
