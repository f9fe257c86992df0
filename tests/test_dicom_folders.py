"""DICOM folders as users have them (issue 21.6): neighbours that are no image of the series (notes, a DICOMDIR, a
broken file, an RT structure set) are skipped with one warning naming them; multi-frame (enhanced) CT and RT dose are
read and placed; unsigned CT that carries HU through RescaleIntercept keeps them, and the ct presets classify it."""

from __future__ import annotations

import logging
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pydicom.data import get_testdata_file
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.sequence import Sequence
from pydicom.uid import ExplicitVRLittleEndian, generate_uid

from test_loaders import density_at, write_dicom_series
from volren.data.loaders import load_volume
from volren.errors import VolrenError

ENHANCED_CT = "1.2.840.10008.5.1.4.1.1.2.1"
RT_DOSE = "1.2.840.10008.5.1.4.1.1.481.2"
MR = "1.2.840.10008.5.1.4.1.1.4"
CT = "1.2.840.10008.5.1.4.1.1.2"


def dataset(sop_class: str, stored: np.ndarray, **attributes) -> Dataset:
    """A minimal image dataset: ``stored`` [frame, row, column] (or [row, column]) as its pixel data, unsigned with
    the dtype's bits (BitsStored from ``attributes`` when given), plus ``attributes``."""
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = sop_class, meta.MediaStorageSOPInstanceUID
    ds.SeriesInstanceUID = generate_uid()
    ds.Rows, ds.Columns = stored.shape[-2:]
    if stored.ndim == 3:
        ds.NumberOfFrames = len(stored)
    bits = 8 * stored.dtype.itemsize
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = bits, bits, bits - 1, 0
    for keyword, value in attributes.items():
        setattr(ds, keyword, value)
    ds.PixelData = stored.astype(stored.dtype.newbyteorder("<")).tobytes()
    return ds


def _item(**attributes) -> Dataset:
    item = Dataset()
    for keyword, value in attributes.items():
        setattr(item, keyword, value)
    return item


def test_neighbours_that_are_no_image_are_skipped_with_one_warning(tmp_path: Path, caplog) -> None:
    """A series of extensionless slices beside notes.txt, a DICOMDIR (pydicom's), an RT structure set (no pixels),
    a file of random bytes and a slice whose pixel data is cut short: the series reads exactly as alone, one warning
    names the five skipped files (and no slice); without the series the folder is refused naming why."""
    z = [0.0, 2.0, 4.0, 6.0]
    write_dicom_series(tmp_path / "clean", [(0, 0, zz) for zz in z], size=(6, 5), radius=3.0)
    expected = load_volume(tmp_path / "clean")
    folder = tmp_path / "ct"
    folder.mkdir()
    for n, file in enumerate(sorted((tmp_path / "clean").iterdir())):
        shutil.copy(file, folder / f"IM{n:04d}")
    (folder / "notes.txt").write_text("scanned on Tuesday\n")
    shutil.copy(get_testdata_file("DICOMDIR"), folder / "DICOMDIR")
    structures = dataset("1.2.840.10008.5.1.4.1.1.481.3", np.zeros((1, 1), np.uint8), Modality="RTSTRUCT")
    for keyword in ("PixelData", "Rows", "Columns"):
        delattr(structures, keyword)
    structures.save_as(folder / "RS0001", enforce_file_format=True)
    (folder / "noise").write_bytes(np.random.default_rng(0).bytes(300))
    whole = (folder / "IM0001").read_bytes()
    (folder / "IM0001-partial").write_bytes(whole[:-20])  # a copy cut short: no full pixel data
    with caplog.at_level(logging.WARNING, logger="volren.data"):
        loaded = load_volume(folder)
    np.testing.assert_array_equal(loaded.density, expected.density)
    np.testing.assert_array_equal(loaded.to_world, expected.to_world)
    assert len(caplog.records) == 1
    line = caplog.records[0].getMessage()
    assert "\n" not in line and line.startswith(f"volren: warning: {folder}: skipped 5 file(s)")
    for name, why in (("DICOMDIR", "a DICOMDIR index"), ("IM0001-partial", "unreadable pixel data"),
                      ("RS0001", "no image: RTSTRUCT"), ("noise", "not DICOM"), ("notes.txt", "not DICOM")):
        assert f"{name}: {why}" in line, (name, line)
    assert "IM0000" not in line and "IM0002" not in line
    for file in folder.glob("IM000?"):
        file.unlink()
    with pytest.raises(VolrenError, match=rf"^{folder}: no DICOM image to read \(DICOMDIR: a DICOMDIR index; "
                                          r"RS0001: no image: RTSTRUCT; noise: not DICOM; notes\.txt: not DICOM; "
                                          r"IM0001-partial: unreadable pixel data .*\)$"):
        load_volume(folder)


def test_skip_warning_is_one_line_on_stderr(tmp_path: Path) -> None:
    """Outside pytest's log capture the warning reaches stderr as exactly one line (logging's last-resort handler),
    as the CLI prints it."""
    write_dicom_series(tmp_path / "ct", [(0, 0, zz) for zz in (0.0, 2.0)], size=(4, 4), radius=1.0)
    (tmp_path / "ct" / "bad.dcm").write_bytes(b"not dicom")
    code = f"from volren.data.loaders import load_volume; load_volume({str(tmp_path / 'ct')!r})"
    err = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stderr
    assert err == f"volren: warning: {tmp_path / 'ct'}: skipped 1 file(s) that are no image of the series: bad.dcm: " \
                  "not DICOM\n"


def test_many_skipped_files_are_counted_not_listed(tmp_path: Path) -> None:
    """pydicom's TINY_ALPHA file set holds 50 CT headers without pixel data: refused, six named and 44 counted."""
    folder = Path(get_testdata_file("DICOMDIR")).parent / "TINY_ALPHA" / "PT000000" / "ST000000" / "SE000000"
    with pytest.raises(VolrenError, match=r"no DICOM image to read \(IM000000: no image: CT; (IM\w+: no image: CT; ){5}"
                                          r"and 44 more\)$"):
        load_volume(folder)


def enhanced_ct(path: Path, z_mm: list[float], marker: tuple[int, int, int] | None, **attributes) -> None:
    """An Enhanced CT of one frame per ``z_mm`` (uint16 stored, RescaleIntercept -1024 shared): frames at LPS (-10,
    -20, z) mm, written in the order of ``z_mm``; 1000 HU at ``marker`` = (frame, row, column), -1000 HU elsewhere;
    0.5 mm columns, 0.8 mm rows."""
    hu = np.full((len(z_mm), 6, 8), -1000.0)
    if marker is not None:
        hu[marker] = 1000.0
    shared = _item(PlaneOrientationSequence=Sequence([_item(ImageOrientationPatient=[1, 0, 0, 0, 1, 0])]),
                   PixelMeasuresSequence=Sequence([_item(PixelSpacing=[0.8, 0.5], SliceThickness=2.0)]),
                   PixelValueTransformationSequence=Sequence([_item(RescaleSlope=1, RescaleIntercept=-1024,
                                                                    RescaleType="HU")]))
    per_frame = [_item(PlanePositionSequence=Sequence([_item(ImagePositionPatient=[-10.0, -20.0, zz])]))
                 for zz in z_mm]
    groups = {"SharedFunctionalGroupsSequence": Sequence([shared]),
              "PerFrameFunctionalGroupsSequence": Sequence(per_frame)}
    ds = dataset(ENHANCED_CT, (hu + 1024).astype(np.uint16), Modality="CT", **groups, **attributes)
    ds.save_as(path, enforce_file_format=True)


def test_enhanced_ct_frames_placed_by_their_functional_groups(tmp_path: Path) -> None:
    """Frames at z = 6, 0, 4, 2 mm (stored out of order) sort to 0, 2, 4, 6; the marker on the frame at z = 4 mm,
    row 2, column 5 lands at LPS (-10 + 5 * 0.5, -20 + 2 * 0.8, 4) mm = world (-7.5, 4, 18.4) mm; HU kept."""
    (tmp_path / "e").mkdir()
    enhanced_ct(tmp_path / "e" / "ct.dcm", [6.0, 0.0, 4.0, 2.0], (2, 2, 5))
    loaded = load_volume(tmp_path / "e")
    assert loaded.density.shape == (4, 6, 8)
    assert loaded.value_range == (-1000.0, 1000.0) and loaded.hounsfield
    assert loaded.value_mapping.to_dict() == {"source": "uint16", "range": [-1000.0, 1000.0], "units": "HU"}
    assert np.argwhere(loaded.density == 1.0).tolist() == [[2, 2, 5]]
    marker = np.array([[-7.5, 4.0, 18.4]]) * 1e-3
    assert density_at(loaded, marker) == 1.0
    assert density_at(loaded, marker * [1, -1, 1] + [0, 6e-3, 0]) == 0.0  # z = 4 mm mirrored about the middle: 2
    one = load_volume(tmp_path / "e" / "ct.dcm")  # the file names its series: itself
    np.testing.assert_array_equal(one.to_world, loaded.to_world)
    series = generate_uid()  # the same frames as one single-frame enhanced file each (as some scanners export)
    (tmp_path / "f").mkdir()
    for n, zz in enumerate([6.0, 0.0, 4.0, 2.0]):
        enhanced_ct(tmp_path / "f" / f"{n}.dcm", [zz], (0, 2, 5) if zz == 4.0 else None, SeriesInstanceUID=series)
    split = load_volume(tmp_path / "f")
    np.testing.assert_array_equal(split.density, loaded.density)
    np.testing.assert_allclose(split.to_world, loaded.to_world, atol=1e-15)


def rt_dose(path: Path, offsets: list[float], ipp_z: float = -30.0, scaling: float = 2e-4) -> np.ndarray:
    """An RT dose grid (uint32, DoseGridScaling ``scaling`` Gy) of 3 frames at GridFrameOffsetVector ``offsets``
    from ImagePositionPatient (12, 16, ``ipp_z``) mm, 2 x 2.5 mm pixels; returns the stored values: 10000 at frame 2,
    row 1, column 3, 500 elsewhere."""
    stored = np.full((3, 4, 5), 500, np.uint32)
    stored[2, 1, 3] = 10000
    dataset(RT_DOSE, stored, Modality="RTDOSE", ImagePositionPatient=[12.0, 16.0, ipp_z],
            ImageOrientationPatient=[1, 0, 0, 0, 1, 0], PixelSpacing=[2.5, 2.0], GridFrameOffsetVector=offsets,
            FrameIncrementPointer=0x3004000C, DoseGridScaling=scaling, DoseUnits="GY",
            DoseType="PHYSICAL").save_as(path, enforce_file_format=True)
    return stored


def test_rt_dose_frames_by_grid_offsets_values_in_gray(tmp_path: Path) -> None:
    """Frame k sits at ImagePositionPatient + offset_k * normal: the 2.0 Gy marker (frame 2 at offset 6 mm, row 1,
    column 3) lands at LPS (12 + 6, 16 + 2.5, -30 + 6) mm = world (18, -24, -18.5) mm; value_range is 0..2 Gy
    (stored * DoseGridScaling), density dose / 2 Gy. Offsets that are absolute z (the first equals the position's z)
    place the frames the same way."""
    (tmp_path / "a").mkdir()
    stored = rt_dose(tmp_path / "a" / "rd.dcm", [0.0, 3.0, 6.0])
    loaded = load_volume(tmp_path / "a")
    assert loaded.density.shape == (3, 4, 5) and not loaded.hounsfield
    assert loaded.value_range == (0.0, pytest.approx(2.0, rel=1e-6))
    assert loaded.value_mapping.units == "Gy" and loaded.value_mapping.source == "uint32"
    np.testing.assert_allclose(loaded.density, stored / 10000, rtol=1e-6)
    marker = np.array([[18.0, -24.0, -18.5]]) * 1e-3
    assert density_at(loaded, marker) == 1.0
    assert density_at(loaded, marker - np.array([2e-3, 0, 0])) == pytest.approx(0.05)  # column 2: 500 * 2e-4 Gy
    (tmp_path / "b").mkdir()
    rt_dose(tmp_path / "b" / "rd.dcm", [-30.0, -27.0, -24.0])
    np.testing.assert_allclose(load_volume(tmp_path / "b").to_world, loaded.to_world, atol=1e-15)


def test_pydicom_bundled_rt_dose(tmp_path: Path) -> None:
    """pydicom's rtdose.dcm (15 frames of 10 x 10, 10 mm pixels, 5 mm offsets, relative dose * 1e-6): its box spans
    LPS x 184.4..284.4, y 194.4..294.4 and z -764.4..-689.4 mm (voxel boxes about the 10 x 10 x 5 mm centres)."""
    (tmp_path / "rd").mkdir()
    shutil.copy(get_testdata_file("rtdose.dcm"), tmp_path / "rd" / "rtdose.dcm")
    loaded = load_volume(tmp_path / "rd")
    assert loaded.density.shape == (15, 10, 10) and loaded.value_mapping.units == "relative"
    corners = loaded.corners_world * 1e3
    np.testing.assert_allclose(corners.min(axis=0), [184.43125, -764.37, -294.43125], atol=1e-6)
    np.testing.assert_allclose(corners.max(axis=0), [284.43125, -689.37, -194.43125], atol=1e-6)


def test_unsigned_ct_with_rescale_intercept_keeps_hounsfield_units_for_the_ct_presets(tmp_path: Path) -> None:
    """A uint16 CT series (stored = HU + 1024, RescaleIntercept -1024) of air, soft tissue (40 HU) and bone
    (1000 HU): value_range stays in HU, and under ct-bone only bone has extinction (120 /m), under ct-muscle tissue
    12 /m and bone 80 /m, as the presets' HU points say."""
    from volren.render.vpt.tracer import transfer_tables
    from volren.scene import Volume

    folder = tmp_path / "ct"
    folder.mkdir()
    hu = np.full((3, 6, 6), -1000.0)
    hu[:, 1:5, 1:5] = 40.0
    hu[:, 2:4, 2:4] = 1000.0
    series = generate_uid()
    for k in range(3):
        dataset(CT, (hu[k] + 1024).astype(np.uint16), Modality="CT", SeriesInstanceUID=series,
                ImagePositionPatient=[0.0, 0.0, 2.0 * k], ImageOrientationPatient=[1, 0, 0, 0, 1, 0],
                PixelSpacing=[1.0, 1.0], RescaleSlope=1, RescaleIntercept=-1024).save_as(folder / f"{k}.dcm",
                                                                                      enforce_file_format=True)
    loaded = load_volume(folder)
    assert loaded.value_range == (-1000.0, 1000.0) and loaded.hounsfield
    assert loaded.value_mapping.to_dict() == {"source": "uint16", "range": [-1000.0, 1000.0], "units": "HU"}
    volume = Volume(loaded.density, value_range=loaded.value_range)
    for name, expected in (("ct-bone", np.select([hu == 1000], [120.0], 0.0)),
                           ("ct-muscle", np.select([hu == 1000, hu == 40], [80.0, 12.0], 0.0))):
        table = transfer_tables([volume], name)[0]
        extinction = np.interp(loaded.density, np.linspace(0, 1, len(table)), table[:, 0])  # max density is 1
        np.testing.assert_allclose(extinction, expected, atol=0.2, err_msg=name)


def test_mr_without_rescale_is_no_hounsfield_and_maps_by_bits_stored(tmp_path: Path) -> None:
    """An MR series (no rescale, 12 of 16 bits stored, values up to 1000) keeps its stored integers, density
    v / 4095, units raw: it is no CT (the loader called every DICOM series HU before)."""
    folder = tmp_path / "mr"
    folder.mkdir()
    series = generate_uid()
    for k in range(2):
        stored = np.full((4, 4), 250 * (k + 1), np.uint16)
        stored[0, 0] = 1000
        dataset(MR, stored, Modality="MR", SeriesInstanceUID=series, BitsStored=12, HighBit=11,
                ImagePositionPatient=[0.0, 0.0, 3.0 * k], ImageOrientationPatient=[1, 0, 0, 0, 1, 0],
                PixelSpacing=[1.0, 1.0]).save_as(folder / f"{k}.dcm", enforce_file_format=True)
    loaded = load_volume(folder)
    assert not loaded.hounsfield and loaded.value_range == (0.0, 4095.0)
    assert loaded.value_mapping.to_dict() == {"source": "uint16", "range": [0.0, 4095.0], "units": "raw"}
    np.testing.assert_allclose(loaded.density[:, 1, 1], [250 / 4095, 500 / 4095], rtol=1e-6)


@pytest.mark.parametrize(("modality", "sop_class"), [("CT", CT), ("MR", MR)])
def test_each_slice_is_rescaled_by_its_own_slope_and_intercept(tmp_path: Path, modality: str, sop_class: str) -> None:
    """Scanners may change RescaleSlope / RescaleIntercept from slice to slice (PET and Philips MR do per slice):
    here the first slice has slope 1, intercept 0 and the two later ones slope 2, intercept -1024. Each slice's
    values are its stored values rescaled by its own pair, in a CT (HU) as in an MR (whose first slice's identity
    rescale must not make the series read as stored integers): slice 0 holds 40 and 1000, slice 1 -1000 and 1000,
    slice 2 40 and 0, so the loaded values span -1000..1000."""
    folder = tmp_path / modality
    folder.mkdir()
    series = generate_uid()
    stored = np.array([[40, 1000], [12, 1012], [532, 512]], np.uint16)  # per slice: its fill and its pixel (0, 0)
    rescale = [(1, 0), (2, -1024), (2, -1024)]
    for k, ((fill, corner), (slope, intercept)) in enumerate(zip(stored, rescale, strict=True)):
        pixels = np.full((4, 5), fill, np.uint16)
        pixels[0, 0] = corner
        dataset(sop_class, pixels, Modality=modality, SeriesInstanceUID=series,
                ImagePositionPatient=[0.0, 0.0, 2.0 * k], ImageOrientationPatient=[1, 0, 0, 0, 1, 0],
                PixelSpacing=[1.0, 1.0], RescaleSlope=slope, RescaleIntercept=intercept).save_as(
                    folder / f"{k}.dcm", enforce_file_format=True)
    loaded = load_volume(folder)
    assert loaded.value_range == (-1000.0, 1000.0)
    assert loaded.value_mapping.units == ("HU" if modality == "CT" else "raw")
    lo, hi = loaded.value_range
    values = lo + loaded.density * (hi - lo)  # back to the rescaled values
    np.testing.assert_allclose(values[:, 1, 1], [40.0, -1000.0, 40.0], atol=1e-3)  # each slice's fill
    np.testing.assert_allclose(values[:, 0, 0], [1000.0, 1000.0, 0.0], atol=1e-3)  # each slice's pixel (0, 0)


PYDICOM_NEIGHBOURS = ("CT_small.dcm", "MR_small.dcm", "MR_small_RLE.dcm", "rtplan.dcm", "SC_rgb_jpeg.dcm",
                      "ExplVR_BigEndNoMeta.dcm")
"""pydicom's bundled files: a CT slice, an MR slice and a copy of it (the same SOP instance, RLE-compressed), an RT
plan (no pixels), a colour image and a header without file meta"""


def _mixed_folder(tmp_path: Path) -> Path:
    """A folder as users have them (issue 45 item 3): pydicom's files beside two sphere series written here, A (5
    axial slices of 6 x 5, bone about LPS (2, 2, 4) mm) and B (3 slices of 4 x 7), and notes."""
    folder = tmp_path / "mixed"
    folder.mkdir()
    for name in PYDICOM_NEIGHBOURS:
        shutil.copy(get_testdata_file(name), folder / name)
    (folder / "notes.txt").write_text("two series and pydicom's test files\n")
    write_dicom_series(tmp_path / "a", [(0.0, 0.0, z) for z in (0.0, 2.0, 4.0, 6.0, 8.0)], size=(6, 5), radius=3.0,
                       centre=(2.0, 2.0, 4.0))
    write_dicom_series(tmp_path / "b", [(0.0, 0.0, z) for z in (0.0, 3.0, 6.0)], size=(4, 7), radius=4.0,
                       centre=(1.0, 1.0, 3.0))
    for series in ("a", "b"):
        for file in (tmp_path / series).iterdir():
            shutil.copy(file, folder / f"{series}-{file.name}")
    return folder


def test_a_file_alone_reads_its_own_series_beside_others(tmp_path: Path, caplog, monkeypatch) -> None:
    """``a-im002.dcm`` reads series A (5 slices), ``b-im001.dcm`` series B (3), each exactly as its own folder reads;
    pixel data is read from that series' files only, and the folder's other files (pydicom's, notes) raise no
    warning: they are not of the series."""
    import pydicom

    folder = _mixed_folder(tmp_path)
    full_reads: list[str] = []
    dcmread = pydicom.dcmread

    def counting(file, *args, **kwargs):
        if not kwargs.get("stop_before_pixels"):
            full_reads.append(Path(file).name)
        return dcmread(file, *args, **kwargs)

    monkeypatch.setattr(pydicom, "dcmread", counting)
    for series, member, shape in (("a", "a-im002.dcm", (5, 6, 5)), ("b", "b-im001.dcm", (3, 4, 7))):
        expected = load_volume(tmp_path / series)
        full_reads.clear()
        with caplog.at_level(logging.WARNING):
            loaded = load_volume(folder / member)
        assert loaded.density.shape == shape
        np.testing.assert_array_equal(loaded.density, expected.density)
        np.testing.assert_array_equal(loaded.to_world, expected.to_world)
        assert loaded.value_range == (-1000.0, 1000.0) and loaded.hounsfield
        assert sorted(full_reads) == sorted(f"{series}-{f.name}" for f in (tmp_path / series).iterdir())
    assert not caplog.records, [r.getMessage() for r in caplog.records]
    a = load_volume(folder / "a-im000.dcm")
    # LPS (2, 2, 4) mm is world (2, 4, -2) mm: bone (1000 HU, density 1); LPS (0, 7.5, 0) mm is air
    np.testing.assert_array_equal(density_at(a, np.array([[2.0, 4.0, -2.0], [0.0, 0.0, -7.5]]) * 1e-3), [1.0, 0.0])


@pytest.mark.parametrize(("name", "copies"), [
    ("CT_small.dcm", ""), ("MR_small.dcm", " (1 other file(s) hold copies of it: MR_small_RLE.dcm)")])
def test_a_lone_slice_is_refused_naming_its_file(tmp_path: Path, name: str, copies: str) -> None:
    """pydicom's CT_small.dcm and MR_small.dcm are each the only slice (MR_small_RLE.dcm the same image again) of
    their series: one line naming the file, its folder and the count, not the folder's other series."""
    folder = _mixed_folder(tmp_path)
    with pytest.raises(VolrenError) as err:
        load_volume(folder / name)
    assert str(err.value) == f"{folder / name}: its series has 1 slice in {folder}{copies}; a volume needs at least 2"


def test_an_extensionless_dicom_file_alone_reads_its_series(tmp_path: Path) -> None:
    """Scanners name slices IM0001 with no extension: one given alone reads its series too (the .dcm series beside
    it is skipped); before, an unknown extension was refused."""
    folder = _mixed_folder(tmp_path)
    for n, file in enumerate(sorted((tmp_path / "a").iterdir())):
        shutil.copy(file, folder / f"IM{n:04d}")
        (folder / f"a-{file.name}").unlink()
    loaded = load_volume(folder / "IM0003")
    np.testing.assert_array_equal(loaded.density, load_volume(tmp_path / "a").density)


def test_cli_renders_a_file_alone_as_its_series(tmp_path: Path, capfd) -> None:
    """``volren render --volume mixed/b-im001.dcm`` is the picture of series B's own folder; a lone slice is one
    error line naming the file."""
    from test_cli import _linear_render, render_error

    folder = _mixed_folder(tmp_path)
    reference = _linear_render(capfd, tmp_path / "ref", tmp_path / "b")
    assert reference[..., 3].max() > 0.05
    np.testing.assert_array_equal(_linear_render(capfd, tmp_path / "one", folder / "b-im001.dcm"), reference)
    line = render_error(capfd, tmp_path, ["--volume", folder / "CT_small.dcm"], f"{folder / 'CT_small.dcm'}: its "
                        "series has 1 slice")
    assert line.count("CT_small.dcm") == 1
