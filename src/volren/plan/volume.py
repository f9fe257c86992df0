"""A ``--volume`` file or sequence: read once with the options that say how, its scene (one volume, or one per
channel), and the checks of the flags that only a file takes."""

from __future__ import annotations

import argparse
import functools
import math
import os
from pathlib import Path

from volren.errors import VolrenError
from volren.plan.options import CliError


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


def _file_scene(args: argparse.Namespace, frame: int = 0):
    """``--volume``'s scene (of frame ``frame`` of a sequence), before the material and light overrides."""
    from volren.plan.defaults import volume_from_file
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
    from volren.plan.defaults import BOX_OPTICAL_DEPTH, box_density_scale
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
