"""A ``--volume`` file or sequence: read once with the options that say how, its scene (one volume, or one per
channel), and the checks of the flags that only a file takes."""

from __future__ import annotations

import argparse
import functools
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from volren.errors import VolrenError, flag
from volren.plan.options import CliError
from volren.store import StoreURL

if TYPE_CHECKING:
    from volren.data.loaders import LoadedVolume
    from volren.render.compositing.channels import Channels
    from volren.scene import Volume

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


def check_memory_budget(budget: float | None, level: int | None, words: Callable[[str], str] = flag) -> None:
    """--memory-budget [GiB]: a positive number no larger than the machine's memory (a level it would admit could
    not be held), and not beside --level, which names the level the budget would choose; the options named in
    ``words`` (`volren.errors.flag`, or `keyword` for the Python API)."""
    if budget is None:
        return
    if level is not None:
        raise CliError(f"{words('memory_budget')} chooses a level by its size; {words('level')} {level} names the "
                       "level, so the budget would do nothing: give one of them")
    if isinstance(budget, bool) or not isinstance(budget, int | float):
        raise CliError(f"{words('memory_budget')} must be a positive number of GiB, got {budget!r}")
    if not (math.isfinite(budget) and budget > 0):
        raise CliError(f"{words('memory_budget')} must be a positive number of GiB, got {budget:g}")
    memory = host_memory()
    if memory is not None and budget * 2**30 > memory:
        raise CliError(f"{words('memory_budget')} {budget:g} GiB exceeds this machine's memory "
                       f"({memory / 2**30:.1f} GiB): a level that large could not be read")


def channel_scene(args: argparse.Namespace, loaded):
    """A multi-channel ``--volume``: one volume per channel glowing in its colour, unlit
    (`volren.render.compositing.channels`); material and light flags would do nothing and are refused."""
    unused = [name for name, value in (
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
    return file_channels(loaded, args.volume, args.channel_colors, args.channel_opacity).scene


def file_channels(loaded: LoadedVolume, path: Path, colors=None, opacity=None,
                  words: Callable[[str], str] = flag) -> Channels:
    """A multi-channel file's `Channels`: one unlit volume per channel in ``colors`` (given, else the file's own:
    OME-Zarr omero; else the palette) with ``opacity`` (`volren.render.compositing.channels.channel_volumes`), the
    options named in ``words``."""
    from volren.render.compositing.channels import Channels, channel_volumes

    volumes = channel_volumes(loaded.channels, loaded.to_world, colors=colors or loaded.channel_colors or None,
                              opacity=opacity, name=path.name, words=words)
    return Channels(volumes, name=path.stem)


def _file_scene(args: argparse.Namespace, frame: int = 0):
    """``--volume``'s scene (of frame ``frame`` of a sequence), before the material and light overrides."""
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
    set it: "--density-scale" (given, per metre) or "box" (`box_density_scale`: ``optical_depth`` at
    density 1 across the box's ``longest_side`` [m])."""
    from volren.scene import box_longest_side

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
    if getattr(args, "volume", None) is None or isinstance(args.volume, StoreURL):  # a store's URL: one volume
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
    return VolumeSequence(SequenceConfig(files, loop=loop), lambda frame, **box: _read_volume(frame, *options, **box))


class VolumeSequence:
    """A volume sequence as `volren.load` opens it (numbered files ``sim_####.npy``, ``sim_%04d.vdb``, a glob, a
    folder of numbered files, or a 4-D NIfTI's time points): lazy, frame i read when asked (the next ones read ahead
    in a thread, at most 3 held: `volren.data.sequence.VolumeSequence`, which checks every frame against the first
    and maps its values as the first's), each a `Volume` (or `Channels`) made as ``volren render --volume PATTERN``
    makes frame i. ``len``, indexing (negative too) and iteration give the frames; `volren.render` renders them
    (``frames=``), `volren.Viewer` plays them."""

    def __init__(self, path: str | Path, reader, make: Callable[[LoadedVolume], Any]) -> None:
        self.path = Path(path)
        """the pattern, folder or 4-D NIfTI named"""
        self._reader, self._make = reader, make
        make(reader.frame(0))  # the first frame's options checked now (channel_colors= on one channel, ...)

    def __len__(self) -> int:
        return len(self._reader)

    @property
    def files(self) -> tuple:
        """Each frame's file (or `volren.data.loaders.TimePoint` of a 4-D NIfTI), in frame order."""
        return self._reader.config.files

    def __getitem__(self, i: int):
        """Frame ``i`` (negative counts from the end): a `Volume`, or `Channels` for a multi-channel sequence."""
        n = len(self)
        if isinstance(i, bool) or not isinstance(i, int):
            raise VolrenError(f"a VolumeSequence is indexed by a frame number, got {type(i).__name__}")
        if not -n <= i < n:
            raise IndexError(f"frame {i} is outside the sequence's {n} frames")
        return self._make(self._reader.frame(i % n))

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    def __repr__(self) -> str:
        """A summary: frame count and files, the first frame's grid, box and value mapping (every frame's)."""
        from volren.scene import box_sides

        first, files = self._reader.first, self.files
        nz, ny, nx = first.shape
        centre = ", ".join(f"{c:.3g}" for c in first.to_world[:3, 3])
        parts = [f"{str(self.path)!r}", f"{len(self)} frames ({files[0].name} .. {files[-1].name})",
                 f"{nx}x{ny}x{nz} (x, y, z)" + (f" in {first.channels} channels" if first.channels else ""),
                 f"box {' x '.join(f'{e:.3g}' for e in box_sides(first.to_world))} m at ({centre})"]
        if first.value_mapping is not None:
            m = first.value_mapping
            parts.append(f"values {m.source}" + ("" if m.range is None else f" {m.range[0]:g}..{m.range[1]:g}")
                         + ("" if m.units == "raw" else f" {m.units}") + " -> density")
        return f"VolumeSequence({', '.join(parts)})"


def _load_volume(path: Path, shape, dtype, spacing, units, grid=None, level=None, memory_budget=None,
                 emission_grid=None):
    """``--volume`` read once: the scene and the default camera framing both need it (keyed on the file's mtime too,
    so a rewritten file is read again). One DICOM file (``.dcm``, or DICOM content without another extension) stands
    for its series: the files of its folder with its SeriesInstanceUID (other series beside it are skipped)."""
    from volren.data.loaders import dicom_member

    dicom_file = not isinstance(path, StoreURL) and dicom_member(path, shape)
    source = path.parent if dicom_file else path
    stamp = source.stat().st_mtime_ns if not isinstance(path, StoreURL) and source.exists() else None
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


def _read_volume(path: Path, shape, dtype, spacing, units, grid, level, memory_budget, emission_grid,
                 index_box=None):
    from volren.data.loaders import load_volume

    budget = None if memory_budget is None else memory_budget * 2**30  # --memory-budget is in GiB
    return load_volume(path, shape=shape, dtype=dtype, spacing=spacing, units=units, grid=grid, level=level,
                       memory_budget=budget, emission_grid=emission_grid, index_box=index_box)
