"""A DICOM series (a folder of single-frame slices) as one grid placed in patient coordinates (LPS, mm), via pydicom.

Slices are sorted by their position along the slice normal (ImageOrientationPatient row x column direction); the
series is refused, with one line naming the folder, when slices differ in size, orientation or pixel spacing, when
two share a position, or when the steps between positions are uneven (a missing slice). Stored values become
RescaleSlope * v + RescaleIntercept (Hounsfield units for CT) per slice.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from volren.errors import VolrenError

_STEP_TOLERANCE = 0.01
"""Relative spread allowed between slice steps (and between the steps' directions) before a series is refused."""


def _series_files(folder: Path) -> list[Path]:
    """The ``.dcm`` files of the folder; when there are none, every visible regular file (series without extensions)."""
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    dcm = [p for p in files if p.suffix.lower() == ".dcm"]
    return dcm or files


def _vector(ds, keyword: str, count: int, folder: Path, file: Path) -> np.ndarray:
    value = getattr(ds, keyword, None)
    if value is None or len(value) != count:
        raise VolrenError(f"{folder}: DICOM slice {file.name} has no {keyword}; volren cannot place the series")
    return np.asarray([float(v) for v in value], dtype=np.float64)


def read_dicom_series(folder: Path, member: Path | None = None):
    """Read the series in ``folder`` as a ``volren.data.loaders._Grid`` (values float32, rescaled; index -> LPS mm).
    With ``member`` (one of its files), read that file's series (its SeriesInstanceUID) and skip the folder's other
    series; without it, a folder of several series is refused."""
    import pydicom  # lazy: only DICOM users pay for the import
    from pydicom.errors import InvalidDicomError

    from volren.data.loaders import _Grid

    files = _series_files(folder)
    if not files:
        raise VolrenError(f"{folder}: empty folder; a DICOM series needs its slice files (.dcm)")
    wanted = None
    if member is not None:
        try:
            wanted = str(getattr(pydicom.dcmread(member, stop_before_pixels=True), "SeriesInstanceUID", ""))
        except InvalidDicomError:
            raise VolrenError(f"{member}: not a DICOM file") from None
    slices = []
    series: dict[str, Path] = {}  # SeriesInstanceUID -> its first file
    for file in files:
        try:
            if wanted is not None and str(getattr(pydicom.dcmread(file, stop_before_pixels=True),
                                                  "SeriesInstanceUID", "")) != wanted:
                continue  # another series in the same folder
            ds = pydicom.dcmread(file)
            pixels = ds.pixel_array if "PixelData" in ds else None
        except InvalidDicomError:
            raise VolrenError(f"{folder}: {file.name} is not a DICOM file") from None
        except Exception as exc:  # pydicom raises many kinds on corrupt or unsupported pixel data
            raise VolrenError(f"{folder}: cannot read DICOM slice {file.name} ({type(exc).__name__}: {exc})") from None
        if pixels is None:
            raise VolrenError(f"{folder}: {file.name} holds no image (no PixelData)")
        if pixels.ndim != 2:
            raise VolrenError(f"{folder}: {file.name} holds pixel data of shape {pixels.shape}; volren reads "
                              "single-frame grey slices")
        orientation = _vector(ds, "ImageOrientationPatient", 6, folder, file)
        position = _vector(ds, "ImagePositionPatient", 3, folder, file)
        spacing = _vector(ds, "PixelSpacing", 2, folder, file)
        slope = float(getattr(ds, "RescaleSlope", 1.0) or 1.0)
        intercept = float(getattr(ds, "RescaleIntercept", 0.0) or 0.0)
        rescaled = pixels.astype(np.float32) * np.float32(slope) + np.float32(intercept)  # float32: HU are exact
        slices.append((file, rescaled, orientation, position, spacing))
        series.setdefault(str(getattr(ds, "SeriesInstanceUID", "")), file)
    if len(series) > 1:
        names = ", ".join(f.name for f in series.values())
        raise VolrenError(f"{folder}: holds {len(series)} DICOM series (first files {names}); put each series in its "
                          "own folder")
    first_file, first_pixels, orientation, _, spacing = slices[0]
    for file, pixels, o, _, s in slices[1:]:
        if pixels.shape != first_pixels.shape:
            raise VolrenError(f"{folder}: slices differ in size ({first_file.name} is {first_pixels.shape[1]}x"
                              f"{first_pixels.shape[0]}, {file.name} is {pixels.shape[1]}x{pixels.shape[0]})")
        if not np.allclose(o, orientation, atol=1e-4):
            raise VolrenError(f"{folder}: slices have different orientations ({first_file.name} and {file.name}: "
                              "ImageOrientationPatient differs); one series at a time")
        if not np.allclose(s, spacing, rtol=1e-4):
            raise VolrenError(f"{folder}: slices have different PixelSpacing ({first_file.name} and {file.name})")
    row, column = orientation[:3], orientation[3:]
    normal = np.cross(row, column)
    slices.sort(key=lambda sl: float(np.dot(sl[3], normal)))
    positions = np.array([sl[3] for sl in slices])
    if len(slices) < 2:
        raise VolrenError(f"{folder}: one DICOM slice; a volume needs at least 2")
    steps = np.diff(positions, axis=0)
    along = steps @ normal
    if np.min(along) <= 1e-6 * max(1.0, float(np.max(np.abs(along)))):
        at = int(np.argmin(along))
        raise VolrenError(f"{folder}: slices {slices[at][0].name} and {slices[at + 1][0].name} share a position "
                          "along the slice normal (duplicates, or two series in one folder)")
    step = (positions[-1] - positions[0]) / (len(slices) - 1)
    deviation = np.linalg.norm(steps - step, axis=1)
    if np.max(deviation) > _STEP_TOLERANCE * np.linalg.norm(step):
        at = int(np.argmax(deviation))
        raise VolrenError(
            f"{folder}: uneven slice spacing: {np.linalg.norm(steps[at]):.4g} mm between "
            f"{slices[at][0].name} and {slices[at + 1][0].name}, {np.linalg.norm(step):.4g} mm on average "
            "(a missing slice?)")
    m = np.eye(4)
    m[:3, 0] = row * spacing[1]  # PixelSpacing = (between rows, between columns); columns advance along x
    m[:3, 1] = column * spacing[0]
    m[:3, 2] = step
    m[:3, 3] = positions[0]
    data = np.stack([sl[1] for sl in slices])  # [z, y, x]: pixel_array is [row, column] = [y, x]
    return _Grid(data, m, "LPS", 1e-3, rescale=True)
