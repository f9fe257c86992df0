"""OpenVDB ``.vdb`` files through tinyvdb (issue 21 item 1): files written by OpenVDB itself (Debian's pyopenvdb
under the system Python), compared with the numpy arrays they were written from."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from conftest import DEVICE, axis_camera, scene_of
from volren.bench.load import SYSTEM_PYTHON, openvdb_available, write_with_openvdb
from volren.data.loaders import load_volume
from volren.data.vdb import read_vdb_grid_like
from volren.errors import VolrenError
from volren.render import METHODS
from volren.scene import Volume

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
PRUNED = np.zeros((40, 40, 48), np.float32)
PRUNED[4:28, 4:28, 4:36] = 0.5  # a thick smoke's constant interior: OpenVDB stores its whole 8^3 blocks as tiles
PRUNED[8, 14, 14] = 0.9  # one whole block of the interior (index x 0-7, y 16-23, z 8-15) stays a leaf
PRUNED[32:, 32:, 40:] = RNG.uniform(0.1, 1.0, (8, 8, 8))  # a far corner: background between it and the interior
PRUNED_IJK = (-12, 5, 3)
"""x from -12: the interior's tiles lie in two lower internal nodes (x < 0 and x >= 0)"""
INACTIVE_TILES = [((-128, 0, 0), (-121, 7, 7), 5.0, False), ((-120, 0, 0), (-113, 7, 7), 6.0, False),
                  ((-112, 0, 0), (-105, 7, 7), 7.0, False), ((64, 64, 64), (71, 71, 71), 5.0, False)]
"""inactive 8^3 tiles outside the active box, in the lower nodes that hold the interior's tiles: three distinct
inactive values (plus the background) make OpenVDB store all 4096 tile values of one node (metadata
NO_MASK_AND_ALL_VALS), one value the active ones and a selection mask"""
COARSE = np.zeros((128, 128, 136), np.float32)
COARSE[:, :, 8:] = 2.0  # an upper internal node's 128^3 tile (index x 128-255), filled by grid.fill
COARSE[:8, :8, :8] = RNG.uniform(0.1, 1.0, (8, 8, 8))  # a leaf at index x 120-127
FLOOR = np.full((40, 40, 40), 300.0, np.float32)
FLOOR[12:20, 14:30, 9:17] = 300.0 + 1500.0 * RNG.uniform(0.0, 1.0, (8, 16, 8))
"""a temperature grid: an ambient 300 K floor (tiles wherever a whole 8^3 block is at the floor) and a hot core"""
SMOKE = RNG.uniform(0.1, 1.0, (16, 16, 16)).astype(np.float32)
SMOKE_IJK = (-8, 200, 300)
"""x -8 to 7: across two root tiles, an inactive and an active one"""
AMBIENT = [((0, 0, 0), (4095, 4095, 4095), 300.0, True), ((4096, 0, 0), (8191, 4095, 4095), 1200.0, True),
           ((-4096, 0, 0), (-1, 4095, 4095), 70.0, False)]
"""a temperature grid of root tiles only: 300 K over index x 0-4095 and 1200 K over 4096-8191 (4096^3 each), beside
an inactive one (its value not the background 0; inactive voxels read as the background)"""


FLAME_IJK = (13, 5, 3)
"""file index (x, y, z) of the smoke's first voxel: its active box is index x 13-35, y 5-22, z 3-22, which the
reader widens to whole leaves, x 8-39, y 0-23, z 0-23 (4 x 3 x 3 blocks)"""
FLAME = np.random.default_rng(47).uniform(0.2, 1.0, (20, 18, 23)).astype(np.float32)
CANVAS_IJK = (-16, -16, -16)
"""file index of element [0, 0, 0] of the temperature canvases below, which reach index 47 / 31 / 31 (x / y / z)"""


def _canvas(*pieces) -> np.ndarray:
    """A temperature grid as float32 ``[z, y, x]`` over index x -16-47, y -16-31, z -16-31: each piece
    ``(lo, hi, values)`` (inclusive index (x, y, z); a constant, or random in [1000, 1800]) written into zeros
    (inactive: the background). A constant 8^3 block is stored as a tile, the rest as leaves."""
    out, rng = np.zeros((48, 48, 64), np.float32), np.random.default_rng(48)
    for lo, hi, value in pieces:
        box = tuple(slice(a - o, b - o + 1) for a, b, o in zip(lo[::-1], hi[::-1], CANVAS_IJK[::-1], strict=True))
        out[box] = value if value is not None else rng.uniform(1000.0, 1800.0, out[box].shape)
    return out


BELOW = _canvas(
    ((-16, 8, 8), (-9, 15, 15), 2000.0),  # a tile 3 blocks below the widened box in x (block -3)
    ((2, 9, 9), (6, 14, 14), None),  # a leaf at index x 0-7, one block below in x (block -1: the last, x 32-39)
    ((17, -6, 10), (22, -2, 13), None),  # a leaf one block below in y
    ((24, 8, -8), (31, 15, -1), 1800.0),  # a tile one block below in z
    ((9, 2, 4), (15, 9, 9), None),  # a leaf inside the widened box, partly below the active box: x 13-15 overlap
    ((8, 16, 16), (15, 23, 23), 900.0),  # a tile there, likewise
)
"""fire at and below the smoke's low corner: only what lies in the smoke's box (x >= 13) may read hot"""
ABOVE = _canvas(
    ((40, 8, 8), (47, 15, 15), 2000.0),  # a tile one block above the widened box in x
    ((33, 10, 15), (38, 20, 21), None),  # leaves across the high corner x 35: x 33-35 overlap
    ((16, 23, 8), (23, 30, 12), None),  # leaves from y 23 (the box's last row is 22) to 30
    ((24, 8, 24), (31, 15, 31), 1500.0),  # a tile one block above in z
)
"""fire at and above the smoke's high corner"""
FAR_BELOW = [((-128, 0, 0), (-1, 127, 127), 1500.0, True)]
"""a 128^3 tile of an upper internal node just below the smoke's widened box in x (it ends at x -1, the box starts
at x 8), level with it in y and z: a temperature grid with nothing in the smoke's box"""


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
        "pruned.vdb": [{"name": "density", "array": PRUNED, "ijk": PRUNED_IJK, "matrix": _matrix(),
                        "fills": INACTIVE_TILES}],
        "pruned-half.vdb": [{"name": "density", "array": PRUNED, "ijk": PRUNED_IJK, "half": True}],
        "coarse.vdb": [{"name": "density", "array": COARSE[:, :, :8], "ijk": (120, 0, 0),
                        "fills": [((128, 0, 0), (255, 127, 127), 2.0, True)]}],
        "floor.vdb": [{"name": "temperature", "array": FLOOR}],
        "ambient.vdb": [{"name": "density", "array": SMOKE, "ijk": SMOKE_IJK},
                        {"name": "temperature", "array": None, "fills": AMBIENT}],
        "flame.vdb": [{"name": "density", "array": FLAME, "ijk": FLAME_IJK},
                      {"name": "below", "array": BELOW, "ijk": CANVAS_IJK},
                      {"name": "above", "array": ABOVE, "ijk": CANVAS_IJK},
                      {"name": "far-below", "array": None, "fills": FAR_BELOW}],
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
    np.testing.assert_array_equal(loaded.density.to_dense(), DENSITY)
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
    np.testing.assert_array_equal(load_volume(vdb_dir / "two.vdb", grid="temperature").density.to_dense(), TEMPERATURE)
    np.testing.assert_array_equal(load_volume(vdb_dir / "smoke.vdb").density.to_dense(), DENSITY)  # the only float grid
    with pytest.raises(VolrenError, match=r"several scalar grids.*--grid NAME\): heat \(float\), flame \(float\)$"):
        load_volume(vdb_dir / "several.vdb")
    with pytest.raises(VolrenError, match=r"two\.vdb: no grid named 'fuel' \(grid=, CLI: --grid\); pick one of density "
                       r"\(float\), temperature \(float\); its other grids, velocity \(vec3s\), are not scalar"):
        load_volume(vdb_dir / "two.vdb", grid="fuel")
    with pytest.raises(VolrenError, match=r"'velocity' is of type Tree_vec3s.*needs a scalar float or double grid: "
                       r"pick one of density \(float\), temperature \(float\)$"):
        load_volume(vdb_dir / "two.vdb", grid="velocity")
    with pytest.raises(VolrenError, match=r"apply to \.vdb only \(CLI: --grid"):
        load_volume(vdb_dir / "nothing.npy", grid="density")


def test_a_grid_of_hundreds_of_leaves_reads_every_voxel(vdb_dir):
    loaded = load_volume(vdb_dir / "many.vdb")
    np.testing.assert_array_equal(loaded.density.to_dense(), MANY)
    corner = np.array(SCALE) * np.array([100 + 63, -20 + 35, 3 + 39]) + TRANSLATION
    np.testing.assert_allclose(_world(loaded, (39, 35, 63)), corner, atol=1e-12)


def test_half_precision_reads_as_float32(vdb_dir):
    loaded = load_volume(vdb_dir / "half.vdb")
    assert loaded.density.dtype == np.float32
    np.testing.assert_array_equal(loaded.density.to_dense(), DENSITY.astype(np.float16).astype(np.float32))
    assert not np.array_equal(loaded.density.to_dense(), DENSITY)  # it really was stored as half


def test_openvdb_wrote_blosc_and_zip_reads_the_same(vdb_dir, tmp_path):
    import tinyvdb

    with tinyvdb.open(str(vdb_dir / "two.vdb")) as f:
        f.read_grids()
        assert f.grid(0).metadata["file_compression"].startswith("blosc")
        (tmp_path / "zip.vdb").write_bytes(f.to_bytes(compression=tinyvdb.COMPRESS_ZIP, level=5))
    np.testing.assert_array_equal(load_volume(tmp_path / "zip.vdb").density.to_dense(), DENSITY)


def test_sparse_grid_densified_over_its_active_box(vdb_dir):
    nz = np.nonzero(SPARSE)
    lo, hi = [int(a.min()) for a in nz], [int(a.max()) for a in nz]
    loaded = load_volume(vdb_dir / "sparse.vdb")
    crop = SPARSE[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1, lo[2]:hi[2] + 1]
    np.testing.assert_array_equal(loaded.density.to_dense(), crop)
    assert loaded.density.shape != SPARSE.shape
    marker = np.argwhere(loaded.density.to_dense() == 7.0)[0]
    np.testing.assert_allclose(_world(loaded, marker), 0.1 * np.array([-8 + 6, 4 + 9, 0 + 10]) + TRANSLATION,
                               atol=1e-12)


def test_page_table_check_refuses_before_allocating(vdb_dir, monkeypatch):
    import volren.data.vdb as vdb

    monkeypatch.setattr(vdb, "MAX_TABLE_BRICKS", 0)
    with pytest.raises(VolrenError, match=r"two\.vdb: the active box of 9x5x7 voxels needs 1 bricks' page table"):
        load_volume(vdb_dir / "two.vdb")


@pytest.mark.parametrize("name, fragment", [("empty.vdb", "grid 'density' has no active voxels"),
                                            ("truncated.vdb", "not a readable OpenVDB file, truncated or corrupt")])
def test_empty_and_truncated_files_are_one_line_errors(vdb_dir, name, fragment):
    with pytest.raises(VolrenError) as err:
        load_volume(vdb_dir / name)
    assert fragment in str(err.value) and str(vdb_dir / name) in str(err.value) and "\n" not in str(err.value)


def test_emission_grid_lines_up_with_the_density(vdb_dir):
    loaded = load_volume(vdb_dir / "two.vdb", emission_grid="temperature")
    np.testing.assert_array_equal(loaded.density.to_dense(), DENSITY)
    np.testing.assert_array_equal(loaded.emission_source.to_dense(), TEMPERATURE)  # raw (kelvin-like) values
    np.testing.assert_array_equal(read_vdb_grid_like(vdb_dir / "two.vdb", "temperature").to_dense(), TEMPERATURE)
    sparse_box = read_vdb_grid_like(vdb_dir / "sparse.vdb", "density")
    assert sparse_box.shape == load_volume(vdb_dir / "sparse.vdb").density.shape
    with pytest.raises(VolrenError, match=r"'temperature' \(emission_grid=, CLI: --emission-grid\) has another "
                       r"index-to-world transform"):
        load_volume(vdb_dir / "moved.vdb", emission_grid="temperature")
    with pytest.raises(VolrenError, match=r"no grid named 'heat' \(emission_grid=, CLI: --emission-grid\)"):
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


def _tile_counts(path: Path) -> tuple[int, int]:
    """Active tiles of the (upper, lower) internal nodes, as tinyvdb counts them: the fixture really has tiles."""
    import tinyvdb

    with tinyvdb.open(str(path)) as f:
        f.read_grids()
        tree = f.grid(0).tree
        nodes = [tree.node(i) for i in range(tree.num_nodes)]
        return tuple(sum(n.active_voxel_count for n in nodes if n.level == level) for level in (1, 2))


def _active_crop(array: np.ndarray) -> np.ndarray:
    nz = np.nonzero(array)
    return array[tuple(slice(int(a.min()), int(a.max()) + 1) for a in nz)]


@pytest.mark.parametrize("compression", ["blosc", "zip", "zip-active-mask", "none"])
def test_pruned_interior_tiles_read_as_their_value(vdb_dir, tmp_path, compression):
    """A thick smoke whose constant interior OpenVDB stored as 8^3 tiles of the lower internal nodes (their values
    compressed as the grid says) reads exactly as the array written; the inactive tiles beside it add nothing."""
    import tinyvdb

    path = vdb_dir / "pruned.vdb"
    assert _tile_counts(path) == (0, 4 * 2 * 2 - 1)  # the interior's whole 8^3 blocks of index space, but one
    if compression != "blosc":
        flags = {"zip": tinyvdb.COMPRESS_ZIP, "zip-active-mask": tinyvdb.COMPRESS_ZIP | tinyvdb.COMPRESS_ACTIVE_MASK,
                 "none": tinyvdb.COMPRESS_NONE}[compression]
        with tinyvdb.open(str(path)) as f:
            f.read_grids()
            path = tmp_path / f"{compression}.vdb"
            path.write_bytes(f.to_bytes(compression=flags, level=5))
    loaded = load_volume(path)
    np.testing.assert_array_equal(loaded.density.to_dense(), _active_crop(PRUNED))
    lo = np.add(PRUNED_IJK, (4, 4, 4))  # the active box's first voxel (x, y, z)
    np.testing.assert_allclose(_world(loaded, (0, 0, 0)), np.array(SCALE) * lo + TRANSLATION, atol=1e-12)


def test_pruned_half_precision_tiles(vdb_dir):
    loaded = load_volume(vdb_dir / "pruned-half.vdb")
    assert _tile_counts(vdb_dir / "pruned-half.vdb") == (0, 15)
    np.testing.assert_array_equal(loaded.density.to_dense(), _active_crop(PRUNED).astype(np.float16).astype(np.float32))


def test_upper_node_tile_fills_128_cubed(vdb_dir):
    assert _tile_counts(vdb_dir / "coarse.vdb") == (1, 0)
    np.testing.assert_array_equal(load_volume(vdb_dir / "coarse.vdb").density.to_dense(), COARSE)


def test_temperature_floor_tiles(vdb_dir):
    """300 K ambient everywhere but a hot core: the floor's whole 8^3 blocks are tiles, read back exactly."""
    assert _tile_counts(vdb_dir / "floor.vdb")[1] >= 100
    np.testing.assert_array_equal(load_volume(vdb_dir / "floor.vdb").density.to_dense(), FLOOR)


def test_root_tiles_fill_the_density_box_and_their_own_box_is_8192_wide(vdb_dir):
    """Ambient temperature as root tiles (4096^3 each) densified over the smoke's box, which straddles the inactive
    one and an active one; on its own its active box is the two active root tiles, too large to densify."""
    loaded = load_volume(vdb_dir / "ambient.vdb", emission_grid="temperature")
    np.testing.assert_array_equal(loaded.density.to_dense(), SMOKE)
    expected = np.full(SMOKE.shape, 300.0, np.float32)
    expected[:, :, :8] = 0.0  # index x < 0: the inactive root tile
    np.testing.assert_array_equal(loaded.emission_source.to_dense(), expected)
    # on its own: 8192 x 4096 x 4096 voxels in two root tiles, 300 K and 1200 K, as constant bricks but for the one
    # layer whose apron meets the other tile (bricks of x 4080-4096): 256 x 256 of 33.5 M in the pool
    ambient = load_volume(vdb_dir / "ambient.vdb", grid="temperature").density
    assert ambient.shape == (4096, 4096, 8192) and len(ambient.pool) == 256 * 256 and ambient.max() == 1200.0
    assert np.all(ambient.table[:, :, 255] >= 0) and np.all(ambient.table[:, :, :255] < 0)
    assert ambient.read((4000, 7, 4094), (4001, 8, 4098)).tolist() == [[[300.0, 300.0, 1200.0, 1200.0]]]


def _flame_box(canvas: np.ndarray) -> np.ndarray:
    """The canvas over the smoke's active box (index x 13-35, y 5-22, z 3-22)."""
    lo = np.subtract(FLAME_IJK, CANVAS_IJK)[::-1]
    return canvas[tuple(slice(a, a + n) for a, n in zip(lo, FLAME.shape, strict=True))]


def test_fire_outside_the_smoke_box_is_cropped_not_wrapped(vdb_dir):
    """A simulation's temperature grid reaches past the smoke (its leaves, 8^3 tiles and a 128^3 tile below the
    smoke's low corner in x, y and z, and above its high corner): ``--emission-grid`` reads it over the smoke's box
    only, the overlap with its own values and zero (unburnt) everywhere else; nothing outside wraps round to the far
    end of the box (a block index -1 is the last block to numpy)."""
    import tinyvdb

    path = vdb_dir / "flame.vdb"
    with tinyvdb.open(str(path)) as f:  # the fixture holds what it means to: tiles of both sizes
        f.read_grids()
        tiles = {}  # active tiles of the upper and lower internal nodes
        for i in range(f.grid_count):
            tree = f.grid(i).tree
            nodes = [tree.node(j) for j in range(tree.num_nodes)]
            tiles[f.grid(i).name] = [sum(n.active_voxel_count for n in nodes if n.level == k) for k in (1, 2)]
    assert tiles == {"density": [0, 0], "below": [0, 3], "above": [0, 2], "far-below": [1, 0]}
    for name, canvas in (("below", BELOW), ("above", ABOVE)):
        loaded = load_volume(path, emission_grid=name)
        np.testing.assert_array_equal(loaded.density.to_dense(), FLAME)
        expected = _flame_box(canvas)
        assert 0 < np.count_nonzero(expected) < expected.size // 10  # a sliver of the box overlaps the fire
        np.testing.assert_array_equal(loaded.emission_source.to_dense(), expected, err_msg=name)
    assert load_volume(path, emission_grid="far-below").emission_source.max() == 0


def test_fire_below_the_smoke_does_not_glow_on_its_far_side(vdb_dir):
    """The user's picture of that smoke (albedo 0, no lights: only the fire shows) seen along z: the overlap at the
    low-x face glows, the far (high-x) half of the picture is black; with the 128^3 tile below it, all is black."""
    cls, config = METHODS["dssrm"]
    renderer = cls(config(samples=64, light_grid=8), device=DEVICE)
    camera = axis_camera(position=(0.0, 0.0, 20.0), size=(24, 24), fov_y=5.0)  # local x -0.83 to 0.83 at the front
    path = vdb_dir / "flame.vdb"
    for name in ("below", "far-below"):
        loaded = load_volume(path, emission_grid=name)
        fire = Volume(loaded.density, density_scale=1.0, albedo=0.0, emission_grid=loaded.emission_source.to_dense(),
                      temperature_range=(1000.0, 2000.0), emission_scale=5.0)
        image = renderer.render(scene_of(fire), [camera]).images[0]
        assert image[..., 3].min() > 0.5  # the smoke covers the picture
        rgb = image[..., :3].sum(axis=-1)
        assert not rgb[:, 12:].any(), name  # the far half: local x > 0, index x > 24, nothing burns there
        if name == "below":
            assert rgb[:, :3].max() > 0.1  # the overlap, index x 13-15: local x < -0.74
        else:
            assert not rgb.any()
