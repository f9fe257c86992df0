"""A DICOM series as one grid placed in patient coordinates (LPS, mm), via pydicom.

A series is a folder of single-frame slices, a multi-frame (enhanced) image whose frames are placed by the functional
groups (PlanePositionSequence per frame; PlaneOrientationSequence, PixelMeasuresSequence and
PixelValueTransformationSequence per frame or shared), or an RT dose grid (frames at ImagePositionPatient + offset *
normal for each GridFrameOffsetVector offset, values * DoseGridScaling). Files of the folder that are no image of a
series (not DICOM, a DICOMDIR index, no pixel data, unreadable pixel data) are skipped with one warning naming them;
a folder with no image left is refused. Frames are sorted by their position along the slice normal
(ImageOrientationPatient row x column direction); the series is refused, with one line naming the folder, when
frames differ in size, orientation or pixel spacing, when two share a position, or when the steps between positions
are uneven (a missing slice). Stored values become RescaleSlope * v + RescaleIntercept per frame: Hounsfield units
for CT; other modalities without a rescale keep their stored integers (normalised by BitsStored).

One file given alone (``read_dicom_series(folder, member=file)``) stands for its series: the files of its folder with
its SeriesInstanceUID, whatever else the folder holds. Other files are sorted out by two tags read from each
(``specific_tags``: no pixel data, no other element parsed), silently: other series, notes and non-DICOM files are
no concern of this series. Copies of one image (the same SOPInstanceUID, e.g. in another transfer syntax) count once.
A series of one slice is refused naming the file.
"""

from __future__ import annotations

import logging
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from volren.errors import VolrenError

_STEP_TOLERANCE = 0.01
"""Relative spread allowed between slice steps (and between the steps' directions) before a series is refused."""
_DICOMDIR = "1.2.840.10008.1.3.10"
"""Media Storage Directory Storage: the SOP class of a DICOMDIR (an index of a file set, no image)."""
_LISTED = 6
"""skipped files named in the warning; more are counted."""
_PREAMBLE = 128
"""a DICOM Part 10 file holds b"DICM" after its 128-byte preamble"""
log = logging.getLogger("volren.data")


def is_dicom_file(path: Path, readers: tuple[str, ...] = (), sniff: bool = True) -> bool:
    """Whether ``path``, a file given alone, is a DICOM image standing for its series: a ``.dcm``, or (with
    ``sniff``: not for raw data given its shape) a file whose extension no other reader (``readers``) takes that holds
    b"DICM" after the preamble (scanners write IM0001 or 1.2.840.113619.2.55.3.1 without an extension)."""
    if not path.is_file():
        return False
    if path.suffix.lower() == ".dcm":
        return True
    if not sniff or any(path.name.lower().endswith(r) for r in readers):
        return False
    try:
        with open(path, "rb") as f:
            f.seek(_PREAMBLE)
            return f.read(4) == b"DICM"
    except OSError:
        return False


@dataclass(frozen=True)
class _Frame:
    """One plane of the series: a single-frame file, or frame k of a multi-frame file (``name`` "file[k]")."""

    name: str
    pixels: np.ndarray
    """stored values [row, column]"""
    orientation: np.ndarray
    position: np.ndarray
    spacing: np.ndarray
    slope: float
    intercept: float


def _series_files(folder: Path, member: Path | None = None) -> list[Path]:
    """The ``.dcm`` files of the folder; when there are none, or ``member`` has another extension, every visible
    regular file (series without extensions)."""
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    dcm = [p for p in files if p.suffix.lower() == ".dcm"]
    return files if member is not None and member.suffix.lower() != ".dcm" else dcm or files


def _uids(pydicom, file: Path) -> tuple[str, str] | None:
    """(SeriesInstanceUID, SOPInstanceUID) of a file, reading those two tags only; None when it is not DICOM or its
    header does not parse."""
    pydicom_log, thread = logging.getLogger("pydicom"), threading.get_ident()

    def this_thread(record: logging.LogRecord) -> bool:
        return record.thread != thread

    pydicom_log.addFilter(this_thread)  # pydicom warns and logs about another series' files: no concern here
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = pydicom.dcmread(file, stop_before_pixels=True, specific_tags=["SeriesInstanceUID", "SOPInstanceUID"])
    except Exception:  # not DICOM, truncated, ...: not of the series either way
        return None
    finally:
        pydicom_log.removeFilter(this_thread)
    return str(ds.get("SeriesInstanceUID", "")), str(ds.get("SOPInstanceUID", ""))


def _member_series(pydicom, folder: Path, member: Path, skipped: list[str]) -> tuple[list[Path], list[str]]:
    """The image files of ``member``'s series in its folder, ``member`` first, each SOP instance once (a copy is the
    same image: no warning); and the names of the files that hold copies. Files of the series that are no image are
    added to ``skipped``."""
    header, reason = _read_header(pydicom, member)
    if header is None:
        raise VolrenError(f"{member}: {'not a DICOM file' if reason == 'not DICOM' else reason}; name an image "
                          "of the series, or its folder")
    wanted = str(header.get("SeriesInstanceUID", ""))
    files, copies = [member], []
    seen = {str(header.get("SOPInstanceUID", "")): member.name}
    for file in _series_files(folder, member):
        uids = None if file.samefile(member) else _uids(pydicom, file)
        if uids is None or uids[0] != wanted:
            continue  # the member itself, or no file of its series
        if uids[1] and uids[1] in seen:
            copies.append(file.name)
            continue
        header, reason = _read_header(pydicom, file)
        if header is None:
            skipped.append(f"{file.name}: {reason}")
            continue
        seen[uids[1]] = file.name
        files.append(file)
    return files, copies


def _vector(item, keyword: str, count: int, folder: Path, name: str) -> np.ndarray:
    value = None if item is None else item.get(keyword)
    if value is None or len(value) != count:
        raise VolrenError(f"{folder}: DICOM image {name} has no {keyword}; volren cannot place the series")
    return np.asarray([float(v) for v in value], dtype=np.float64)


def _not_an_image(ds) -> str:
    """Why a header (read without pixels) is no image of a series, or "" when it is one."""
    if str(ds.file_meta.get("MediaStorageSOPClassUID", "")) == _DICOMDIR or "DirectoryRecordSequence" in ds:
        return "a DICOMDIR index"
    if "Rows" not in ds or "Columns" not in ds:
        return f"no image: {ds.get('Modality', 'no modality')}"
    if int(ds.get("SamplesPerPixel", 1) or 1) != 1:
        return "a colour image"
    return ""


def _read_header(pydicom, file: Path):
    """(header without pixels, "") or (None, why it is skipped)."""
    from pydicom.errors import InvalidDicomError

    try:
        ds = pydicom.dcmread(file, stop_before_pixels=True)
    except InvalidDicomError:
        return None, "not DICOM"
    except Exception as exc:  # pydicom raises many kinds on a truncated or corrupt header
        return None, f"unreadable: {type(exc).__name__}"
    reason = _not_an_image(ds)
    return (None, reason) if reason else (ds, "")


def _number(item, keyword: str, default: float) -> float:
    value = None if item is None else item.get(keyword)
    return default if value is None or value == "" else float(value)


def _group(ds, frame: int, sequence: str):
    """Frame ``frame``'s item of the functional group ``sequence`` (per-frame, else shared), or None."""
    for groups, index in (("PerFrameFunctionalGroupsSequence", frame), ("SharedFunctionalGroupsSequence", 0)):
        items = ds.get(groups)
        if items is not None and len(items) > index and items[index].get(sequence):
            return items[index].get(sequence)[0]
    return None


def _frames(ds, pixels: np.ndarray, file: Path, folder: Path) -> list[_Frame]:
    """The planes of one file. Enhanced images (any number of frames) are placed by their functional groups (PS3.3
    C.7.6.16); an RT dose's frames by GridFrameOffsetVector (PS3.3 C.8.8.3.2: offsets along the normal, frame 0 at
    ImagePositionPatient); a single frame by its top-level attributes."""
    count = int(ds.get("NumberOfFrames", 1) or 1)
    if pixels.ndim != (3 if count > 1 else 2) or (count > 1 and len(pixels) != count):
        raise VolrenError(f"{folder}: {file.name} holds pixel data of shape {pixels.shape} for {count} frame(s); "
                          "volren reads grey images")
    planes = pixels if count > 1 else pixels[None]
    names = [f"{file.name}[{k}]" for k in range(count)] if count > 1 else [file.name]
    if "GridFrameOffsetVector" not in ds and _group(ds, 0, "PlanePositionSequence") is not None:
        frames = []
        for k, name in enumerate(names):
            transform = _group(ds, k, "PixelValueTransformationSequence") or ds
            frames.append(_Frame(
                name, planes[k],
                _vector(_group(ds, k, "PlaneOrientationSequence"), "ImageOrientationPatient", 6, folder, name),
                _vector(_group(ds, k, "PlanePositionSequence"), "ImagePositionPatient", 3, folder, name),
                _vector(_group(ds, k, "PixelMeasuresSequence"), "PixelSpacing", 2, folder, name),
                _number(transform, "RescaleSlope", 1.0), _number(transform, "RescaleIntercept", 0.0)))
        return frames
    orientation = _vector(ds, "ImageOrientationPatient", 6, folder, file.name)
    origin = _vector(ds, "ImagePositionPatient", 3, folder, file.name)
    spacing = _vector(ds, "PixelSpacing", 2, folder, file.name)
    if ds.get("Modality") == "RTDOSE":
        slope, intercept = _number(ds, "DoseGridScaling", 1.0), 0.0  # Gy = DoseGridScaling * v
    else:
        slope, intercept = _number(ds, "RescaleSlope", 1.0), _number(ds, "RescaleIntercept", 0.0)
    if count == 1:
        return [_Frame(file.name, planes[0], orientation, origin, spacing, slope, intercept)]
    offsets = _vector(ds, "GridFrameOffsetVector", count, folder, file.name)  # else the frames have no positions
    normal = np.cross(orientation[:3], orientation[3:])
    # a first offset of 0 means offsets relative to frame 0; one equal to frame 0's z means absolute z (axial)
    return [_Frame(name, planes[k], orientation, origin + (offsets[k] - offsets[0]) * normal, spacing, slope,
                   intercept) for k, name in enumerate(names)]


def _units(ds) -> str:
    """What the series' rescaled values are: "HU" (CT), "Gy" or "relative" (RT dose), "" (unknown)."""
    if ds.get("Modality") == "RTDOSE":
        return "Gy" if str(ds.get("DoseUnits", "GY")).upper() == "GY" else "relative"
    return "HU" if ds.get("Modality") == "CT" or str(ds.get("RescaleType", "")).upper() == "HU" else ""


def read_dicom_series(folder: Path, member: Path | None = None):
    """Read the series in ``folder`` as a ``volren.data.grid.Grid`` (index -> LPS mm; values rescaled to
    float32, or the stored integers with their BitsStored where no rescale applies). With ``member`` (one of its
    files), read that file's series (its SeriesInstanceUID) and skip the folder's other series; without it, a folder
    of several series is refused."""
    import pydicom  # lazy: only DICOM users pay for the import

    from volren.data.grid import Grid, one_line

    skipped: list[str] = []  # "name: why"
    series: dict[str, list[Path]] = {}  # SeriesInstanceUID -> its image files
    copies: list[str] = []
    if member is not None:
        series[""], copies = _member_series(pydicom, folder, member, skipped)
    else:
        files = _series_files(folder)
        if not files:
            raise VolrenError(f"{folder}: empty folder; a DICOM series needs its slice files (.dcm)")
        for file in files:
            header, reason = _read_header(pydicom, file)
            if header is None:
                skipped.append(f"{file.name}: {reason}")
                continue
            series.setdefault(str(header.get("SeriesInstanceUID", "")), []).append(file)
    if len(series) > 1:
        names = ", ".join(f[0].name for f in series.values())
        raise VolrenError(f"{folder}: holds {len(series)} DICOM series (first files {names}); put each series in its "
                          "own folder")
    frames: list[_Frame] = []
    first = None
    for file in next(iter(series.values()), []):
        try:
            ds = pydicom.dcmread(file)
            pixels = ds.pixel_array
        except Exception as exc:  # pydicom raises many kinds on corrupt or unsupported pixel data
            skipped.append(f"{file.name}: unreadable pixel data ({one_line(exc)})")
            continue
        frames += _frames(ds, pixels, file, folder)
        first = ds if first is None else first
    listed = "; ".join(skipped[:_LISTED]) + (f"; and {len(skipped) - _LISTED} more" if len(skipped) > _LISTED else "")
    if not frames:
        raise VolrenError(f"{folder}: no DICOM image to read ({listed})")
    if skipped:
        log.warning(f"volren: warning: {folder}: skipped {len(skipped)} file(s) that are no image of the series: "
                    f"{listed}")
    head = frames[0]
    for f in frames[1:]:
        if f.pixels.shape != head.pixels.shape:
            raise VolrenError(f"{folder}: slices differ in size ({head.name} is {head.pixels.shape[1]}x"
                              f"{head.pixels.shape[0]}, {f.name} is {f.pixels.shape[1]}x{f.pixels.shape[0]})")
        if not np.allclose(f.orientation, head.orientation, atol=1e-4):
            raise VolrenError(f"{folder}: slices have different orientations ({head.name} and {f.name}: "
                              "ImageOrientationPatient differs); one series at a time")
        if not np.allclose(f.spacing, head.spacing, rtol=1e-4):
            raise VolrenError(f"{folder}: slices have different PixelSpacing ({head.name} and {f.name})")
    row, column = head.orientation[:3], head.orientation[3:]
    normal = np.cross(row, column)
    frames.sort(key=lambda f: float(np.dot(f.position, normal)))
    positions = np.array([f.position for f in frames])
    if len(frames) < 2 and member is not None:
        named = ", ".join(copies[:3]) + (", ..." if len(copies) > 3 else "")
        also = f" ({len(copies)} other file(s) hold copies of it: {named})" if copies else ""
        raise VolrenError(f"{member}: its series has 1 slice in {folder}{also}; a volume needs at least 2")
    if len(frames) < 2:
        raise VolrenError(f"{folder}: one DICOM slice; a volume needs at least 2")
    steps = np.diff(positions, axis=0)
    along = steps @ normal
    if np.min(along) <= 1e-6 * max(1.0, float(np.max(np.abs(along)))):
        at = int(np.argmin(along))
        raise VolrenError(f"{folder}: slices {frames[at].name} and {frames[at + 1].name} share a position "
                          "along the slice normal (duplicates, or two series in one folder)")
    step = (positions[-1] - positions[0]) / (len(frames) - 1)
    deviation = np.linalg.norm(steps - step, axis=1)
    if np.max(deviation) > _STEP_TOLERANCE * np.linalg.norm(step):
        at = int(np.argmax(deviation))
        raise VolrenError(
            f"{folder}: uneven slice spacing: {np.linalg.norm(steps[at]):.4g} mm between "
            f"{frames[at].name} and {frames[at + 1].name}, {np.linalg.norm(step):.4g} mm on average "
            "(a missing slice?)")
    m = np.eye(4)
    m[:3, 0] = row * head.spacing[1]  # PixelSpacing = (between rows, between columns); columns advance along x
    m[:3, 1] = column * head.spacing[0]
    m[:3, 2] = step
    m[:3, 3] = positions[0]
    units = _units(first)
    stored = head.pixels.dtype
    if not units and all(f.slope == 1.0 and f.intercept == 0.0 for f in frames):
        # no rescale (MR, PET counts, ...): the stored integers, normalised by their BitsStored
        data = np.stack([f.pixels for f in frames])  # [z, y, x]: pixel_array is [row, column] = [y, x]
        return Grid(data, m, "LPS", 1e-3, bits_stored=int(first.get("BitsStored", 0) or 0) or None)
    # float32: HU are exact
    data = np.stack([f.pixels.astype(np.float32) * np.float32(f.slope) + np.float32(f.intercept) for f in frames])
    return Grid(data, m, "LPS", 1e-3, rescale=True, units=units, source=stored.name)
