"""Volume files placed in the world: NRRD, NIfTI and DICOM spheres of known radius in physical units land with the
right size, position and orientation; formats without placement keep their aspect; bad DICOM series are refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from volren.data.loaders import load_volume
from volren.errors import VolrenError

RADIUS_MM = 12.0


def sphere(shape_zyx: tuple[int, int, int], index_to_mm) -> np.ndarray:
    """uint8 grid [z, y, x]: 200 inside a sphere of RADIUS_MM about the origin of the file's space, 0 outside."""
    k, j, i = np.indices(shape_zyx)
    p = index_to_mm(np.stack([i, j, k], axis=-1).astype(float))
    return np.where(np.linalg.norm(p, axis=-1) < RADIUS_MM, 200, 0).astype(np.uint8)


def density_at(loaded, world: np.ndarray) -> np.ndarray:
    """Nearest-voxel density at world points, through the loaded to_world (local -1 + (i + 0.5) * 2 / n = voxel i)."""
    local = (np.c_[world, np.ones(len(world))] @ np.linalg.inv(loaded.to_world).T)[:, :3]
    n = np.array(loaded.density.shape[::-1])
    idx = np.rint((local + 1) * n / 2 - 0.5).astype(int)
    assert np.all((idx >= 0) & (idx < n)), "probe outside the grid"
    return loaded.density[idx[:, 2], idx[:, 1], idx[:, 0]]


def check_sphere(loaded, centre_world_m: np.ndarray) -> None:
    """Inside at 0.75 r and outside at 1.25 r along each world axis (both signs) about the expected centre; the
    boxes of the voxels above half density span 2 r along every world axis to within one voxel step."""
    r = RADIUS_MM * 1e-3
    axes = np.vstack([np.eye(3), -np.eye(3)])
    np.testing.assert_allclose(density_at(loaded, centre_world_m + 0.75 * r * axes), 200 / 255, rtol=1e-6)
    np.testing.assert_array_equal(density_at(loaded, centre_world_m + 1.25 * r * axes), 0)
    k, j, i = np.nonzero(loaded.density > 0.5)
    n = np.array(loaded.density.shape[::-1])
    local = -1 + (np.stack([i, j, k], axis=-1) + 0.5) * 2 / n
    world = local @ loaded.to_world[:3, :3].T + loaded.to_world[:3, 3]
    step = np.abs(loaded.to_world[:3, :3] @ (2 / n))  # one voxel's world extent per axis
    extent = world.max(axis=0) - world.min(axis=0) + step  # the voxels' boxes, not their centres
    assert np.all(np.abs(extent - 2 * r) <= step + 1e-9), (extent, step)
    np.testing.assert_allclose((world.max(axis=0) + world.min(axis=0)) / 2, centre_world_m, atol=1e-9 + step.max())


def test_anisotropic_lps_nrrd_sphere(tmp_path: Path) -> None:
    """NRRD in LPS mm with spacing 0.5 x 1 x 2 mm and an origin off zero: LPS (x, y, z) -> world (x, z, -y) m."""
    import nrrd

    origin = np.array([-20.0, -18.0, -16.0])  # the sphere sits at LPS (0, 0, 0), off the grid centre
    spacing = np.array([0.5, 1.0, 2.0])
    shape = (18, 40, 80)  # z, y, x: 36 x 40 x 40 mm
    data = sphere(shape, lambda ijk: origin + ijk * spacing)
    header = {"space": "left-posterior-superior", "space directions": np.diag(spacing), "space origin": origin,
              "space units": ["mm", "mm", "mm"]}
    nrrd.write(str(tmp_path / "s.nrrd"), data, header, index_order="C")
    loaded = load_volume(tmp_path / "s.nrrd")
    check_sphere(loaded, np.zeros(3))
    assert loaded.value_range == (0.0, 255.0) and not loaded.hounsfield  # unsigned values are not HU
    # the voxel axes: x index along world +x at 0.5 mm, y index (Posterior) along world -z, z index (Superior) +y
    np.testing.assert_allclose(loaded.to_world[:3, :3] @ np.diag(2 / np.array(shape[::-1])),
                               [[5e-4, 0, 0], [0, 0, 2e-3], [0, -1e-3, 0]], atol=1e-15)
    np.testing.assert_allclose(density_at(loaded, np.array([[0.0, 0.0, 0.0]])), 200 / 255, rtol=1e-6)
    # voxel (0, 0, 0) sits at local -1 + 1 / n and lands exactly on the space origin: LPS (-20, -18, -16) mm
    first = loaded.to_world @ np.r_[-1 + 1 / np.array(shape[::-1]), 1.0]
    np.testing.assert_allclose(first[:3], np.array([-20.0, -16.0, 18.0]) * 1e-3, atol=1e-15)


def test_nrrd_units_flag_and_stated_metres(tmp_path: Path) -> None:
    """--units m reads the same file 1000x larger; a file that states metres is read in metres."""
    import nrrd

    data = np.zeros((4, 4, 4), np.uint8)
    nrrd.write(str(tmp_path / "a.nrrd"), data, {"space": "RAS", "space directions": np.eye(3) * 2,
                                                "space origin": np.zeros(3)}, index_order="C")
    mm = load_volume(tmp_path / "a.nrrd").to_world
    m = load_volume(tmp_path / "a.nrrd", units="m").to_world
    np.testing.assert_allclose(m[:3, :3], mm[:3, :3] * 1000)
    np.testing.assert_allclose(mm[:3, :3], [[-4e-3, 0, 0], [0, 0, 4e-3], [0, 4e-3, 0]])  # RAS -> (-x, z, y)
    nrrd.write(str(tmp_path / "b.nrrd"), data, {"space": "RAS", "space directions": np.eye(3) * 2,
                                                "space units": ["m", "m", "m"]}, index_order="C")
    np.testing.assert_allclose(load_volume(tmp_path / "b.nrrd").to_world[:3, :3], m[:3, :3])


def test_nifti_affine_sphere(tmp_path: Path) -> None:
    """NIfTI with an anisotropic, rotated affine (RAS mm): the sphere at RAS (5, -20, 30) mm lands at world
    (-5, 30, -20) mm with radius 12 mm."""
    import nibabel as nib

    c, s = np.cos(0.3), np.sin(0.3)
    affine = np.eye(4)
    affine[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.diag([0.8, 1.0, 1.5])
    centre_ras = np.array([5.0, -20.0, 30.0])
    shape_xyz = (40, 36, 24)
    affine[:3, 3] = centre_ras - affine[:3, :3] @ (np.array(shape_xyz) - 1) / 2
    data_zyx = sphere(shape_xyz[::-1], lambda ijk: ijk @ affine[:3, :3].T + affine[:3, 3] - centre_ras)
    image = nib.Nifti1Image(np.ascontiguousarray(data_zyx.transpose(2, 1, 0)), affine)
    image.header.set_xyzt_units("mm")
    nib.save(image, str(tmp_path / "s.nii.gz"))
    loaded = load_volume(tmp_path / "s.nii.gz")
    check_sphere(loaded, np.array([-5.0, 30.0, -20.0]) * 1e-3)


def write_dicom_series(folder: Path, positions_mm, *, orientation=(1, 0, 0, 0, 1, 0), size=(20, 24),
                       spacing=(1.5, 1.0), intercept=-1024.0, slope=1.0, radius=RADIUS_MM,
                       centre=(0.0, 0.0, 0.0), series: str | None = None) -> None:
    """Single-frame CT slices (uint16 stored values; HU = slope * v + intercept): bone (1000 HU) inside a sphere of
    ``radius`` mm about ``centre`` (LPS), air (-1000 HU) outside, all in ``series`` (a new SeriesInstanceUID by
    default). Files are written in shuffled order."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

    folder.mkdir(parents=True, exist_ok=True)
    rows, cols = size
    row_dir, col_dir = np.array(orientation[:3], float), np.array(orientation[3:], float)
    series = series or generate_uid()
    order = np.random.default_rng(1).permutation(len(positions_mm))
    for n, index in enumerate(order):
        ipp = np.asarray(positions_mm[index], float)
        j, i = np.indices((rows, cols))
        p = ipp + i[..., None] * spacing[1] * row_dir + j[..., None] * spacing[0] * col_dir
        hu = np.where(np.linalg.norm(p - np.asarray(centre), axis=-1) < radius, 1000.0, -1000.0)
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID, ds.SOPInstanceUID = CTImageStorage, meta.MediaStorageSOPInstanceUID
        ds.SeriesInstanceUID = series
        ds.Modality = "CT"
        ds.Rows, ds.Columns = rows, cols
        ds.ImagePositionPatient = [f"{v:.6g}" for v in ipp]
        ds.ImageOrientationPatient = [f"{v:.6g}" for v in orientation]
        ds.PixelSpacing = [f"{v:.6g}" for v in spacing]
        ds.RescaleSlope, ds.RescaleIntercept = f"{slope:g}", f"{intercept:g}"
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
        ds.PixelData = np.rint((hu - intercept) / slope).astype("<u2").tobytes()
        ds.save_as(folder / f"im{n:03d}.dcm", enforce_file_format=True)


def test_dicom_series_sphere_sorted_by_position(tmp_path: Path) -> None:
    """An axial series (2.5 mm slices, 1.5 x 1.0 mm pixels) written in shuffled order: sorted by position, rescaled
    to Hounsfield units (value_range -1000..1000), the sphere at LPS (3, -4, 20) mm at world (3, 20, 4) mm."""
    centre = np.array([3.0, -4.0, 20.0])
    z = 20.0 + 2.5 * np.arange(-7, 8)
    origin = np.array([3.0 - 16.5, -4.0 - 15.75])  # pixel (0, 0) so that the sphere centre is the grid centre
    write_dicom_series(tmp_path / "ct", [(origin[0], origin[1], zz) for zz in z], centre=centre, size=(22, 34))
    loaded = load_volume(tmp_path / "ct")
    assert loaded.density.shape == (15, 22, 34)
    assert loaded.value_range == (-1000.0, 1000.0) and loaded.hounsfield
    r = RADIUS_MM * 1e-3
    world_centre = np.array([3.0, 20.0, 4.0]) * 1e-3
    axes = np.vstack([np.eye(3), -np.eye(3)])
    np.testing.assert_array_equal(density_at(loaded, world_centre + 0.75 * r * axes), 1.0)
    np.testing.assert_array_equal(density_at(loaded, world_centre + 1.25 * r * axes), 0.0)
    np.testing.assert_allclose(loaded.to_world[:3, :3] @ np.diag(2 / np.array([34, 22, 15])),
                               [[1e-3, 0, 0], [0, 0, 2.5e-3], [0, -1.5e-3, 0]], atol=1e-15)


def test_dicom_sagittal_orientation(tmp_path: Path) -> None:
    """Sagittal slices (rows along -y... columns along -z: IOP 0,1,0,0,0,-1) stacked along x: the voxel axes map to
    world through LPS -> (x, z, -y)."""
    write_dicom_series(tmp_path / "sag", [(x, 0.0, 0.0) for x in (0.0, 2.0, 4.0)],
                       orientation=(0, 1, 0, 0, 0, -1), size=(4, 5), spacing=(1.0, 1.0))
    m = load_volume(tmp_path / "sag").to_world[:3, :3] @ np.diag(2 / np.array([5, 4, 3]))
    # normal = row x column = (0,1,0) x (0,0,-1) = (-1, 0, 0): sorted by -x, so the step runs from x = 4 to x = 0
    np.testing.assert_allclose(m, [[0, 0, -2e-3], [0, -1e-3, 0], [-1e-3, 0, 0]], atol=1e-15)


def test_pydicom_bundled_ct_slice_refused_alone(tmp_path: Path) -> None:
    """pydicom's bundled CT_small.dcm reads (its values rescale) but one slice is not a volume: alone in a folder,
    and named as a file in pydicom's own test folder (85 other files, other series), where the refusal names the
    file and its series' one slice, not the folder's other files (issue 45 item 3)."""
    import shutil

    from pydicom.data import get_testdata_file

    path = get_testdata_file("CT_small.dcm")
    if path is None:
        pytest.skip("pydicom test data not installed")
    (tmp_path / "one").mkdir()
    shutil.copy(path, tmp_path / "one" / "a.dcm")
    with pytest.raises(VolrenError, match=r"/one: one DICOM slice; a volume needs at least 2$"):
        load_volume(tmp_path / "one")
    with pytest.raises(VolrenError) as err:
        load_volume(path)
    assert str(err.value) == f"{path}: its series has 1 slice in {Path(path).parent}; a volume needs at least 2"


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("missing", r"uneven slice spacing: 4 mm between im\d+\.dcm and im\d+\.dcm, 2\.222 mm on average"),
        ("orientation", r"slices have different orientations"),
        ("size", r"slices differ in size"),
        ("duplicate", r"slices im\d+\.dcm and zz\.dcm share a position along the slice normal"),
        ("empty", r"empty folder; a DICOM series needs its slice files"),
        ("not-dicom", r"no DICOM image to read \(junk\.dcm: not DICOM\)$"),
        ("two-series", r"holds 2 DICOM series \(first files im\d+\.dcm, zz\.dcm\); put each series in its own folder"),
    ],
)
def test_bad_dicom_series_refused(tmp_path: Path, case: str, message: str) -> None:
    folder = tmp_path / case
    folder.mkdir()
    z = [0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0, 16.0, 18.0, 20.0]
    if case == "missing":
        write_dicom_series(folder, [(0, 0, zz) for zz in z if zz != 10.0], size=(4, 4), radius=1.0)
    elif case in ("orientation", "size", "duplicate", "two-series"):
        write_dicom_series(folder, [(0, 0, zz) for zz in z[:3]], size=(4, 4), radius=1.0, series="1.2.3")
        extra = {"orientation": {"orientation": (1, 0, 0, 0, 0.8, 0.6)}, "size": {"size": (4, 5)}, "duplicate": {},
                 "two-series": {"series": "1.2.4"}}[case]
        write_dicom_series(tmp_path / "x", [(0, 0, 2.0)], **{"size": (4, 4), "radius": 1.0, "series": "1.2.3", **extra})
        (tmp_path / "x" / "im000.dcm").rename(folder / "zz.dcm")
    elif case == "not-dicom":
        (folder / "junk.dcm").write_bytes(b"\x00" * 200)
    with pytest.raises(VolrenError, match=rf"^{folder}: {message}"):
        load_volume(folder)


def test_unplaced_formats_keep_their_aspect(tmp_path: Path) -> None:
    """.npy without --spacing: cubic voxels, longest side 2 m, centred; with spacing 1,1,3 mm: 3x taller voxels
    along z; a TIFF stack takes spacing the same way; spacing for a placed format is refused."""
    import tifffile

    a = np.zeros((10, 20, 40), np.float32)  # z, y, x
    np.save(tmp_path / "a.npy", a)
    np.testing.assert_allclose(load_volume(tmp_path / "a.npy").to_world[:3, :3], np.diag([1.0, 0.5, 0.25]))
    m = load_volume(tmp_path / "a.npy", spacing=(1, 1, 3)).to_world
    np.testing.assert_allclose(m[:3, :3], np.diag([0.02, 0.01, 0.015]))
    np.testing.assert_allclose(m[:3, 3], 0)
    tifffile.imwrite(tmp_path / "a.tif", (a + 1).astype(np.uint16))
    loaded = load_volume(tmp_path / "a.tif", spacing=(0.2, 0.2, 1), units="m")
    np.testing.assert_allclose(loaded.to_world[:3, :3], np.diag([4.0, 2.0, 5.0]))
    np.testing.assert_allclose(loaded.density, 1 / 255, rtol=1e-6)  # uint16 holding 1: an 8-bit depth
    import nrrd

    nrrd.write(str(tmp_path / "p.nrrd"), a, {"spacings": [1.0, 1.0, 3.0]}, index_order="C")
    with pytest.raises(VolrenError, match=r"p\.nrrd: this volume stores its own voxel spacing; spacing \(CLI: "
                       r"--spacing\) applies"):
        load_volume(tmp_path / "p.nrrd", spacing=(1, 1, 1))
    with pytest.raises(VolrenError, match=r"spacing must be three positive voxel sizes x,y,z"):
        load_volume(tmp_path / "a.npy", spacing=(1, 0, 1))
    # centimetres and microns (microscopy): the same spacing, scaled
    np.testing.assert_allclose(load_volume(tmp_path / "a.npy", spacing=(1, 1, 3), units="cm").to_world[:3, :3],
                               np.diag([0.2, 0.1, 0.15]))
    np.testing.assert_allclose(load_volume(tmp_path / "a.npy", spacing=(1, 1, 3), units="um").to_world[:3, :3],
                               np.diag([2e-5, 1e-5, 1.5e-5]))
    with pytest.raises(VolrenError, match=r"units must be one of m, cm, mm, um, got 'km'"):
        load_volume(tmp_path / "a.npy", units="km")


def test_non_square_spacing_nrrd_keeps_its_aspect(tmp_path: Path) -> None:
    """A 40 x 40 x 10 grid at 0.5 x 0.5 x 2 mm (plain ``spacings``, no space) is a 20 x 20 x 20 mm cube in the world."""
    import nrrd

    nrrd.write(str(tmp_path / "c.nrrd"), np.zeros((10, 40, 40), np.float32), {"spacings": [0.5, 0.5, 2.0]},
               index_order="C")
    loaded = load_volume(tmp_path / "c.nrrd")
    extent = np.ptp(np.array([c for c in _corners(loaded.to_world)]), axis=0)
    np.testing.assert_allclose(extent, [0.02, 0.02, 0.02])


def _corners(to_world: np.ndarray) -> np.ndarray:
    c = np.array([[x, y, z, 1.0] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)])
    return (c @ to_world.T)[:, :3]


def test_framing_distance_closed_form() -> None:
    """Cube [-1, 1]^3 seen along +z with a 90 degree square view: the near corners (z = 1, |x| = |y| = 1) need
    D = 1 + 1 / tan(45 deg) = 2, times the 10 % margin; a 2:1 image halves the x term; a stereo eye offset adds to x."""
    from volren.plan.views import framing_distance

    corners = _corners(np.eye(4))
    args = (corners, (0, 0, 0), np.array([0.0, 0.0, 1.0]), (0, 1, 0), 90.0)
    assert framing_distance(*args, 1.0) == pytest.approx(2.2)
    assert framing_distance(*args, 2.0) == pytest.approx(2.2)  # y now decides: 1 + 1 / 1
    assert framing_distance(*args, 1.0, eye_offset=0.5) == pytest.approx(1.1 * 2.5)
    assert framing_distance(corners * 3 + 7, (7, 7, 7), *args[2:], 1.0) == pytest.approx(6.6)


def test_cli_frames_an_anisotropic_sphere_round_and_centred(tmp_path: Path) -> None:
    """An NRRD sphere (r = 12 mm) at 0.5 x 1 x 2 mm voxels, its centre far from the origin, rendered with the default
    camera: the silhouette sits in the middle of the frame and is round (a grid squashed into a cube would show an
    ellipse of axis ratio 2 here)."""
    import nrrd

    from volren.cli import main

    spacing = np.array([0.5, 1.0, 2.0])
    shape = (16, 30, 60)  # z, y, x: 32 x 30 x 30 mm
    origin = np.array([400.0, 300.0, -900.0]) - spacing * (np.array(shape[::-1]) - 1) / 2
    data = sphere(shape, lambda ijk: origin + ijk * spacing - [400.0, 300.0, -900.0])
    nrrd.write(str(tmp_path / "s.nrrd"), data, {"space": "LPS", "space directions": np.diag(spacing),
                                                "space origin": origin}, index_order="C")
    out = tmp_path / "out"
    assert main(["render", "--volume", str(tmp_path / "s.nrrd"), "--views", "mono", "--width", "48", "--height", "48",
                 "--density-scale", "2000", "--samples", "64", "--light-grid", "16", "--device", "cpu",
                 "--save-linear", "--out", str(out)]) == 0
    alpha = np.load(out / "view0.npy")[..., 3]
    rows, cols = np.nonzero(alpha > 0.5)
    assert 8 <= cols.max() - cols.min() + 1 <= 40
    assert abs((cols.max() - cols.min()) - (rows.max() - rows.min())) <= 2
    assert abs((cols.max() + cols.min()) / 2 - 23.5) <= 1.5 and abs((rows.max() + rows.min()) / 2 - 23.5) <= 1.5


def test_nvdb_voxel_size_and_origin_place_the_grid(tmp_path: Path) -> None:
    """A 2 x 3 x 4 grid at 0.5 x 0.25 x 2 mm whose voxel (0, 0, 0) sits at (1, 2, 3) mm: the world box starts at
    (0.75, 1.875, 2) mm and spans n voxels of that size; --units m scales it by 1000; --spacing replaces it
    (centred); the identity map Warp writes by default is no placement (cubic voxels, longest side 2 m)."""
    import warp as wp

    from volren.device import init_warp

    init_warp()
    xyz = np.ones((2, 3, 4), np.float32)
    wp.Volume.load_from_numpy(xyz, min_world=(1.0, 2.0, 3.0), voxel_size=(0.5, 0.25, 2.0),
                              device="cpu").save_to_nvdb(str(tmp_path / "p.nvdb"))
    loaded = load_volume(tmp_path / "p.nvdb")
    n = np.array(loaded.density.shape[::-1])  # Warp activates whole 8^3 leaves: the dense copy is the leaf
    np.testing.assert_array_equal(loaded.density[:4, :3, :2], 1)
    corners = loaded.corners_world
    np.testing.assert_allclose(corners.min(axis=0), [0.75e-3, 1.875e-3, 2e-3], rtol=1e-6)
    np.testing.assert_allclose(corners.max(axis=0), [0.75e-3, 1.875e-3, 2e-3] + n * [0.5e-3, 0.25e-3, 2e-3], rtol=1e-6)
    np.testing.assert_allclose(load_volume(tmp_path / "p.nvdb", units="m").corners_world, corners * 1000, rtol=1e-6)
    m = load_volume(tmp_path / "p.nvdb", spacing=(1, 1, 1)).to_world
    np.testing.assert_allclose(m[:3, :3], np.diag(n * 0.5e-3), rtol=1e-12)
    np.testing.assert_allclose(m[:3, 3], 0, atol=1e-15)
    wp.Volume.load_from_numpy(xyz, device="cpu").save_to_nvdb(str(tmp_path / "i.nvdb"))
    np.testing.assert_allclose(load_volume(tmp_path / "i.nvdb").to_world, np.eye(4), atol=1e-15)  # one 8^3 leaf


def test_imagej_tiff_spacing_places_the_stack(tmp_path: Path) -> None:
    """An ImageJ stack of 7 x 6 x 5 voxels at 0.5 x 0.25 x 2 um is a 3.5 x 1.5 x 10 um box centred on the origin;
    --units mm overrides the stated micron; --spacing replaces the stored size; an ImageJ stack with nothing set is
    unplaced; a zero resolution is refused."""
    import tifffile

    a = np.zeros((5, 6, 7), np.uint16)
    tifffile.imwrite(tmp_path / "s.tif", a, imagej=True, resolution=(1 / 0.5, 1 / 0.25),
                     metadata={"spacing": 2.0, "unit": "um"})
    corners = load_volume(tmp_path / "s.tif").corners_world
    np.testing.assert_allclose(corners.max(axis=0), [1.75e-6, 0.75e-6, 5e-6], rtol=1e-12)
    np.testing.assert_allclose(corners.min(axis=0), [-1.75e-6, -0.75e-6, -5e-6], rtol=1e-12)
    np.testing.assert_allclose(load_volume(tmp_path / "s.tif", units="mm").corners_world, corners * 1000, rtol=1e-12)
    m = load_volume(tmp_path / "s.tif", spacing=(1, 1, 1), units="m").to_world
    np.testing.assert_allclose(m[:3, :3], np.diag([3.5, 3.0, 2.5]))
    tifffile.imwrite(tmp_path / "micron.tif", a, imagej=True, metadata={"spacing": 3.0, "unit": "micron"})
    np.testing.assert_allclose(load_volume(tmp_path / "micron.tif").to_world[:3, :3],
                               np.diag([3.5e-6, 3e-6, 7.5e-6]), rtol=1e-12)
    tifffile.imwrite(tmp_path / "mm.tif", a, imagej=True, metadata={"spacing": 3.0})  # no unit: millimetres
    np.testing.assert_allclose(load_volume(tmp_path / "mm.tif").to_world[2, 2], 7.5e-3, rtol=1e-12)
    tifffile.imwrite(tmp_path / "bare.tif", a, imagej=True)
    np.testing.assert_allclose(load_volume(tmp_path / "bare.tif").to_world[:3, :3], np.diag([1.0, 6 / 7, 5 / 7]))
    tifffile.imwrite(tmp_path / "zero.tif", a, imagej=True, metadata={"spacing": 0.0, "unit": "um"})
    with pytest.raises(VolrenError, match=r"zero\.tif: the ImageJ voxel size .* is not three positive numbers"):
        load_volume(tmp_path / "zero.tif")


def test_nvdb_rotated_map_follows_warp(tmp_path: Path) -> None:
    """A map that swaps axes (M = [[0, 1, 0], [2, 0, 0], [0, 0, 3]], written into the file's Map) places index +x
    along world +y, as Warp's own volume_index_to_world does: world = M (i, j, k), row-major."""
    import struct

    import warp as wp

    from volren.device import init_warp

    init_warp()
    wp.Volume.load_from_numpy(np.ones((2, 2, 2), np.float32), device="cpu").save_to_nvdb(str(tmp_path / "r.nvdb"))
    data = bytearray((tmp_path / "r.nvdb").read_bytes())
    matrix = np.array([[0.0, 1.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 3.0]])
    for fmt in ("<9f", "<9d"):  # Map.mMatF and Map.mMatD: the first identity matrix of each precision
        at = data.find(struct.pack(fmt, *np.eye(3).ravel()))
        data[at : at + struct.calcsize(fmt)] = struct.pack(fmt, *matrix.ravel())
    (tmp_path / "r.nvdb").write_bytes(bytes(data))
    loaded = load_volume(tmp_path / "r.nvdb", units="m")
    n = np.array(loaded.density.shape[::-1])
    np.testing.assert_allclose(loaded.to_world[:3, :3], matrix * n / 2)


def _render_alpha(volume: Path, out: Path, *extra: str) -> np.ndarray:
    """The default camera's mono view of ``volume`` (``volren render`` defaults but a 64x64 image and a light
    march), its alpha."""
    from volren.cli import main

    assert main(["render", "--volume", str(volume), "--views", "mono", "--width", "64", "--height", "64",
                 "--samples", "96", "--light-samples", "8", "--light-grid", "16", "--device", "cpu", "--save-linear",
                 "--out", str(out), *extra]) == 0
    return np.load(out / "view0.npy")[..., 3]


def _marker_stack(pages: int = 16) -> np.ndarray:
    """uint8 pages [page, row, column], 64x64: a 5x5 marker about row 5, column 54 (the page's top right) on every
    page, and one brighter voxel at page 2, row 5, column 54."""
    stack = np.zeros((pages, 64, 64), np.uint8)
    stack[:, 3:8, 52:57] = 200
    stack[2, 5, 54] = 255
    return stack


def test_tiff_page_row_zero_renders_at_the_top(tmp_path: Path) -> None:
    """Issue 21.6: a marker at the top right of the page image (row 5, column 54) shows at the top right with the
    default camera (it rendered at the bottom right). The stack turns upright by a half turn about x, so page 0 sits
    in front (z > 0), as napari and Fiji show a stack."""
    import tifffile

    tifffile.imwrite(tmp_path / "m.tif", _marker_stack())
    alpha = _render_alpha(tmp_path / "m.tif", tmp_path / "out", "--density-scale", "400")
    rows, cols = np.nonzero(alpha > 0.5)
    assert len(rows) > 4
    assert rows.max() < 20 and cols.min() > 44, (rows.min(), rows.max(), cols.min(), cols.max())
    loaded = load_volume(tmp_path / "m.tif")  # unplaced: cubic voxels of 2 / 64 m, centred
    step = 2 / 64
    marker = np.array([[(54.5 - 32) * step, (32 - 5.5) * step, (8 - 2.5) * step]])  # page 2 of 16: in front
    assert density_at(loaded, marker) == 1.0
    for mirrored in ([1, -1, 1], [1, 1, -1]):  # the marker voxel is not where a flip of one axis would put it
        assert density_at(loaded, marker * mirrored) < 1.0


def test_imagej_tiff_spacing_and_page_order_place_the_marker(tmp_path: Path) -> None:
    """ImageJ voxels of 0.5 x 0.25 x 2 um: the marker voxel (page 2, row 5, column 54 of 16 pages) lands at
    ((54.5 - 32) * 0.5, (32 - 5.5) * 0.25, (8 - 2.5) * 2) um, page 0 in front, rows down; --spacing replaces the
    voxel size the same way."""
    import tifffile

    tifffile.imwrite(tmp_path / "s.tif", _marker_stack(), imagej=True, resolution=(1 / 0.5, 1 / 0.25),
                     metadata={"spacing": 2.0, "unit": "um"})
    loaded = load_volume(tmp_path / "s.tif")
    marker = np.array([[(54.5 - 32) * 0.5e-6, (32 - 5.5) * 0.25e-6, (8 - 2.5) * 2e-6]])
    assert density_at(loaded, marker) == 1.0
    assert density_at(loaded, marker * [1, -1, 1]) == 0.0 and density_at(loaded, marker * [1, 1, -1]) < 1.0
    replaced = load_volume(tmp_path / "s.tif", spacing=(1, 1, 3), units="mm")
    assert density_at(replaced, np.array([[22.5e-3, 26.5e-3, 16.5e-3]])) == 1.0


def test_twelve_bit_uint16_renders_as_its_float_twin(tmp_path: Path) -> None:
    """Issue 21.6: 12-bit data in uint16 (0..4095) maps by its bit depth, density = v / 4095 (max 1.0), and renders
    exactly as the same data as float v / 4095 does (it was divided by 65535: 16x thinner, nearly black); stats.json
    says the mapping. 8-bit data keeps v / 255, 10-bit v / 1023; DICOM's BitsStored is used where stated."""
    import json

    from volren.data.grid import Grid
    from volren.data.loaders import _normalise

    z, y, x = np.mgrid[0:24, 0:24, 0:24] / 11.5 - 1
    ct = np.clip(4400 * (1 - 1.5 * (x**2 + y**2 + z**2)), 0, 4095).round().astype(np.uint16)
    assert ct.max() == 4095
    np.save(tmp_path / "u16.npy", ct)
    np.save(tmp_path / "f32.npy", ct.astype(np.float32) / 4095)
    loaded = load_volume(tmp_path / "u16.npy")
    assert loaded.density.max() == 1.0 and loaded.value_range == (0.0, 4095.0) and not loaded.hounsfield
    assert loaded.value_mapping.to_dict() == {"source": "uint16", "range": [0.0, 4095.0], "units": "raw"}
    alpha = _render_alpha(tmp_path / "u16.npy", tmp_path / "u16", "--density-scale", "2")
    np.testing.assert_allclose(alpha, _render_alpha(tmp_path / "f32.npy", tmp_path / "f32", "--density-scale", "2"),
                               rtol=0, atol=1e-6)
    np.save(tmp_path / "old.npy", ct.astype(np.float32) / 65535)  # what the loader made of it before
    old = _render_alpha(tmp_path / "old.npy", tmp_path / "old", "--density-scale", "2")
    assert alpha.max() > 0.8 and alpha.mean() > 5 * old.mean(), (alpha.max(), alpha.mean(), old.mean())  # 9x
    stats = json.loads((tmp_path / "u16" / "stats.json").read_text())
    assert stats["value_mapping"] == {"source": "uint16", "range": [0.0, 4095.0], "units": "raw"}
    assert json.loads((tmp_path / "f32" / "stats.json").read_text())["value_mapping"] == {
        "source": "float32", "range": None, "units": "raw"}
    for values, bits, top in (([0, 51], None, 255), ([3, 700], None, 1023), ([0, 700], 12, 4095),
                              ([0, 70000], None, 131071)):
        data = np.array(values, np.uint32 if max(values) > 65535 else np.uint16)
        out, value_range = _normalise(Grid(data, bits_stored=bits))
        assert value_range == (0.0, top)
        np.testing.assert_allclose(out, data / top, rtol=1e-6)


def test_unsigned_nifti_ct_with_scl_inter_keeps_hounsfield_units(tmp_path: Path) -> None:
    """A uint16 NIfTI CT storing HU + 1024 (scl_inter -1024): the loader applies the rescale, so value_range is in
    HU (-1000..1000) and the ct presets classify it (as a signed CT)."""
    import nibabel as nib

    hu = np.full((6, 5, 4), -1000.0)
    hu[2:4, 1:4, 1:3] = 1000.0
    image = nib.Nifti1Image(np.ascontiguousarray((hu + 1024).astype(np.uint16).transpose(2, 1, 0)), np.eye(4))
    image.header.set_slope_inter(1.0, -1024.0)
    nib.save(image, tmp_path / "ct.nii.gz")
    loaded = load_volume(tmp_path / "ct.nii.gz")
    assert loaded.value_range == (-1000.0, 1000.0) and loaded.hounsfield
    assert loaded.value_mapping.to_dict() == {"source": "uint16", "range": [-1000.0, 1000.0], "units": "HU"}
    np.testing.assert_array_equal(loaded.density, (hu + 1000) / 2000)
