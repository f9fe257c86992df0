"""Load a density grid from a file: ``.npy``, ``.npz``, raw binary, NRRD, NIfTI, or NanoVDB.

Every loader returns float32 ``[z, y, x]`` (DESIGN.md) validated by ``validate_density``; every failure is a
one-line ``VolrenError`` that names the file. Voxel spacing and orientation stored in a file are not used: the grid is
placed by the caller's ``to_world`` matrix.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np
import warp as wp

from volren.device import init_warp
from volren.errors import VolrenError
from volren.scene import validate_density

RAW_EXTENSIONS = (".raw", ".bin", ".dat")
_MAX_NVDB_VOXELS = 1 << 30
"""A dense copy of a sparse grid larger than this (4 GiB of float32) is refused rather than exhausting memory."""


def _one_line(exc: BaseException) -> str:
    return " ".join(f"{type(exc).__name__}: {exc}".split())


def _normalise_integers(data: np.ndarray) -> np.ndarray:
    """Integers carry no physical density unit: map unsigned by the dtype's max, signed (CT Hounsfield) by min-max."""
    if data.dtype == np.bool_:
        return data.astype(np.float32)
    if not np.issubdtype(data.dtype, np.integer):
        return data
    if np.issubdtype(data.dtype, np.unsignedinteger):
        out = data.astype(np.float32)
        out *= np.float32(1.0 / np.iinfo(data.dtype).max)
        return out
    lo, hi = (int(v) for v in (data.min(), data.max())) if data.size else (0, 0)
    out = data.astype(np.float32)
    out -= np.float32(lo)
    if hi > lo:
        out *= np.float32(1.0 / (hi - lo))
    return out


def _read_npy(path: Path) -> np.ndarray:
    with open(path, "rb") as f:
        if f.read(6) != b"\x93NUMPY":
            raise VolrenError(f"{path}: not a .npy file (no NumPy header)")
    return np.load(path, allow_pickle=False)


def _read_npz(path: Path) -> np.ndarray:
    with np.load(path, allow_pickle=False) as archive:
        keys = list(archive.files)
        if "density" in keys:
            return archive["density"]
        if len(keys) == 1:
            return archive[keys[0]]
    raise VolrenError(f"{path}: holds arrays {', '.join(keys) or '(none)'}; store the grid under the key 'density'")


def _parse_dtype(path: Path, dtype: str | None) -> np.dtype:
    if dtype is None:
        raise VolrenError(f"{path}: a raw file needs dtype (e.g. uint8, uint16, int16, float32; CLI: --dtype)")
    try:
        dt = np.dtype(dtype)
    except TypeError:
        raise VolrenError(f"{path}: unknown dtype {dtype!r}; use uint8, uint16, int16, float32, ...") from None
    if not (np.issubdtype(dt, np.integer) or np.issubdtype(dt, np.floating)):
        raise VolrenError(f"{path}: dtype {dtype!r} is not an integer or floating type")
    return dt


def _read_raw(path: Path, shape: tuple[int, int, int] | None, dtype: str | None) -> np.ndarray:
    if shape is None:
        raise VolrenError(
            f"{path}: raw data needs shape=(X, Y, Z) and dtype (CLI: --shape X,Y,Z --dtype uint8); "
            "or use .npy, .npz, .nrrd, .nii, .nii.gz, .nvdb"
        )
    dims = tuple(int(v) for v in shape)
    if len(dims) != 3 or min(dims) < 1:
        raise VolrenError(f"{path}: shape must be three positive sizes (X, Y, Z), got {shape!r}")
    dt = _parse_dtype(path, dtype)
    nx, ny, nz = dims
    expected = nx * ny * nz * dt.itemsize
    actual = path.stat().st_size
    if actual != expected:
        raise VolrenError(
            f"{path}: file has {actual} bytes but shape {nx}x{ny}x{nz} of {dt.name} needs {expected} bytes"
        )
    return np.fromfile(path, dtype=dt).reshape(nz, ny, nx)  # x varies fastest on disk


def _read_nrrd(path: Path) -> np.ndarray:
    import nrrd  # lazy: only NRRD users pay for the import

    data, _header = nrrd.read(str(path), index_order="C")  # C order: the fastest NRRD axis (x) is last
    return data


def _read_nifti(path: Path) -> np.ndarray:
    """NIfTI stores ``[x, y, z]``. Integer voxels are read unscaled (the linear scl_slope/scl_inter does not change
    the normalised result of signed data); float voxels are read with the scaling applied."""
    import nibabel as nib  # lazy: only NIfTI users pay for the import

    image = nib.load(str(path))
    if np.issubdtype(image.get_data_dtype(), np.integer):
        data = np.asarray(image.dataobj.get_unscaled())
    else:
        data = image.get_fdata(dtype=np.float32)
    if data.ndim == 4 and data.shape[3] == 1:
        data = data[..., 0]
    elif data.ndim == 4:
        raise VolrenError(f"{path}: a 4D NIfTI with {data.shape[3]} volumes; volren needs one 3D volume")
    if data.ndim != 3:
        raise VolrenError(f"{path}: NIfTI data has {data.ndim} dimension(s) {data.shape}; volren needs 3D")
    return np.ascontiguousarray(data.transpose(2, 1, 0))


@wp.kernel
def _nvdb_to_dense(volume: wp.uint64, lo: wp.vec3i, out: wp.array3d(dtype=wp.float32)):
    z, y, x = wp.tid()
    out[z, y, x] = wp.volume_lookup_f(volume, lo[0] + x, lo[1] + y, lo[2] + z)


def _active_index_bbox(volume: wp.Volume) -> tuple[np.ndarray, np.ndarray]:
    """Inclusive index bounds of the active voxels, read from the NanoVDB root node (RootData::mBBox).

    Warp has no accessor for it; the layout is NanoVDB 32.x: GridData (672 bytes), then TreeData whose first field
    mNodeOffset[4] gives the root node's offset from the tree; the root node starts with CoordBBox (6 x int32).
    """
    buf = volume.array().numpy()
    tree = 672
    root = tree + int(np.frombuffer(buf[tree + 24 : tree + 32].tobytes(), dtype="<u8")[0])
    bbox = np.frombuffer(buf[root : root + 24].tobytes(), dtype="<i4")
    return bbox[:3].astype(np.int64), bbox[3:].astype(np.int64)


def _read_nvdb(path: Path) -> np.ndarray:
    """Resample the first grid of a NanoVDB file densely over its active index bounding box (index i, j, k = x,
    y, z), on the CPU. Voxels outside the active set read as the grid's background value."""
    init_warp()
    try:
        volume = wp.Volume.load_from_nvdb(path.read_bytes(), device="cpu")
        grid_type = volume.get_grid_info().type_str
    except (RuntimeError, struct.error, ValueError) as exc:
        raise VolrenError(f"{path}: not a readable NanoVDB file ({_one_line(exc)})") from None
    if grid_type != "float":
        raise VolrenError(f"{path}: NanoVDB grid of type '{grid_type}' is not supported; volren needs a float grid")
    lo, hi = _active_index_bbox(volume)
    size = hi - lo + 1
    if np.any(size < 1):
        raise VolrenError(f"{path}: the NanoVDB grid has no active voxels")
    if int(np.prod(size)) > _MAX_NVDB_VOXELS:
        raise VolrenError(f"{path}: dense copy of {size[0]}x{size[1]}x{size[2]} voxels is too large to load")
    out = wp.empty((int(size[2]), int(size[1]), int(size[0])), dtype=wp.float32, device="cpu")
    wp.launch(_nvdb_to_dense, dim=out.shape, inputs=[volume.id, wp.vec3i(*(int(v) for v in lo)), out], device="cpu")
    return out.numpy()


_READERS: dict[str, Callable[[Path], np.ndarray]] = {
    ".npy": _read_npy,
    ".npz": _read_npz,
    ".nrrd": _read_nrrd,
    ".nhdr": _read_nrrd,
    ".nii": _read_nifti,
    ".nii.gz": _read_nifti,
    ".nvdb": _read_nvdb,
}


def load_volume_file(
    path: str | Path, *, shape: tuple[int, int, int] | None = None, dtype: str | None = None
) -> np.ndarray:
    """Read a density grid as validated float32 ``[z, y, x]``.

    The format follows the extension: ``.npy``; ``.npz`` (its single array, or the key ``density``); ``.nrrd`` /
    ``.nhdr`` (pynrrd); ``.nii`` / ``.nii.gz`` (nibabel; stored ``[x, y, z]``, transposed; a 4D file with one
    volume is accepted); ``.nvdb`` (NanoVDB through Warp: the first grid, which must be float, densely resampled
    over its active index bounding box). Any other extension (``.raw``, ``.bin``, ``.dat``, ...) is raw binary and
    needs ``shape = (X, Y, Z)`` (as the CLI's ``--shape X,Y,Z``: x varies fastest in the file) and ``dtype``
    (a numpy name: ``uint8``, ``uint16``, ``int16``, ``float32``, ``>u2`` for big-endian, ...); ``shape`` and
    ``dtype`` are refused for self-describing formats.

    Floating-point values are returned unchanged. Integer values have no density unit, so they are normalised to
    [0, 1]: unsigned by the dtype's maximum (uint8 / 255, uint16 / 65535), signed (CT Hounsfield units) by
    ``(v - min) / (max - min)`` over the file (all zeros when the file is constant).
    """
    path = Path(path)
    if not path.exists():
        raise VolrenError(f"{path}: file not found")
    if not path.is_file():
        raise VolrenError(f"{path}: not a regular file")
    if path.stat().st_size == 0:  # parsers fail on it with messages such as "StopIteration:"
        raise VolrenError(f"{path}: the file is empty")
    suffix = ".nii.gz" if path.name.lower().endswith(".nii.gz") else path.suffix.lower()
    reader = _READERS.get(suffix)
    if reader is not None and (shape is not None or dtype is not None):
        raise VolrenError(f"{path}: shape/dtype apply to raw binary files only; this format stores its own")
    if reader is None and suffix not in RAW_EXTENSIONS and shape is None:
        raise VolrenError(
            f"{path}: unknown extension '{suffix}'; use {', '.join(_READERS)}, "
            "or give shape=(X, Y, Z) and dtype to read raw binary (CLI: --shape X,Y,Z --dtype uint8)"
        )
    try:
        data = reader(path) if reader is not None else _read_raw(path, shape, dtype)
    except VolrenError:
        raise
    except Exception as exc:  # any parser failure on user data means an unreadable or corrupt file
        raise VolrenError(f"{path}: cannot read the file ({_one_line(exc)})") from None
    return validate_density(_normalise_integers(data), f"volume file {path}")
