"""Read an OME-Zarr multiscale image (NGFF 0.4 and 0.5) or a plain Zarr array as a ``Grid`` for ``load_volume``.

OME-Zarr (https://ngff.openmicroscopy.org/0.5/#multiscale-md): the group's ``multiscales[0]`` lists ``axes`` (name,
type ``space`` / ``channel`` / ``time``, a unit such as ``micrometer``) and ``datasets`` finest first, each with
``coordinateTransformations``: a ``scale`` and an optional ``translation`` per axis mapping a voxel index to its centre
(coordinate = index * scale + translation), followed by the multiscale's own optional transformations. Only the one
level chosen is read from disk (zarr reads the chunks of that array only), never the pyramid.

One volume per file: a ``t`` axis of length 1 (bioformats2raw's ``tczyx``) is dropped; a longer one (a time-lapse),
or any other axis that is neither space nor channel, is refused in one line naming the file, the axis and its length,
rather than read as its first time point (sequences are numbered files: `volren.data.sequence`).

Chunks not on disk: zarr reads them as the array's fill value, and leaves out by design a chunk that holds only
that value, so an absent chunk is either empty or lost. A level with no chunk on disk is refused; a chunk absent
where the next coarser level holds data is a hole, and the holes are warned of in one line naming the store
(`_missing_chunks`). The coarsest level, with nothing to compare, is read as zarr reads it.

Orientation: as microscopy viewers show an image (row 0 at the top, x to the right, z away from the viewer), the
file's x, y, z axes map onto the world's +x, -y, -z (a rotation, nothing mirrored): the default camera, looking down
-z, sees row 0 at the top of the picture, as TIFF pages.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from volren.data.grid import Grid, one_line
from volren.data.ngff import _attributes, _axes, _fill, _scale_translation, coarser_inner_box
from volren.errors import VolrenError, VolrenWarning

DEFAULT_MEMORY_BUDGET = 1 << 30
"""[bytes] of float32 voxels (all channels) the automatically chosen level may take: 1 GiB."""
NGFF_UNITS = {"angstrom": 1e-10, "nanometer": 1e-9, "micrometer": 1e-6, "millimeter": 1e-3, "centimeter": 1e-2,
              "meter": 1.0, "kilometer": 1e3, "nm": 1e-9, "um": 1e-6, "µm": 1e-6, "mm": 1e-3, "cm": 1e-2, "m": 1.0}
"""[m] per unit of the NGFF space units volren meets (UDUNITS-2 names; short forms some writers use)."""
IMAGE_SPACE = "LIP"
"""the file's x, y, z as anatomical letters (`volren.data.loaders`): Left = world +x, Inferior = -y, Posterior = -z."""


def _choose_level(path: Path, shapes: list[tuple[int, ...]], level: int | None, budget: float) -> int:
    """``level`` if given, else the finest level whose float32 voxels fit in ``budget`` bytes."""
    if level is not None:
        if not 0 <= level < len(shapes):
            raise VolrenError(f"{path}: level {level} is out of range: the pyramid has levels 0 to {len(shapes) - 1} "
                              "(CLI: --level)")
        return level
    sizes = [4 * int(np.prod(s, dtype=np.int64)) for s in shapes]
    fitting = [i for i, n in enumerate(sizes) if n <= budget]
    if not fitting:
        raise VolrenError(f"{path}: even the coarsest level ({len(shapes) - 1}, {sizes[-1] / 2**30:.2f} GiB of "
                          f"float32) exceeds the memory budget of {budget / 2**30:.2f} GiB; raise memory_budget (CLI: "
                          "--memory-budget)")
    return min(fitting)


def read_zarr(path: Path | str, *, level: int | None = None, memory_budget: float | None = None,
              stream: bool | None = None) -> Grid:
    """The voxels of one pyramid level of an OME-Zarr image as ``[c,] z, y, x`` (a ``t`` axis of length 1 is
    dropped), placed by its coordinate transformations: index -> file coordinates in the axes' unit (or in metres
    where the spatial axes' units differ). A plain Zarr array is read as a ``.npy`` would be (no placement).

    Streaming (issue 41 item 3): a pyramid whose finest level does not fit ``memory_budget`` (and no ``level``
    asked for), or any pyramid with ``stream`` True, is not read here: its finest level is a
    `volren.stream.density.StreamedDensity`, read brick by brick as the views need them within the budget; a
    multi-channel one is a tuple of them, one per channel with budget / C each (`_streamed_channels`)."""
    import zarr  # lazy: only Zarr users pay for the import

    budget = DEFAULT_MEMORY_BUDGET if memory_budget is None else float(memory_budget)
    if not (np.isfinite(budget) and budget > 0):
        raise VolrenError(f"memory_budget must be a positive number of bytes, got {memory_budget!r} "
                          "(CLI: --memory-budget GIB)")
    if isinstance(path, Path) and not path.exists():  # a URL (a str) is found, or not, by fsspec
        raise VolrenError(f"{path}: file not found")
    try:
        node = zarr.open(str(path), mode="r")
    except Exception as exc:  # zarr raises several types for a folder that is no Zarr
        raise VolrenError(f"{path}: not a readable Zarr store ({one_line(exc)})") from None
    if isinstance(node, zarr.Array):
        if level is not None:
            raise VolrenError(f"{path}: a plain Zarr array has no pyramid levels; level applies to OME-Zarr (CLI: "
                              "--level)")
        return Grid(np.asarray(node[...]))
    try:
        return _read_multiscale(path, node, level, budget, stream)
    except VolrenError:
        raise
    except Exception as exc:  # KeyError, TypeError, ValueError, ...: metadata that is not NGFF
        raise VolrenError(f"{path}: malformed OME-Zarr metadata ({one_line(exc)})") from None


def _read_multiscale(path: Path, group: Any, level: int | None, budget: float, stream: bool | None) -> Grid:
    attrs = _attributes(group)
    if "multiscales" not in attrs:
        raise VolrenError(f"{path}: a Zarr group without OME-Zarr 'multiscales' metadata (arrays: "
                          f"{', '.join(sorted(group.array_keys())) or 'none'})")
    multiscale = attrs["multiscales"][0]
    datasets = multiscale["datasets"]
    if not datasets:
        raise ValueError("'datasets' is empty")
    arrays = [group[str(d["path"])] for d in datasets]
    axes = _axes(multiscale, arrays[0].ndim)
    names = [a[0] for a in axes]
    space = [i for i, a in enumerate(axes) if a[1] == "space"]
    if [names[i] for i in space] != ["z", "y", "x"]:
        raise VolrenError(f"{path}: axes {''.join(names)}: volren needs the space axes z, y, x in that order")
    keep = [i for i, a in enumerate(axes) if a[1] == "channel"] + space
    for i, (name, _, _) in enumerate(axes):
        if i not in keep and arrays[0].shape[i] != 1:
            raise VolrenError(f"{path}: axis '{name}' has {arrays[0].shape[i]} entries; volren reads one volume "
                              "(a channel axis 'c' and z, y, x)")
    if len(keep) > 4:
        raise VolrenError(f"{path}: axes {''.join(names)} hold more than one channel axis")
    shapes = [tuple(a.shape[i] for i in keep) for a in arrays]
    if stream and level is not None:
        raise VolrenError(f"{path}: stream= reads a pyramid brick by brick; it takes no level= and reads the finest "
                          "level")
    streaming = (stream if stream is not None else level is None and 4 * math.prod(shapes[0]) > budget)
    streaming = streaming and len(arrays) > 1
    chosen = 0 if streaming else _choose_level(path, shapes, level, budget)
    ndim = len(axes)
    scale, offset = _scale_translation(datasets[chosen]["coordinateTransformations"], ndim)
    outer_scale, outer_offset = _scale_translation(multiscale.get("coordinateTransformations", []), ndim)
    scale, offset = scale * outer_scale, offset * outer_scale + outer_offset
    index = tuple(slice(None) if i in keep else 0 for i in range(ndim))
    windows = _omero_windows(attrs, shapes[0][0] if len(keep) == 4 else 1)
    if streaming and len(keep) == 4:
        data, source_dtype = _streamed_channels(path, arrays[-1], index, keep[0], budget, windows), ""
    elif streaming:
        data = _streamed(path, np.asarray(arrays[-1][index]), budget, peak=windows[0])
        source_dtype = arrays[0].dtype.name
    else:
        data, source_dtype = _read_level(path, arrays, chosen, index, keep), ""
    if len(keep) == 4 and not streaming:  # the channel axis first, whatever its place among the kept axes
        data = np.moveaxis(data, sorted(keep).index(keep[0]), 0)
    # index (i, j, k) = (x, y, z) -> file coordinates; the NGFF axes run z, y, x
    step, origin = scale[space][::-1], offset[space][::-1]
    units = [axes[i][2] for i in space]
    metres = [NGFF_UNITS.get(str(u).lower()) if u is not None else None for u in units]
    if any(u is not None and m is None for u, m in zip(units, metres, strict=True)):
        raise VolrenError(f"{path}: unknown space unit in {units}; volren knows {', '.join(NGFF_UNITS)}")
    if not all(v > 0 for v in step):
        raise VolrenError(f"{path}: level {chosen}'s voxel size {step.tolist()} (x, y, z) is not positive")
    if len(set(metres)) == 1:  # one unit (or none: --units or millimetres then)
        metres_per_unit = metres[0]
    elif None in metres:
        raise VolrenError(f"{path}: some space axes state a unit and some do not ({units})")
    else:  # differing units: convert each axis to metres here
        step, origin, metres_per_unit = step * metres[::-1], origin * metres[::-1], 1.0
    m = np.eye(4)
    m[:3, :3] = np.diag(step)
    m[:3, 3] = origin
    colors = _omero_colors(attrs, shapes[0][0]) if len(keep) == 4 else ()
    return Grid(data, m, IMAGE_SPACE, metres_per_unit, level=chosen, channel_colors=colors, source=source_dtype)


def _read_level(path: Path, arrays: list[Any], chosen: int, index: tuple, keep: list[int]) -> np.ndarray:
    """Level ``chosen``'s voxels (its chunks only), holes warned of (module docstring)."""
    level = arrays[chosen]
    stored, chunks = level.nchunks_initialized, level.nchunks  # the first lists the level's keys
    if stored == 0:
        raise VolrenError(f"{path}: level {chosen} has none of its {chunks} chunks on disk (every voxel would read "
                          f"as the fill value {_fill(level):g}): an incomplete copy?")
    data = np.asarray(level[index])  # this level's chunks only
    if stored < chunks and chosen + 1 < len(arrays):
        holes = _missing_chunks(data, level, np.asarray(arrays[chosen + 1][index]), keep)
        if holes:
            warnings.warn(f"{path}: level {chosen} is missing {holes} of its {chunks} chunks where level {chosen + 1} "
                          f"holds data; zarr reads them as the fill value {_fill(level):g} (holes in the volume)",
                          VolrenWarning, stacklevel=3)
    return data


def _streamed(path: Path, raw: np.ndarray, budget: float, *, channel: int | None = None,
              window: tuple[float, float] | None = None, peak: tuple[float, float] | None = None):
    """The pyramid (its channel ``channel``) as a `volren.stream.density.StreamedDensity` within ``budget`` bytes,
    ``raw`` its coarsest level. One channel maps its values as `volren.data.loaders` maps a level read whole
    (integers by their bit depth or range, judged on ``raw``; floats as they are); a channel of several maps
    ``window`` (lo, hi) onto 0..1, as the loader's per-channel min-max does. ``peak``: the file's (lo, hi) of the
    values (omero ``window``), whose hi stands for the largest density (MIP's normalisation) where the coarsest
    level's means fall below it."""
    from volren.stream.density import StreamedDensity  # lazy: the stream package only for pyramids that stream
    from volren.stream.source import PyramidSource

    if window is not None:
        lo, hi = window
    elif raw.dtype == np.bool_ or np.issubdtype(raw.dtype, np.integer):
        hi = float(raw.max()) if raw.size else 0.0
        if np.issubdtype(raw.dtype, np.signedinteger):
            lo = float(raw.min()) if raw.size else 0.0
        else:
            lo, hi = 0.0, float(max(hi, 2 ** max(8, int(hi).bit_length()) - 1)) if raw.dtype != np.bool_ else 1.0
    else:  # floats as they are
        lo, hi = 0.0, 1.0
    scale, offset = (1.0 / (hi - lo), -lo / (hi - lo)) if hi > lo else (1.0, -lo)
    top = None if peak is None else peak[1] * scale + offset
    return StreamedDensity(PyramidSource(path, channel=channel), budget, scale, offset, peak=top)


def _streamed_channels(path: Path, coarsest: Any, index: tuple, axis: int, budget: float,
                       windows: list[tuple[float, float] | None]) -> tuple:
    """Each channel c of a multi-channel pyramid streamed alone (`_streamed`) within budget / C, its values mapped
    by its own range as the loader maps a channel read whole (min-max): the omero ``window`` (start, end) where the
    file states one (the contrast limits viewers such as napari show), else the coarsest level's min and max (a
    level's extremes lie within the finest level's, so the window the channel's dense read would use is at least
    this wide)."""
    count = len(windows)
    out = []
    for c, window in enumerate(windows):
        raw = np.asarray(coarsest[tuple(c if i == axis else s for i, s in enumerate(index))])
        rng = window or ((float(raw.min()), float(raw.max())) if raw.size else (0.0, 0.0))
        out.append(_streamed(path, raw, budget / count, channel=c, window=rng, peak=window))
    return tuple(out)


def _omero_windows(attrs: dict[str, Any], count: int) -> list[tuple[float, float] | None]:
    """Each channel's omero ``window`` as (start, end), or (min, max) where start or end is missing; None for a
    channel that states neither (or where the omero channels do not number ``count``)."""
    omero = attrs.get("omero")
    channels = omero.get("channels", []) if isinstance(omero, dict) else []
    if not isinstance(channels, list) or len(channels) != count:
        return [None] * count
    out: list[tuple[float, float] | None] = []
    for channel in channels:
        window = channel.get("window") if isinstance(channel, dict) else None
        window = window if isinstance(window, dict) else {}
        pair = next(((window[a], window[b]) for a, b in (("start", "end"), ("min", "max"))
                     if isinstance(window.get(a), int | float) and isinstance(window.get(b), int | float)), None)
        out.append(None if pair is None else (float(pair[0]), float(pair[1])))
    return out


def _missing_chunks(data: np.ndarray, array: Any, coarser: np.ndarray, keep: list[int]) -> int:
    """How many chunks (shards, where the array is sharded) of the level read as ``data`` (``array``'s kept axes
    ``keep``) are missing rather than empty: zarr leaves out a chunk that holds only the fill value, so an absent
    chunk is a hole only where the next coarser level (read as ``coarser``) holds data in the same box, its
    margins (`volren.data.ngff.CHUNK_MARGIN`) left out."""
    fill = _fill(array)
    unit = [(getattr(array, "shards", None) or array.chunks)[i] for i in sorted(keep)]
    ratio = [c / f for c, f in zip(coarser.shape, data.shape, strict=True)]
    holes = 0
    for corner in np.ndindex(*(-(-n // u) for n, u in zip(data.shape, unit, strict=True))):
        box = [(k * u, min((k + 1) * u, n)) for k, u, n in zip(corner, unit, data.shape, strict=True)]
        block = data[tuple(slice(a, b) for a, b in box)]
        if not (np.all(block == fill) or (np.isnan(fill) and np.all(np.isnan(block)))):
            continue
        inner = coarser_inner_box(box, ratio)
        if all(s.start < s.stop for s in inner):
            region = coarser[tuple(inner)]
            holes += bool(np.any((region != fill) & ~np.isnan(region)))
    return holes


def _omero_colors(attrs: dict[str, Any], count: int) -> tuple[tuple[float, float, float], ...]:
    """The channels' display colours of the (transitional) ``omero`` metadata, hex ``RRGGBB``; () unless every
    channel has one."""
    channels = attrs.get("omero", {}).get("channels", []) if isinstance(attrs.get("omero"), dict) else []
    colors = [str(c.get("color", "")) if isinstance(c, dict) else "" for c in channels]
    if len(colors) != count or not all(len(c) == 6 and all(h in "0123456789abcdefABCDEF" for h in c) for c in colors):
        return ()
    return tuple(tuple(int(c[i : i + 2], 16) / 255 for i in (0, 2, 4)) for c in colors)
