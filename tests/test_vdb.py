"""OpenVDB ``.vdb`` files through tinyvdb (issue 21 item 1): files written by OpenVDB itself (Debian's pyopenvdb
under the system Python), compared with the numpy arrays they were written from."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from volren.bench.load import SYSTEM_PYTHON, openvdb_available, write_with_openvdb
from volren.data.loaders import load_volume
from volren.data.vdb import read_vdb_grid_like
from volren.errors import VolrenError

SCALE = (0.5, 0.25, 2.0)
"""non-uniform voxel size [m] of the placed grids"""
TRANSLATION = (1.0, 2.0, 3.0)
IJK = (3, -5, 7)
"""file index of dense voxel (0, 0, 0)"""
SHAPE = (7, 5, 9)
"""[z, y, x]"""


if not openvdb_available():
    if os.environ.get("CI") == "true":
        pytest.fail(f"{SYSTEM_PYTHON} cannot import pyopenvdb in CI: .ci/run installs python3-openvdb", pytrace=False)
    pytest.skip(f"{SYSTEM_PYTHON} cannot import pyopenvdb (apt-get install python3-openvdb)", allow_module_level=True)


def _matrix(scale=SCALE, translation=TRANSLATION) -> list[list[float]]:
    """OpenVDB's row-vector index-to-world map: scale on the diagonal, translation in the last row."""
    m = np.diag([*scale, 1.0])
    m[3, :3] = translation
    return m.tolist()


RNG = np.random.default_rng(21)
DENSITY = RNG.uniform(0.1, 1.0, SHAPE).astype(np.float32)
"""no zeros: every voxel active, so the active box is the array"""
TEMPERATURE = (300.0 + 1500.0 * DENSITY).astype(np.float32)
VELOCITY = RNG.normal(size=(*SHAPE, 3)).astype(np.float32)
SPARSE = np.where(RNG.random((24, 20, 16)) < 0.1, RNG.uniform(0.2, 1.0, (24, 20, 16)), 0.0).astype(np.float32)
SPARSE[:3], SPARSE[-2:], SPARSE[:, :4], SPARSE[:, :, -5:] = 0.0, 0.0, 0.0, 0.0  # the active box is a crop
SPARSE[10, 9, 6] = 7.0  # the marker voxel
MANY = RNG.uniform(0.1, 1.0, (40, 36, 64)).astype(np.float32)
"""5 x 5 x 8 leaves and more at an offset that spans two lower internal nodes in x (128 voxels each): tinyvdb 0.9.0's
own densify keeps at most 64 leaves per lower node"""


CENTRED = -np.array(SCALE) * (np.array(IJK) + (np.array(SHAPE[::-1]) - 1) / 2)
"""the translation that centres the grid as ``--spacing 0.5,0.25,2 --units m`` centres a .npy"""


ROTATED = [[0.0, 0.5, 0.0, 0.0], [-0.25, 0.0, 0.0, 0.0], [0.0, 0.0, 2.0, 0.0], [1.0, 2.0, 3.0, 1.0]]
"""an affine map (row vectors): index x -> world +y (0.5 m), index y -> world -x (0.25 m), index z -> world +z"""


def _grid(name, array, **kw):
    return {"name": name, "array": array, "ijk": IJK, "matrix": _matrix(), **kw}


@pytest.fixture(scope="session")
def vdb_dir(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("vdb")
    write_with_openvdb({
        "two.vdb": [_grid("density", DENSITY), _grid("temperature", TEMPERATURE), _grid("velocity", VELOCITY,
                                                                                        vec3=True)],
        "smoke.vdb": [_grid("velocity", VELOCITY, vec3=True), _grid("smoke", DENSITY)],
        "several.vdb": [_grid("heat", TEMPERATURE), _grid("flame", DENSITY)],
        "half.vdb": [_grid("density", DENSITY, half=True)],
        "empty.vdb": [_grid("density", None)],
        "sparse.vdb": [{"name": "density", "array": SPARSE, "ijk": (-8, 4, 0), "matrix": _matrix((0.1,) * 3)}],
        "centred.vdb": [{**_grid("density", DENSITY), "matrix": _matrix(translation=CENTRED)},
                        {**_grid("temperature", TEMPERATURE), "matrix": _matrix(translation=CENTRED)}],
        "rotated.vdb": [{**_grid("density", DENSITY), "matrix": ROTATED}],
        "many.vdb": [{"name": "density", "array": MANY, "ijk": (100, -20, 3), "matrix": _matrix()}],
        "tiles.vdb": [{"name": "density", "array": np.ones((16, 16, 16), np.float32)}],
        "moved.vdb": [_grid("density", DENSITY), {**_grid("temperature", TEMPERATURE), "matrix": _matrix((0.5,) * 3)}],
    }, folder)
    data = (folder / "two.vdb").read_bytes()
    (folder / "truncated.vdb").write_bytes(data[: len(data) // 2])
    return folder


def _world(loaded, zyx) -> np.ndarray:
    """World position of dense voxel ``zyx``'s centre through ``to_world`` (local = -1 + (i + 0.5) * 2 / n)."""
    n = np.array(loaded.density.shape[::-1], dtype=float)
    local = -1.0 + (np.array(zyx[::-1], dtype=float) + 0.5) * 2.0 / n
    return (loaded.to_world @ np.array([*local, 1.0]))[:3]


def test_density_and_placement_match_what_openvdb_wrote(vdb_dir):
    """Exact values; every voxel centre at OpenVDB's world position scale * (ijk + index) + translation [m]."""
    loaded = load_volume(vdb_dir / "two.vdb")
    np.testing.assert_array_equal(loaded.density, DENSITY)
    assert loaded.emission_source is None and loaded.value_range is None
    for zyx in [(0, 0, 0), (6, 4, 8), (2, 3, 5)]:
        expected = np.array(SCALE) * (np.array(IJK) + zyx[::-1]) + TRANSLATION
        np.testing.assert_allclose(_world(loaded, zyx), expected, rtol=0, atol=1e-12)
    mm = load_volume(vdb_dir / "two.vdb", units="mm")
    np.testing.assert_allclose(mm.to_world[:3], loaded.to_world[:3] * 1e-3, rtol=1e-12, atol=0)


def test_affine_transform_rotates_the_grid(vdb_dir):
    loaded = load_volume(vdb_dir / "rotated.vdb")
    for zyx in [(0, 0, 0), (6, 4, 8)]:
        expected = np.array([*(np.array(IJK) + zyx[::-1]), 1.0]) @ np.array(ROTATED)
        np.testing.assert_allclose(_world(loaded, zyx), expected[:3], rtol=0, atol=1e-12)


def test_spacing_replaces_the_vdb_placement_as_for_nvdb(vdb_dir):
    loaded = load_volume(vdb_dir / "two.vdb", spacing=(1.0, 1.0, 1.0), units="m")
    np.testing.assert_allclose(_world(loaded, (0, 0, 0)), -(np.array(SHAPE[::-1]) - 1) / 2, atol=1e-12)


def test_grid_choice(vdb_dir):
    np.testing.assert_array_equal(load_volume(vdb_dir / "two.vdb", grid="temperature").density, TEMPERATURE)
    np.testing.assert_array_equal(load_volume(vdb_dir / "smoke.vdb").density, DENSITY)  # the only float grid
    with pytest.raises(VolrenError, match=r"several float grids.*--grid NAME: heat \(float\), flame \(float\)"):
        load_volume(vdb_dir / "several.vdb")
    with pytest.raises(VolrenError, match=r"two\.vdb: no grid named 'fuel' \(--grid\); the file holds density "
                       r"\(float\), temperature \(float\), velocity \(vec3s\)"):
        load_volume(vdb_dir / "two.vdb", grid="fuel")
    with pytest.raises(VolrenError, match=r"'velocity' is of type Tree_vec3s.*needs a float grid"):
        load_volume(vdb_dir / "two.vdb", grid="velocity")
    with pytest.raises(VolrenError, match=r"apply to \.vdb only \(CLI: --grid"):
        load_volume(vdb_dir / "nothing.npy", grid="density")


def test_a_grid_of_hundreds_of_leaves_reads_every_voxel(vdb_dir):
    loaded = load_volume(vdb_dir / "many.vdb")
    np.testing.assert_array_equal(loaded.density, MANY)
    corner = np.array(SCALE) * np.array([100 + 63, -20 + 35, 3 + 39]) + TRANSLATION
    np.testing.assert_allclose(_world(loaded, (39, 35, 63)), corner, atol=1e-12)


def test_half_precision_reads_as_float32(vdb_dir):
    loaded = load_volume(vdb_dir / "half.vdb")
    assert loaded.density.dtype == np.float32
    np.testing.assert_array_equal(loaded.density, DENSITY.astype(np.float16).astype(np.float32))
    assert not np.array_equal(loaded.density, DENSITY)  # it really was stored as half


def test_openvdb_wrote_blosc_and_zip_reads_the_same(vdb_dir, tmp_path):
    import tinyvdb

    with tinyvdb.open(str(vdb_dir / "two.vdb")) as f:
        f.read_grids()
        assert f.grid(0).metadata["file_compression"].startswith("blosc")
        (tmp_path / "zip.vdb").write_bytes(f.to_bytes(compression=tinyvdb.COMPRESS_ZIP, level=5))
    np.testing.assert_array_equal(load_volume(tmp_path / "zip.vdb").density, DENSITY)


def test_sparse_grid_densified_over_its_active_box(vdb_dir):
    nz = np.nonzero(SPARSE)
    lo, hi = [int(a.min()) for a in nz], [int(a.max()) for a in nz]
    loaded = load_volume(vdb_dir / "sparse.vdb")
    crop = SPARSE[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1, lo[2]:hi[2] + 1]
    np.testing.assert_array_equal(loaded.density, crop)
    assert loaded.density.shape != SPARSE.shape
    marker = np.argwhere(loaded.density == 7.0)[0]
    np.testing.assert_allclose(_world(loaded, marker), 0.1 * np.array([-8 + 6, 4 + 9, 0 + 10]) + TRANSLATION,
                               atol=1e-12)


def test_memory_check_refuses_before_allocating(vdb_dir, monkeypatch):
    import volren.data.vdb as vdb

    monkeypatch.setattr(vdb, "MAX_DENSE_VOXELS", DENSITY.size - 1)
    with pytest.raises(VolrenError, match=r"two\.vdb: a dense copy of 1 grid\(s\) of 9x5x7 voxels is too large"):
        load_volume(vdb_dir / "two.vdb")
    monkeypatch.setattr(vdb, "MAX_DENSE_VOXELS", DENSITY.size)  # the density fits, density + emission does not
    with pytest.raises(VolrenError, match=r"2 grid\(s\)"):
        load_volume(vdb_dir / "two.vdb", emission_grid="temperature")


@pytest.mark.parametrize("name, fragment", [("empty.vdb", "grid 'density' has no active voxels"),
                                            ("tiles.vdb", "has active tiles (constant regions)"),
                                            ("truncated.vdb", "not a readable OpenVDB file, truncated or corrupt")])
def test_empty_and_truncated_files_are_one_line_errors(vdb_dir, name, fragment):
    with pytest.raises(VolrenError) as err:
        load_volume(vdb_dir / name)
    assert fragment in str(err.value) and str(vdb_dir / name) in str(err.value) and "\n" not in str(err.value)


def test_emission_grid_lines_up_with_the_density(vdb_dir):
    loaded = load_volume(vdb_dir / "two.vdb", emission_grid="temperature")
    np.testing.assert_array_equal(loaded.density, DENSITY)
    np.testing.assert_array_equal(loaded.emission_source, TEMPERATURE)  # raw values (kelvin-like), not normalised
    np.testing.assert_array_equal(read_vdb_grid_like(vdb_dir / "two.vdb", "temperature"), TEMPERATURE)
    sparse_box = read_vdb_grid_like(vdb_dir / "sparse.vdb", "density")
    assert sparse_box.shape == load_volume(vdb_dir / "sparse.vdb").density.shape
    with pytest.raises(VolrenError, match=r"'temperature' .--emission-grid. has another index-to-world transform"):
        load_volume(vdb_dir / "moved.vdb", emission_grid="temperature")
    with pytest.raises(VolrenError, match=r"no grid named 'heat' .--emission-grid."):
        load_volume(vdb_dir / "two.vdb", emission_grid="heat")
    with pytest.raises(VolrenError, match=r"apply to \.vdb only"):
        load_volume(vdb_dir / "x.nvdb", emission_grid="temperature")


def test_vdb_renders_like_the_npy_it_was_written_from(vdb_dir, tmp_path, capfd):
    """``volren render --volume f.vdb`` (CPU, 24x16) equals the same density as .npy placed by --spacing."""
    from test_cli import _linear_render

    np.save(tmp_path / "density.npy", DENSITY)
    reference = _linear_render(capfd, tmp_path / "npy", tmp_path / "density.npy", "--spacing", "0.5,0.25,2",
                               "--units", "m")
    assert reference[..., 3].max() > 0.05
    image = _linear_render(capfd, tmp_path / "vdb", vdb_dir / "centred.vdb")
    np.testing.assert_allclose(image, reference, rtol=0, atol=1e-6)
    np.save(tmp_path / "temperature.npy", TEMPERATURE)
    scale = ("--density-scale", str(1 / 1500))  # kelvin as density: 300-1800 would be opaque
    reference = _linear_render(capfd, tmp_path / "npy-t", tmp_path / "temperature.npy", "--spacing", "0.5,0.25,2",
                               "--units", "m", *scale)
    image = _linear_render(capfd, tmp_path / "vdb-t", vdb_dir / "centred.vdb", "--grid", "temperature", *scale)
    np.testing.assert_allclose(image, reference, rtol=0, atol=1e-6)  # --grid reached the loader


@pytest.mark.parametrize("case", ["npy", "scene", "truncated", "unknown"])
def test_cli_refuses_grid_misuse_and_bad_files_in_one_line(vdb_dir, tmp_path, capfd, case):
    from test_cli import render_error

    np.save(tmp_path / "d.npy", DENSITY)
    extra, fragments = {
        "npy": (["--volume", tmp_path / "d.npy", "--grid", "density"], ["d.npy", "--grid", ".vdb only"]),
        "scene": (["--scene", "smoke", "--grid", "density"], ["--grid", "no --volume"]),
        "truncated": (["--volume", vdb_dir / "truncated.vdb"], ["truncated.vdb", "truncated or corrupt"]),
        "unknown": (["--volume", vdb_dir / "two.vdb", "--grid", "fuel"], ["two.vdb", "'fuel'", "density (float)"]),
    }[case]
    render_error(capfd, tmp_path, extra, *fragments)
