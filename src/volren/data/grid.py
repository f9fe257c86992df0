"""What a file reader returns before placement and normalisation (`volren.data.loaders`): the voxels and what the
file says about them. Its own module so the readers (loaders, dicom, omezarr) import it one way, not each other."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Grid:
    """What a reader found: the voxels, and where the file puts them (if it says)."""

    data: np.ndarray
    index_to_file: np.ndarray | None = None
    """4x4: voxel index (i, j, k) = (x, y, z) to the file's coordinates; None when the file stores no placement."""
    space: str = ""
    """anatomical axis code of the file's coordinates ("LPS", "RAS", ...), "" for plain x, y, z."""
    metres_per_unit: float | None = None
    """the unit the file states, None when it states none (then millimetres are assumed)."""
    rescale: bool = False
    """min-max normalise floats too (DICOM Hounsfield units are floats that go below zero)."""
    units: str = ""
    """what the file says its values are: "HU", "Gy", "relative" (dose), "" when it says nothing."""
    bits_stored: int | None = None
    """the bits of an unsigned integer the file says are used (DICOM BitsStored); None: the data's own depth."""
    source: str = ""
    """the stored values' dtype when ``data`` holds them rescaled (DICOM, NIfTI scl_slope / scl_inter)."""
    spacing_replaces: bool = False
    """``spacing`` replaces the stored placement (ImageJ TIFF, NanoVDB) instead of being refused."""
    level: int | None = None
    """the OME-Zarr pyramid level read (`volren.data.omezarr`)."""
    channel_colors: tuple[tuple[float, float, float], ...] = ()
    """the file's own colour per channel (OME-Zarr ``omero``), () when it states none."""
    emission: np.ndarray | None = None
    """a second grid of an OpenVDB file (``emission_grid``), raw float32 values, the shape of ``data``."""


def one_line(exc: BaseException) -> str:
    """An exception as one line (its type and text, whitespace folded), for a refusal naming a file."""
    return " ".join(f"{type(exc).__name__}: {exc}".split())
