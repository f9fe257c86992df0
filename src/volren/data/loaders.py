"""Load a density grid from a file: ``.npy``, ``.npz``, raw binary, NRRD, NIfTI, or NanoVDB.

Every loader returns float32 ``[z, y, x]`` (DESIGN.md) validated by ``validate_density``; every failure is a
one-line ``VolrenError`` that names the file. ``load_volume`` also places the grid in the world (metres) from what the
file stores: NRRD space directions and origin, the NIfTI affine, DICOM patient coordinates; formats that store no
placement (``.npy``, ``.npz``, raw, plain TIFF) take ``spacing`` or get cubic voxels, longest side 2 m, centred; ImageJ
TIFF spacing and the NanoVDB index-to-world map are used unless ``spacing`` replaces them.

Anatomical axes map onto volren's y-up world as a patient standing upright and facing the default camera (which looks
down -z): world +x = patient Left, +y = Superior, +z = Anterior, so LPS (x, y, z) -> (x, z, -y) and RAS (x, y, z) ->
(-x, z, y); both are rotations (det +1), so nothing is mirrored.
"""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from volren.data.dicom import is_dicom_file
from volren.data.grid import Grid, one_line
from volren.device import init_warp
from volren.errors import VolrenError
from volren.scene import validate_density

RAW_EXTENSIONS = (".raw", ".bin", ".dat")
_MAX_NVDB_VOXELS = 1 << 30
"""A dense copy of a sparse grid larger than this (4 GiB of float32) is refused rather than exhausting memory."""
MAX_CHANNELS = 16
"""A 4D array is (C, Z, Y, X) with at most this many channels (more is likely a time series, which is refused)."""


UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6}
"""``--units``: metres per unit of the file's coordinates (or of ``spacing``)."""
_FILE_UNITS = {"m": 1.0, "meter": 1.0, "cm": 1e-2, "mm": 1e-3, "millimeter": 1e-3, "um": 1e-6, "micron": 1e-6,
               "microns": 1e-6, "µm": 1e-6, "\\u00b5m": 1e-6, "nm": 1e-9}
"""units a file may state (NRRD space units, NIfTI xyzt_units, ImageJ ``unit``; ImageJ may write µ as ``\\u00B5``)."""
_LPS_TO_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""Patient Left-Posterior-Superior to the y-up world: Left -> +x, Superior -> +y, Anterior (-P) -> +z."""
_ANATOMICAL_SIGNS = {"L": (0, 1.0), "R": (0, -1.0), "P": (1, 1.0), "A": (1, -1.0), "S": (2, 1.0), "I": (2, -1.0)}
_NRRD_SPACES = {"left-posterior-superior": "LPS", "right-anterior-superior": "RAS", "left-anterior-superior": "LAS"}
_NIFTI_COMPONENTS = {1004: "a matrix", 1005: "a symmetric matrix", 1006: "a displacement vector", 1007: "a vector",
                     1008: "a point set", 1009: "a triangle", 1010: "a quaternion", 2003: "an RGB vector",
                     2004: "an RGBA vector", 2006: "a displacement field"}
"""NIfTI intent codes whose 4th or 5th dimension holds the components of one value per voxel, not time points"""


@dataclass(frozen=True)
class TimePoint:
    """Time point ``index`` (0-based) of a file that holds a time series (a 4-D NIfTI: x, y, z, t): one frame of a
    sequence (`volren.data.sequence`), which ``load_volume`` reads alone."""

    path: Path
    index: int

    @property
    def name(self) -> str:
        return f"{self.path.name} (time point {self.index})"

    def __str__(self) -> str:
        return f"{self.path} (time point {self.index})"


@dataclass(frozen=True)
class ValueMapping:
    """How a file's values became densities: density = (v - lo) / (hi - lo) over ``range`` = (lo, hi), or the values
    themselves when ``range`` is None (floats)."""

    source: str
    """the stored values' type, a numpy name ("uint16", "int16", "float32"), before any rescale the file states"""
    range: tuple[float, float] | None
    """the values (in ``units``, after the file's rescale) that density 0 and 1 stand for"""
    units: str
    """"HU" (Hounsfield units), "Gy" (dose), "relative" (relative dose) or "raw" (the file states none)"""

    def to_dict(self) -> dict:
        """stats.json's ``value_mapping``."""
        return {"source": self.source, "range": None if self.range is None else list(self.range), "units": self.units}


_DOSE_UNITS = ("Gy", "relative")
"""dose counts from zero (no dose) like unsigned integers do, whatever the series' smallest value."""


@dataclass(frozen=True)
class LoadedVolume:
    """A file's density grid and its placement."""

    density: np.ndarray
    """float32 ``[z, y, x]``, validated."""
    to_world: np.ndarray
    """4x4 mapping volren's local cube [-1, 1]^3 onto the world [m]; voxel centres land at their file positions."""
    value_range: tuple[float, float] | None
    """the file values (e.g. Hounsfield units) that density 0 and 1 stand for, when they were normalised."""
    hounsfield: bool = False
    """``value_range`` is in Hounsfield units: signed integers (CT files store HU so), a DICOM CT series, or
    integers a NIfTI rescale takes below zero; unsigned integers as stored are not."""
    channels: tuple[np.ndarray, ...] = ()
    """a multi-channel file's channels (C >= 2; a (C, Z, Y, X) array, a multi-channel TIFF or OME-Zarr), each float32
    ``[z, y, x]`` min-max normalised by its own range (microscopy channels differ in gain); ``density`` is channel 0.
    () for one channel."""
    level: int | None = None
    """the OME-Zarr pyramid level read (0 = finest); None for other formats."""
    emission_source: np.ndarray | None = None
    """``load_volume(emission_grid=...)``: that grid's raw values (e.g. temperature) as float32 ``[z, y, x]``, voxel
    for voxel with ``density``; None otherwise."""
    value_mapping: ValueMapping | None = None
    """how the file's values became ``density`` (stats.json's ``value_mapping``)."""
    channel_colors: tuple[tuple[float, float, float], ...] = ()
    """a multi-channel file's own colour per channel (OME-Zarr ``omero``); () when it states none."""

    @property
    def corners_world(self) -> np.ndarray:
        """The 8 corners of the grid's box in the world [m], ``(8, 3)``."""
        c = np.array([[x, y, z, 1.0] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)])
        return (c @ self.to_world.T)[:, :3]


def _anatomical_to_world(space: str) -> np.ndarray:
    """3x3 from an anatomical frame named by three letters (e.g. "RAS": +x Right, +y Anterior, +z Superior)."""
    to_lps = np.zeros((3, 3))
    for column, letter in enumerate(space):
        row, sign = _ANATOMICAL_SIGNS[letter]
        to_lps[row, column] = sign
    return _LPS_TO_WORLD @ to_lps


def _local_to_index(shape_zyx: tuple[int, ...]) -> np.ndarray:
    """4x4 from local [-1, 1]^3 to voxel index: local -1 + (i + 0.5) * 2 / n is index i (DESIGN.md voxel centres)."""
    n = np.array(shape_zyx[::-1], dtype=np.float64)
    m = np.eye(4)
    m[:3, :3] = np.diag(n / 2)
    m[:3, 3] = n / 2 - 0.5
    return m


def _normalise(grid: Grid) -> tuple[np.ndarray, tuple[float, float] | None]:
    """Map the file's values to densities in [0, 1]. Returns the data and the values that 0 and 1 stand for (None
    when unchanged: floats are densities already).

    Integers carry no density unit. Unsigned ones count from zero (detector counts, attenuation), so 0 stays 0 and
    1 is the top of their bit depth: 2^BitsStored - 1 where the file states it (DICOM), else the smallest depth of at
    least 8 bits that holds the data's maximum (12-bit CT or microscopy in uint16: 4095, where the dtype's 65535
    rendered it nearly black; 8-bit data keeps 255). A depth rather than the maximum keeps files of one detector on
    one scale; percentiles would clip the brightest voxels. Signed integers and rescaled values (Hounsfield units go
    below zero) map min..max; dose maps 0..max."""
    data = grid.data
    if data.dtype == np.bool_:
        return data.astype(np.float32), None
    if not (np.issubdtype(data.dtype, np.integer) or grid.rescale):
        return data, None
    hi = float(data.max()) if data.size else 0.0
    if np.issubdtype(data.dtype, np.unsignedinteger) and not grid.rescale:
        lo, hi = 0.0, float(max(hi, 2 ** (grid.bits_stored or max(8, int(hi).bit_length())) - 1))
    else:
        lo = 0.0 if grid.units in _DOSE_UNITS else float(data.min()) if data.size else 0.0
    out = data.astype(np.float32)
    out -= np.float32(lo)
    if hi > lo:
        out *= np.float32(1.0 / (hi - lo))
    return out, (lo, hi)


def _read_npy(path: Path) -> np.ndarray:
    with open(path, "rb") as f:
        if f.read(6) != b"\x93NUMPY":
            raise VolrenError(f"{path}: not a .npy file (no NumPy header)")
    return np.load(path, allow_pickle=False)


def _read_npz(path: Path) -> np.ndarray:
    with open(path, "rb") as f:  # np.load takes anything else for a pickle and advises allow_pickle
        if f.read(2) != b"PK":
            raise VolrenError(f"{path}: cannot read the file (not a .npz file: no zip header)")
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


def _read_nrrd(path: Path) -> Grid:
    """Placement from ``space directions`` (one row per axis, x first) and ``space origin``, or from ``spacings``."""
    import nrrd  # lazy: only NRRD users pay for the import

    data, header = nrrd.read(str(path), index_order="C")  # C order: the fastest NRRD axis (x) is last
    m = np.eye(4)
    directions = header.get("space directions")
    if directions is not None and np.asarray(directions, dtype=float).shape == (3, 3):
        m[:3, :3] = np.asarray(directions, dtype=float).T
        m[:3, 3] = np.asarray(header.get("space origin", np.zeros(3)), dtype=float)
    elif header.get("spacings") is not None and len(header["spacings"]) == 3:
        m[:3, :3] = np.diag(np.asarray(header["spacings"], dtype=float))
    else:
        return Grid(data)
    if not np.all(np.isfinite(m)):
        raise VolrenError(f"{path}: the NRRD space directions / origin / spacings are not finite numbers")
    space = str(header.get("space", ""))
    space = _NRRD_SPACES.get(space.lower(), space.upper())
    units = {str(u).lower() for u in header.get("space units", [])}
    scale = _FILE_UNITS.get(units.pop()) if len(units) == 1 else None
    return Grid(data, m, space if len(space) == 3 and set(space) <= set(_ANATOMICAL_SIGNS) else "", scale)


def _nifti_shape(path: Path, image) -> tuple[int, ...]:
    """A NIfTI's shape without the trailing dimensions of size 1 after z; refused, naming the file and its shape,
    unless it is a 3-D volume (x, y, z) or a 4-D time series (x, y, z, t): 5 or more dimensions (NIfTI keeps the 5th
    for the components of a vector or matrix per voxel), or a 4th whose intent code says it holds such components."""
    full = tuple(int(n) for n in image.shape)
    shape = full
    while len(shape) > 3 and shape[-1] == 1:
        shape = shape[:-1]
    what = _NIFTI_COMPONENTS.get(int(image.header["intent_code"]))
    if len(shape) > 4 or (len(shape) == 4 and what is not None):
        per_voxel = f", {shape[-1]} values per voxel ({what or 'components along its 5th dimension'})"
        raise VolrenError(f"{path}: a NIfTI of shape {full}{per_voxel}: volren reads a 3-D volume (x, y, z) or a "
                          "4-D time series (x, y, z, t)")
    return shape


def nifti_time_points(path: Path) -> int:
    """The time points of a 4-D NIfTI time series (x, y, z, t), 0 for a 3-D one (read from the header only);
    refused as ``_nifti_shape`` says for other shapes."""
    import nibabel as nib  # lazy: only NIfTI users pay for the import

    try:
        image = nib.load(str(path))
    except Exception as exc:  # nibabel's many kinds on a bad header
        raise VolrenError(f"{path}: cannot read the file ({one_line(exc)})") from None
    shape = _nifti_shape(path, image)
    return shape[3] if len(shape) == 4 else 0


def _read_nifti(path: Path, time_point: int | None = None) -> Grid:
    """NIfTI stores ``[x, y, z]``; its affine (sform, else qform, as nibabel chooses) maps voxel (i, j, k) to RAS+.
    Voxels are read with scl_slope / scl_inter applied (integers without them unscaled, to keep their bit depth):
    stored unsigned CT values with scl_inter -1024 become Hounsfield units, which go below zero.

    A 4-D time series (x, y, z, t) is read one time point at a time (``time_point``, 0-based: nibabel reads that
    volume alone), each placed by the one affine; without ``time_point`` it is refused, pointing to the CLI's
    sequences (`volren.data.sequence` plays every time point)."""
    import nibabel as nib  # lazy: only NIfTI users pay for the import

    image = nib.load(str(path))
    shape = _nifti_shape(path, image)
    if len(shape) == 4:
        count = shape[3]
        if time_point is None:
            raise VolrenError(f"{path}: a 4-D NIfTI of {count} time points (shape {shape}): the CLI plays them as a "
                              f"sequence (volren render --volume {path.name} --frames {count}, animate, serve); "
                              f"load one with time_point=N (0 to {count - 1})")
        if not 0 <= time_point < count:
            raise VolrenError(f"{path}: time_point {time_point} is outside the NIfTI's {count} time points (0 to "
                              f"{count - 1})")
    elif time_point is not None:
        raise VolrenError(f"{path}: time_point picks a time point of a 4-D NIfTI; this one holds one 3-D volume "
                          f"(shape {shape})")
    stored = image.get_data_dtype()
    rescaled = np.issubdtype(stored, np.integer) and (image.dataobj.slope, image.dataobj.inter) != (1.0, 0.0)
    if time_point is not None:
        # that volume only; integers without a rescale stay the stored ones, as in a 3-D file
        data = np.asarray(image.dataobj[(slice(None),) * 3 + (time_point,) + (0,) * (len(image.shape) - 4)])
        if not np.issubdtype(stored, np.integer) or rescaled:
            data = data.astype(np.float32)
    elif np.issubdtype(stored, np.integer) and not rescaled:
        data = np.asarray(image.dataobj.get_unscaled())
    else:
        data = image.get_fdata(dtype=np.float32)  # scl_slope * v + scl_inter
    if len(shape) == 3:
        data = data.reshape(shape)  # without the trailing dimensions of size 1
    if data.ndim != 3:
        raise VolrenError(f"{path}: NIfTI data has {data.ndim} dimension(s) {data.shape}; volren needs 3D")
    unit = image.header.get_xyzt_units()[0]
    hu = "HU" if rescaled and data.size and float(data.min()) < 0 else ""  # like signed integers: CT
    return Grid(np.ascontiguousarray(data.transpose(2, 1, 0)), np.asarray(image.affine, dtype=float), "RAS",
                 _FILE_UNITS.get(unit), rescale=rescaled, units=hu, source=stored.name if rescaled else "")


def _read_tiff(path: Path) -> Grid:
    """A multi-page TIFF stack (microscopy): pages are z, each page [y, x], turned upright (``_pages_to_grid``: row
    0 at the top, page 0 in front). Colour or multi-channel stacks are refused:
    volren renders one scalar channel. ImageJ stacks place the voxels: x/y size = 1 / XResolution, YResolution (pixels
    per unit), z size = the ImageJ ``spacing``, in the ImageJ ``unit``; the default ImageJ writes when nothing was set
    (1 x 1 x 1, no unit) counts as no placement."""
    import tifffile  # lazy: only TIFF users pay for the import

    with tifffile.TiffFile(str(path)) as tif:
        data = _tiff_channels_first(tif.asarray(), tif.series[0].axes)
        imagej = tif.imagej_metadata
        tags = tif.pages[0].tags
        resolution = [tags[name].value if name in tags else (1, 1) for name in ("XResolution", "YResolution")]
    if data.ndim not in (3, 4):
        raise VolrenError(f"{path}: TIFF holds an array of shape {data.shape}; volren needs a stack of 2D grey pages "
                          "[z, y, x] (or [c, z, y, x] with a C axis, e.g. an ImageJ hyperstack ZCYX)")
    data = _pages_to_grid(data)
    if not imagej:
        return Grid(data)
    unit = str(imagej.get("unit", "")).strip().lower()
    step = [den / num if num else float("inf") for num, den in resolution] + [float(imagej.get("spacing", 1.0))]
    if step == [1.0, 1.0, 1.0] and unit in ("", "pixel"):
        return Grid(data)
    if not all(np.isfinite(v) and v > 0 for v in step):
        raise VolrenError(f"{path}: the ImageJ voxel size {step} (1 / XResolution, 1 / YResolution, spacing) is not "
                          "three positive numbers; give --spacing x,y,z to replace it")
    m = _spacing_placement(data.shape[-3:], step, 1.0)  # ImageJ stores no origin: centred, in the file's unit
    return Grid(data, m, metres_per_unit=_FILE_UNITS.get(unit), spacing_replaces=True)


def _pages_to_grid(pages: np.ndarray) -> np.ndarray:
    """A stack of pages [..., page, row, column] as volren's [..., z, y, x] (y up). A page's row 0 is its top and
    the stack is right-handed (column right, row down, page away from the viewer, as napari and Fiji show it), so a
    half turn about x (not a mirror) puts it in the world: rows run down y, pages towards -z (page 0 nearest the
    default camera)."""
    return pages[..., ::-1, ::-1, :]


def _tiff_channels_first(data: np.ndarray, axes: str) -> np.ndarray:
    """A multi-channel stack (tifffile's series axes with a C: ImageJ hyperstacks 'ZCYX', OME-TIFF 'CZYX') as
    ``[c, z, y, x]``; anything else unchanged (and refused by the caller unless 3D)."""
    if data.ndim == 4 and len(axes) == 4 and "C" in axes and axes.endswith("YX"):
        return np.moveaxis(data, axes.index("C"), 0)
    return data


def _split_channels(path: Path, grid: Grid) -> tuple[Grid, tuple[Grid, ...]]:
    """A (C, Z, Y, X) grid's channels, each min-max normalised by its own range (``rescale``), and channel 0 as the
    grid; a 3D grid (or one channel) unchanged with no channels. A tuple of streamed channels
    (`volren.data.omezarr._streamed_channels`) is mapped already, as it is read."""
    if isinstance(grid.data, tuple):
        channels = tuple(dataclasses.replace(grid, data=d) for d in grid.data)
        return channels[0], channels
    if grid.data.ndim != 4:
        return grid, ()
    count = grid.data.shape[0]
    if not 1 <= count <= MAX_CHANNELS:
        raise VolrenError(f"{path}: a 4D array of shape {grid.data.shape}; volren reads (C, Z, Y, X) with 1 to "
                          f"{MAX_CHANNELS} channels")
    if count == 1:
        return dataclasses.replace(grid, data=grid.data[0]), ()
    channels = tuple(dataclasses.replace(grid, data=grid.data[c], rescale=True) for c in range(count))
    return channels[0], channels


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


def _read_nvdb(path: Path) -> Grid:
    """Resample the first grid of a NanoVDB file densely over its active index bounding box (index i, j, k = x,
    y, z), on the CPU. Voxels outside the active set read as the grid's background value.

    Placement: the grid's linear map, world = M (i, j, k) + t (NanoVDB's row-major 3x3 and translation; the voxel
    size is M's column lengths). NanoVDB states no length unit, so the world is millimetres unless ``units`` says
    otherwise. The identity map (voxel size 1, no translation: what Warp and OpenVDB write when nothing was set)
    counts as no placement."""
    init_warp()
    try:
        volume = wp.Volume.load_from_nvdb(path.read_bytes(), device="cpu")
        grid_type = volume.get_grid_info().type_str
    except (RuntimeError, struct.error, ValueError) as exc:
        raise VolrenError(f"{path}: not a readable NanoVDB file ({one_line(exc)})") from None
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
    info = volume.get_grid_info()
    matrix = np.array(info.transform_matrix, dtype=np.float64).reshape(3, 3)
    translation = np.array(info.translation, dtype=np.float64)
    if np.array_equal(matrix, np.eye(3)) and not translation.any():
        return Grid(out.numpy())
    if not (np.all(np.isfinite(matrix)) and np.all(np.isfinite(translation))):
        raise VolrenError(f"{path}: the NanoVDB index-to-world transform is not finite numbers")
    m = np.eye(4)
    m[:3, :3] = matrix
    m[:3, 3] = matrix @ lo + translation  # dense index 0 is NanoVDB index lo
    return Grid(out.numpy(), m, spacing_replaces=True)


def _read_vdb(path: Path, grid: str | None = None, emission_grid: str | None = None,
              index_box: tuple[np.ndarray, np.ndarray] | None = None, memory_budget: float | None = None) -> Grid:
    """An OpenVDB file through tinyvdb (``volren.data.vdb``): the density grid over its active box, placed by its
    index-to-world map in metres (OpenVDB states no unit; ``units`` overrides), which ``spacing`` replaces as for
    NanoVDB; ``emission_grid`` densified over the same box; their bricks within ``memory_budget`` [bytes]."""
    from volren.data.vdb import read_vdb  # lazy: tinyvdb only for .vdb users

    vdb, emission = read_vdb(path, grid, emission_grid, index_box, memory_budget)
    return Grid(vdb.data, vdb.index_to_world, metres_per_unit=1.0, spacing_replaces=True, emission=emission)


_READERS: dict[str, Callable[..., np.ndarray | Grid]] = {
    ".npy": _read_npy,
    ".npz": _read_npz,
    ".nrrd": _read_nrrd,
    ".nhdr": _read_nrrd,
    ".nii": _read_nifti,
    ".nii.gz": _read_nifti,
    ".nvdb": _read_nvdb,
    ".vdb": _read_vdb,
    ".tif": _read_tiff,
    ".tiff": _read_tiff,
}


def _spacing_placement(shape_zyx: tuple[int, ...], spacing: Sequence[float] | None, metres: float) -> np.ndarray:
    """index -> world for a format with no stored placement: ``spacing`` (x, y, z) in units of ``metres``, or cubic
    voxels with the longest side 2 m; centred on the origin either way."""
    n = np.array(shape_zyx[::-1], dtype=np.float64)
    step = np.asarray(spacing, dtype=np.float64) * metres if spacing is not None else np.full(3, 2.0 / n.max())
    m = np.eye(4)
    m[:3, :3] = np.diag(step)
    m[:3, 3] = -step * (n - 1) / 2
    return m


def dicom_member(path: Path, shape: tuple[int, int, int] | None = None) -> bool:
    """Whether ``path`` is one DICOM file that ``load_volume`` reads as its series: a ``.dcm``, or DICOM Part 10
    content in a file whose extension no other reader takes (unless ``shape`` says it is raw data)."""
    return is_dicom_file(path, (*_READERS, *RAW_EXTENSIONS), sniff=shape is None)


def load_volume(
    path: str | Path | TimePoint,
    *,
    shape: tuple[int, int, int] | None = None,
    dtype: str | None = None,
    spacing: Sequence[float] | None = None,
    units: str | None = None,
    level: int | None = None,
    memory_budget: float | None = None,
    stream: bool | None = None,
    grid: str | None = None,
    emission_grid: str | None = None,
    time_point: int | None = None,
    index_box: tuple[np.ndarray, np.ndarray] | None = None,
) -> LoadedVolume:
    """Read a density grid (see ``load_volume_file`` for the formats and value mapping) or a folder holding a DICOM
    series, and place it in the world.

    Placement: NRRD ``space directions`` / ``space origin`` (or ``spacings``), the NIfTI affine (RAS+), DICOM
    ImagePositionPatient / ImageOrientationPatient / PixelSpacing and the slice positions (LPS); anatomical frames
    map to the world as the module docstring says; ImageJ TIFF voxel sizes (centred) and the NanoVDB index-to-world
    map. Units: what the file states (NRRD ``space units``, NIfTI ``xyzt_units``, ImageJ ``unit``), else millimetres
    (DICOM is always mm; NanoVDB states none); ``units`` (a key of ``UNITS``) overrides both. A DICOM file (``.dcm``,
    or a DICOM Part 10 file with no other reader's extension) is read as its series: the files of its folder with its
    SeriesInstanceUID, whatever else the folder holds (`volren.data.dicom`). ``spacing`` = voxel size
    (x, y, z) in ``units`` (default mm) places ``.npy``, ``.npz``, raw, ``.tif``/``.tiff`` and ``.nvdb`` (replacing
    what a TIFF or NanoVDB stores), centred on the origin; without it and without a stored placement they get cubic
    voxels with the longest side 2 m, centred. ``spacing`` is refused for NRRD, NIfTI and DICOM.

    A ``.zarr`` is an OME-Zarr pyramid or a plain Zarr array (`volren.data.omezarr`): ``level`` (0 = finest) or the
    finest level within ``memory_budget`` [bytes of float32] is read; a pyramid whose finest level does not fit (or
    any, with ``stream`` True) streams its bricks as the views need them (`volren.stream`; a multi-channel one each
    channel alone). A ``.vdb`` whose bricks would exceed a given ``memory_budget`` is refused before its leaves are
    read (`volren.data.vdb`). A 4D array,
    a TIFF with a C axis or a Zarr with a ``c`` axis holds channels (``LoadedVolume.channels``).

    ``path`` may be an fsspec URL of an OME-Zarr store (a ``str``: ``https://host/image.zarr``, ``s3://bucket/a.zarr``
    with the ``s3`` extra, ``zip::file:///data/a.zarr.zip``): read or streamed as a folder is.

    A 4-D NIfTI (x, y, z, t) is a time series: ``time_point`` (0-based), or ``path`` a `TimePoint`, reads one of its
    volumes; the CLI plays them all as a sequence (`volren.data.sequence`).

    ``index_box``: an OpenVDB file read over these inclusive index bounds (x, y, z), not its active box: a sequence's
    frames placed in the union of their boxes (`volren.data.vdb.index_box`).
    """
    if isinstance(path, TimePoint):
        if time_point is not None:
            raise VolrenError(f"{path}: give the time point once (a TimePoint, or time_point=)")
        path, time_point = path.path, path.index
    url = isinstance(path, str) and "://" in path  # an fsspec URL: an OME-Zarr store (http://, s3://, zip://...)
    path = path if url else Path(path)
    name = path.rstrip("/").rsplit("/", 1)[-1] if url else path.name
    suffix = ".zarr" if url else path.suffix.lower()
    options: dict[str, str | int] = {k: v for k, v in (("grid", grid), ("emission_grid", emission_grid),
                                                       ("index_box", index_box)) if v is not None}  # OpenVDB's
    if options and suffix != ".vdb":  # Warp reads a .nvdb's first grid only
        raise VolrenError(f"{path}: grid and emission_grid name grids of an OpenVDB file: they apply to .vdb only "
                          "(CLI: --grid, --emission-grid)")
    if time_point is not None:
        if isinstance(time_point, bool) or not isinstance(time_point, int | np.integer):
            raise VolrenError(f"{path}: time_point must be a whole number (0-based), got {time_point!r}")
        time_point = int(time_point)
        if not name.lower().endswith((".nii", ".nii.gz")):
            raise VolrenError(f"{path}: time_point picks a time point of a 4-D NIfTI (.nii, .nii.gz) only")
        options["time_point"] = time_point  # or a 4-D NIfTI's time point
    if units is not None and units not in UNITS:
        raise VolrenError(f"units must be one of {', '.join(UNITS)}, got {units!r} (CLI: --units)")
    if spacing is not None:
        step = tuple(float(v) for v in spacing)
        if len(step) != 3 or not all(np.isfinite(v) and v > 0 for v in step):
            raise VolrenError(f"spacing must be three positive voxel sizes x,y,z, got {spacing!r} (CLI: --spacing)")
    zarr = suffix == ".zarr"
    if not zarr and stream is not None:
        raise VolrenError(f"{path}: stream= reads an OME-Zarr pyramid brick by brick: it applies to .zarr only")
    if not zarr and (level is not None or (memory_budget is not None and suffix != ".vdb")):
        raise VolrenError(f"{path}: level and memory_budget choose an OME-Zarr pyramid level: they apply to .zarr "
                          "only (CLI: --level, --memory-budget; the budget also holds a .vdb's bricks)")
    if suffix == ".vdb" and memory_budget is not None:
        options["memory_budget"] = memory_budget
    if zarr:
        from volren.data.omezarr import read_zarr  # lazy: zarr only for Zarr users

        if shape is not None or dtype is not None:
            raise VolrenError(f"{path}: shape/dtype apply to raw binary files only; a Zarr array stores its own")
        grid = read_zarr(path, level=level, memory_budget=memory_budget, stream=stream)
    elif path.is_dir() and path.suffix.lower() not in (*_READERS, *RAW_EXTENSIONS):  # "a.npy/" is a mistake, not DICOM
        from volren.data.dicom import read_dicom_series  # lazy: pydicom only for DICOM users

        if shape is not None or dtype is not None:
            raise VolrenError(f"{path}: shape/dtype apply to raw binary files only; a DICOM series stores its own")
        grid = read_dicom_series(path)
    elif dicom_member(path, shape):  # one slice stands for its series, in its folder
        from volren.data.dicom import read_dicom_series

        if shape is not None or dtype is not None:
            raise VolrenError(f"{path}: shape/dtype apply to raw binary files only; a DICOM series stores its own")
        grid = read_dicom_series(path.parent, member=path)
    else:
        grid = _read_file(path, shape, dtype, **options)
    if grid.index_to_file is not None and spacing is not None and not grid.spacing_replaces:
        raise VolrenError(f"{path}: this volume stores its own voxel spacing; spacing (CLI: --spacing) applies to "
                          ".npy, .npz, raw, .tif and .nvdb")
    grid, parts = _split_channels(path, grid)
    channels = tuple(validate_density(_normalise(g)[0], f"volume file {path} channel {c}") for c, g in enumerate(parts))
    data, value_range = (channels[0], None) if channels else _normalise(grid)
    density = validate_density(data, f"volume file {path}")
    if grid.index_to_file is None or spacing is not None:
        index_to_world = _spacing_placement(density.shape, spacing, UNITS[units or "mm"])
    else:
        metres = UNITS[units] if units is not None else grid.metres_per_unit or UNITS["mm"]
        to_world3 = _anatomical_to_world(grid.space) if grid.space else np.eye(3)
        file_to_world = np.eye(4)
        file_to_world[:3, :3] = metres * to_world3
        index_to_world = file_to_world @ grid.index_to_file
    # scale-free (as `Volume`'s check): an absolute 1e-30 m^3 refused angstrom voxels (cryo-EM OME-Zarr) as degenerate
    axes_volume = float(np.prod(np.linalg.norm(index_to_world[:3, :3], axis=0)))
    if not abs(np.linalg.det(index_to_world[:3, :3])) > 1e-9 * axes_volume:
        raise VolrenError(f"{path}: the stored voxel axes are degenerate (zero spacing or parallel directions)")
    units = grid.units or ("HU" if np.issubdtype(grid.data.dtype, np.signedinteger) else "raw")
    hounsfield = value_range is not None and units == "HU"
    mapping = None if channels else ValueMapping(grid.source or grid.data.dtype.name, value_range, units)
    return LoadedVolume(density, index_to_world @ _local_to_index(density.shape), value_range, hounsfield, channels,
                        grid.level, grid.emission, mapping, grid.channel_colors if channels else ())


def _read_file(path: Path, shape: tuple[int, int, int] | None, dtype: str | None, **options: str | int) -> Grid:
    """``options``: the OpenVDB grid names (``grid``, ``emission_grid``), passed to the .vdb reader, or a 4-D
    NIfTI's ``time_point``, passed to the NIfTI reader."""
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
            f"{path}: unknown extension '{suffix}'; use {', '.join(_READERS)}, a folder of DICOM files, "
            "or give shape=(X, Y, Z) and dtype to read raw binary (CLI: --shape X,Y,Z --dtype uint8)"
        )
    try:
        grid = reader(path, **options) if reader is not None else _read_raw(path, shape, dtype)
    except VolrenError:
        raise
    except Exception as exc:  # any parser failure on user data means an unreadable or corrupt file
        raise VolrenError(f"{path}: cannot read the file ({one_line(exc)})") from None
    return grid if isinstance(grid, Grid) else Grid(grid)


def load_volume_file(
    path: str | Path, *, shape: tuple[int, int, int] | None = None, dtype: str | None = None
) -> np.ndarray:
    """Read a density grid as validated float32 ``[z, y, x]`` (``load_volume`` also places it).

    The format follows the extension: ``.npy``; ``.npz`` (its single array, or the key ``density``); ``.nrrd`` /
    ``.nhdr`` (pynrrd); ``.nii`` / ``.nii.gz`` (nibabel; stored ``[x, y, z]``, transposed; a 4D file with one
    volume is accepted); ``.tif`` / ``.tiff`` (tifffile: a stack of grey pages, page = z); ``.nvdb`` (NanoVDB through
    Warp: the first grid, which must be float, densely resampled over its active index bounding box); a folder is a
    DICOM series (``volren.data.dicom``). Any other extension (``.raw``, ``.bin``, ``.dat``, ...) is raw binary and
    needs ``shape = (X, Y, Z)`` (as the CLI's ``--shape X,Y,Z``: x varies fastest in the file) and ``dtype``
    (a numpy name: ``uint8``, ``uint16``, ``int16``, ``float32``, ``>u2`` for big-endian, ...); ``shape`` and
    ``dtype`` are refused for self-describing formats.

    Floating-point values are returned unchanged. Integer values have no density unit, so they are normalised to
    [0, 1] (``_normalise``; ``load_volume`` says how in ``LoadedVolume.value_mapping``): unsigned by the top of their
    bit depth (DICOM BitsStored, else the smallest of at least 8 bits holding the maximum: uint8 / 255, 12-bit data
    in uint16 / 4095), signed (CT Hounsfield units) by ``(v - min) / (max - min)`` over the file (all zeros when the
    file is constant); so are the values after a DICOM RescaleSlope / RescaleIntercept or a NIfTI scl_slope /
    scl_inter; RT dose (Gy) by its maximum.
    """
    return load_volume(path, shape=shape, dtype=dtype).density
