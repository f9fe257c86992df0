"""OpenVDB double grids (issue 45 item 3): a C++ simulation's ``DoubleGrid`` reads as float32, and a refusal offers
as ``--grid`` choices only grids that read. The files in tests/data/openvdb/ were written by OpenVDB 10's C++ library
(Debian's pyopenvdb wraps no DoubleGrid) from the arrays of tests/vdb_double_grids.py."""

from __future__ import annotations

import re

import numpy as np
import pytest

import vdb_double_grids as grids
from volren.data.loaders import load_volume
from volren.errors import VolrenError

SIM, CHOICES = grids.FOLDER / "sim.vdb", grids.FOLDER / "choices.vdb"


def _world(loaded, zyx) -> np.ndarray:
    """World position of dense voxel ``zyx``'s centre through ``to_world`` (local = -1 + (i + 0.5) * 2 / n)."""
    n = np.array(loaded.density.shape[::-1], dtype=float)
    local = -1.0 + (np.array(zyx[::-1], dtype=float) + 0.5) * 2.0 / n
    return (loaded.to_world @ np.array([*local, 1.0]))[:3]


def _types(path) -> list[str]:
    import tinyvdb

    with tinyvdb.open(str(path)) as f:
        f.read_grids()
        return [f.grid_type_name(i) for i in range(f.grid_count)]


def test_double_grid_reads_as_float32_values_tiles_and_placement():
    assert _types(SIM) == ["Tree_double_5_4_3"] * 2  # what OpenVDB wrote: doubles, as C++ simulations do
    loaded = load_volume(SIM)
    assert loaded.density.dtype == np.float32 and loaded.density.shape == grids.SHAPE
    np.testing.assert_array_equal(loaded.density.to_dense(), grids.DENSITY.astype(np.float32))  # leaves and tiles (0.5)
    assert not np.array_equal(loaded.density.to_dense().astype(np.float64), grids.DENSITY)  # rounded from real doubles
    np.testing.assert_allclose(loaded.density.to_dense(), grids.DENSITY, rtol=1e-7, atol=0)
    assert loaded.density.to_dense()[grids.MARKER] == 7.0 and np.count_nonzero(loaded.density.to_dense() == 7.0) == 1
    marker = np.array(grids.SCALE) * (np.array(grids.IJK) + grids.MARKER[::-1]) + grids.CENTRED
    np.testing.assert_allclose(_world(loaded, grids.MARKER), marker, atol=1e-12)
    assert loaded.value_range is None  # floats are densities as they are


def test_double_grid_tiles_are_read_at_double_width():
    """The constant interior's two 8^3 blocks are tiles of two lower internal nodes: their values (and the inactive
    values before them) are 8 bytes wide; reading them as 4 would misplace everything after."""
    import tinyvdb

    with tinyvdb.open(str(SIM)) as f:
        f.read_grids()
        tree = f.grid(0).tree
        nodes = [tree.node(i) for i in range(tree.num_nodes)]
        assert sum(n.active_voxel_count for n in nodes if n.level == 2) == 2  # two active 8^3 tiles
        assert {len(n.data) for n in nodes if n.level == 3} == {8 * 512}  # tinyvdb's leaves: float64
    density = load_volume(SIM).density.to_dense()
    np.testing.assert_array_equal(density[5:13, 3:11, 4:20], 0.5)


def test_double_emission_grid_lines_up():
    loaded = load_volume(SIM, emission_grid="temperature")
    np.testing.assert_array_equal(loaded.emission_source.to_dense(), grids.TEMPERATURE.astype(np.float32))  # kelvin
    temperature = load_volume(SIM, grid="temperature").density.to_dense()
    np.testing.assert_array_equal(temperature, grids.TEMPERATURE.astype(np.float32))


def test_every_grid_offered_as_a_choice_reads():
    """choices.vdb: heat (double), flame (float), count (int32), none named density. The refusal offers heat and
    flame, never count, and each offered name then loads with its values."""
    with pytest.raises(VolrenError) as err:
        load_volume(CHOICES)
    message = str(err.value)
    assert "\n" not in message and str(CHOICES) in message
    offered = re.fullmatch(r".*several scalar grids and none named 'density'; pick one with grid=NAME "
                           r"\(CLI: --grid NAME\): (.*)", message).group(1)
    assert offered == "heat (double), flame (float)"
    expected = {"heat": grids.HEAT, "flame": grids.FLAME}
    for name in re.findall(r"(\w+) \(\w+\)", offered):
        got = load_volume(CHOICES, grid=name).density.to_dense()
        np.testing.assert_array_equal(got, expected[name].astype(np.float32))
    with pytest.raises(VolrenError, match=r"grid 'count' is of type Tree_int32_5_4_3; grid= \(CLI: --grid\) needs a "
                       r"scalar float or double grid: pick one of heat \(double\), flame \(float\)$"):
        load_volume(CHOICES, grid="count")
    with pytest.raises(VolrenError, match=r"no grid named 'density' \(grid=, CLI: --grid\); pick one of heat "
                       r"\(double\), flame \(float\); its other grids, count \(int32\), are not scalar float or "
                       r"double grids$"):
        load_volume(CHOICES, grid="density")


@pytest.mark.parametrize("name, fragment", [
    ("half-double.vdb", "grid 'density' is a double grid saved as half precision, which tinyvdb cannot decode"),
    ("huge.vdb", "grid 'density' (double) holds 1 value(s) beyond the range of float32"),
])
def test_double_grids_volren_cannot_read_are_refused_saying_why(name, fragment):
    with pytest.raises(VolrenError) as err:
        load_volume(grids.FOLDER / name)
    assert fragment in str(err.value) and str(grids.FOLDER / name) in str(err.value) and "\n" not in str(err.value)


def test_cli_renders_a_double_grid_like_the_float32_npy(tmp_path, capfd):
    """``volren render --volume sim.vdb`` equals the same values as float32 .npy placed by --spacing; the CLI's
    refusal for choices.vdb names only readable grids."""
    from test_cli import _linear_render, render_error

    np.save(tmp_path / "density.npy", grids.DENSITY.astype(np.float32))
    scale = ("--density-scale", "0.5")
    reference = _linear_render(capfd, tmp_path / "npy", tmp_path / "density.npy", "--spacing", "0.5,0.25,2",
                               "--units", "m", *scale)
    assert 0.05 < reference[..., 3].max() < 0.999
    image = _linear_render(capfd, tmp_path / "vdb", SIM, *scale)
    np.testing.assert_allclose(image, reference, rtol=0, atol=1e-6)
    line = render_error(capfd, tmp_path, ["--volume", CHOICES], "choices.vdb", "--grid NAME): heat (double), "
                        "flame (float)")
    assert "count" not in line
