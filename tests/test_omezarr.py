"""OME-Zarr / Zarr volumes (issue 21 item 5, `volren.data.omezarr`): pyramids written by ome-zarr itself, placed by
their coordinate transformations (file x, y, z -> world +x, -y, -z in metres), one level read."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

zarr = pytest.importorskip("zarr")
writer = pytest.importorskip("ome_zarr.writer")

from volren.cli import main  # noqa: E402
from volren.data.loaders import load_volume  # noqa: E402
from volren.errors import VolrenError  # noqa: E402

UM = 1e-6
MARKER = (5, 20, 7)
"""channel 1's marker voxel (z, y, x) at level 0"""
SCALE = (2.0, 0.5, 0.5)
"""[um] z, y, x voxel size: anisotropic, as confocal stacks are"""
TRANSLATION = (10.0, 4.0, -3.0)
"""[um] z, y, x of voxel 0's centre"""


def space_axes(units=("micrometer",) * 3) -> list[dict]:
    return [{"name": "c", "type": "channel"}] + [{"name": n, "type": "space", "unit": u}
                                                  for n, u in zip("zyx", units, strict=True)]


def write_pyramid(path, units=("micrometer",) * 3) -> np.ndarray:
    """Two channels (8, 32, 32), levels 0 and 1 (y, x halved), an explicit scale and translation per level."""
    data = np.zeros((2, 8, 32, 32), np.uint16)
    data[(1, *MARKER)] = 4000
    data[0, 2:4, 2:6, 2:6] = 900
    levels = [data, data[:, :, ::2, ::2]]
    transforms = []
    for lv in range(2):
        scale = [1.0, SCALE[0], SCALE[1] * 2**lv, SCALE[2] * 2**lv]
        # voxel centres: a coarser voxel's centre sits half its growth further (as ome-zarr's own writer does)
        offset = [0.0, TRANSLATION[0]] + [t + (s - s0) / 2 for t, s, s0 in zip(TRANSLATION[1:], scale[2:], SCALE[1:],
                                                                                strict=True)]
        transforms.append([{"type": "scale", "scale": scale}, {"type": "translation", "translation": offset}])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # coordinate_transformations: the only way to translate
        writer.write_multiscale(levels, zarr.open_group(str(path), mode="w"), axes=space_axes(units),
                                coordinate_transformations=transforms)
    return data


def voxel_world(loaded, zyx) -> np.ndarray:
    """World position [m] of voxel (z, y, x) of the loaded grid (DESIGN.md voxel centres)."""
    n = np.array(loaded.density.shape[::-1], dtype=float)
    local = -1 + (np.array(zyx[::-1], dtype=float) + 0.5) * 2 / n
    return (loaded.to_world @ np.r_[local, 1.0])[:3]


def test_marker_lands_at_its_world_position(tmp_path):
    write_pyramid(tmp_path / "p.zarr")
    loaded = load_volume(tmp_path / "p.zarr")
    assert loaded.level == 0 and len(loaded.channels) == 2 and loaded.density.shape == (8, 32, 32)
    marker = tuple(np.argwhere(loaded.channels[1] == 1.0)[0])
    assert marker == MARKER  # channel 1 read as channel 1, voxels not reordered
    z, y, x = (t + i * s for t, i, s in zip(TRANSLATION, MARKER, SCALE, strict=True))
    np.testing.assert_allclose(voxel_world(loaded, MARKER), np.array([x, -y, -z]) * UM, rtol=1e-9, atol=1e-15)
    # the coarser level covers the same box (its translation moves the centres of its bigger voxels)
    coarse = load_volume(tmp_path / "p.zarr", level=1)
    assert coarse.level == 1 and coarse.density.shape == (8, 16, 16)
    np.testing.assert_allclose(coarse.corners_world, loaded.corners_world, rtol=1e-9, atol=1e-15)


def test_units_per_axis_and_the_units_override(tmp_path):
    write_pyramid(tmp_path / "mixed.zarr", units=("millimeter", "micrometer", "micrometer"))
    mixed = load_volume(tmp_path / "mixed.zarr")
    # half-extents x, y, z: 32 x 0.5 um, 32 x 0.5 um, 8 x 2 mm
    np.testing.assert_allclose(np.abs(np.diag(mixed.to_world)[:3]), [8 * UM, 8 * UM, 8e-3], rtol=1e-9)
    write_pyramid(tmp_path / "p.zarr")
    as_mm = load_volume(tmp_path / "p.zarr", units="mm")  # the file's numbers read as millimetres
    np.testing.assert_allclose(as_mm.to_world[:3], load_volume(tmp_path / "p.zarr").to_world[:3] * 1e3, rtol=1e-9)


def test_ngff_04_pyramid_from_write_image_with_its_scaler(tmp_path):
    from ome_zarr.format import FormatV04

    data = np.zeros((2, 8, 32, 32), np.uint16)
    data[0, 4, 8, 16] = 100
    group = zarr.open_group(str(tmp_path / "v4.zarr"), mode="w", zarr_format=2)
    writer.write_image(data, group, axes="czyx", scale_factors=(2, 4), fmt=FormatV04(),
                       scale={"c": 1.0, "z": 2.0, "y": 0.5, "x": 0.5},
                       axes_units={a: "micrometer" for a in "zyx"})
    assert "multiscales" in json.loads((tmp_path / "v4.zarr" / ".zattrs").read_text())  # 0.4: no 'ome' key
    loaded = load_volume(tmp_path / "v4.zarr")
    np.testing.assert_allclose(np.abs(np.diag(loaded.to_world)[:3]), [8 * UM, 8 * UM, 8 * UM], rtol=1e-9)
    assert np.argwhere(loaded.channels[0] == 1.0).tolist() == [[4, 8, 16]]


def test_level_choice_by_budget_and_by_level(tmp_path):
    write_pyramid(tmp_path / "p.zarr")
    level0 = 2 * 8 * 32 * 32 * 4  # float32 bytes, both channels
    assert load_volume(tmp_path / "p.zarr", memory_budget=level0).level == 0
    # stream=False: the finest level that fits (without it, a pyramid over the budget streams: test_stream_channels)
    assert load_volume(tmp_path / "p.zarr", memory_budget=level0 - 1, stream=False).level == 1
    assert load_volume(tmp_path / "p.zarr", memory_budget=level0 - 1, level=0).level == 0  # --level overrides
    with pytest.raises(VolrenError, match="exceeds the memory budget"):
        load_volume(tmp_path / "p.zarr", memory_budget=level0 / 4 - 1, stream=False)
    with pytest.raises(VolrenError, match="levels 0 to 1"):
        load_volume(tmp_path / "p.zarr", level=2)
    np.save(tmp_path / "a.npy", np.zeros((4, 4, 4), np.float32))
    with pytest.raises(VolrenError, match=r"apply to \.zarr only"):
        load_volume(tmp_path / "a.npy", level=0)


def test_plain_zarr_array_reads_as_npy_would(tmp_path):
    data = np.random.default_rng(1).integers(0, 255, (6, 7, 8), dtype=np.uint8)
    zarr.create_array(str(tmp_path / "plain.zarr"), shape=data.shape, dtype=data.dtype)[...] = data
    np.save(tmp_path / "plain.npy", data)
    z, n = load_volume(tmp_path / "plain.zarr"), load_volume(tmp_path / "plain.npy")
    np.testing.assert_array_equal(z.density, n.density)
    np.testing.assert_allclose(z.to_world, n.to_world)


@pytest.mark.parametrize(("edit", "message"), [
    (lambda ms: ms["datasets"][0]["coordinateTransformations"][0].update(scale=[1, 2]), "malformed OME-Zarr"),
    (lambda ms: ms["datasets"][0].pop("coordinateTransformations"), "malformed OME-Zarr"),
    (lambda ms: ms["axes"][1].update(name="t", type="time"), "needs the space axes z, y, x"),
    (lambda ms: ms["axes"][3].update(unit="parsec"), "unknown space unit"),
])
def test_malformed_metadata_is_one_line_naming_the_file(tmp_path, edit, message):
    path = tmp_path / "bad.zarr"
    write_pyramid(path)
    meta = json.loads((path / "zarr.json").read_text())
    edit(meta["attributes"]["ome"]["multiscales"][0])
    (path / "zarr.json").write_text(json.dumps(meta))
    with pytest.raises(VolrenError, match=message) as info:
        load_volume(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_cli_renders_a_level_with_row_0_at_the_top(tmp_path):
    """A 16 um stack in the default stereo pair (its eyes closer than the stack is wide, its near plane closer than
    1 cm): channel 0's block at rows 2-5 (near y = 0) must show in each eye's top half."""
    write_pyramid(tmp_path / "p.zarr")
    out = tmp_path / "out"
    assert main(["render", "--volume", str(tmp_path / "p.zarr"), "--level", "1", "--width", "32", "--height", "32",
                 "--samples", "48", "--channel-opacity", "20", "--out", str(out), "--save-linear"]) == 0
    rows = np.arange(32)
    for eye in ("view0", "view1"):
        green = np.load(out / f"{eye}.npy")[..., 1].sum(axis=1)
        assert green.sum() > 1.0 and (green * rows).sum() / green.sum() < 14


def test_cli_refuses_level_without_a_volume(tmp_path, capsys):
    assert main(["render", "--scene", "cloud", "--level", "1", "--out", str(tmp_path / "o")]) == 2
    assert "there is no --volume" in capsys.readouterr().err


@pytest.mark.parametrize(("flags", "message"), [
    (["--level", "1", "--memory-budget", "0.5"], "--memory-budget chooses a level by its size; --level 1 names the "
     "level, so the budget would do nothing: give one of them"),
    (["--memory-budget", "1e12"], "--memory-budget 1e+12 GiB exceeds this machine's memory ({memory:.1f} GiB): a "
     "level that large could not be read"),
    (["--memory-budget", "0"], "--memory-budget must be a positive number of GiB, got 0"),
])
def test_cli_memory_budget_that_would_do_nothing_is_one_line(tmp_path, capsys, flags, message):
    """--memory-budget beside --level did nothing, and 1e12 GiB was taken as given: one line each, exit 2."""
    from volren.plan.volume import host_memory

    write_pyramid(tmp_path / "p.zarr")
    assert main(["render", "--volume", str(tmp_path / "p.zarr"), *flags, "--out", str(tmp_path / "o")]) == 2
    memory = host_memory()
    assert memory is not None  # Linux and macOS say
    assert capsys.readouterr().err.splitlines() == [f"volren: error: {message.format(memory=memory / 2**30)}"]


def chunked_pyramid(path, density: np.ndarray) -> None:
    """One channel, levels 0 and 1 (every axis halved), chunks of 16^3 voxels: 8 chunks at level 0 for 32^3."""
    levels = [density, density[::2, ::2, ::2]]
    writer.write_multiscale(levels, zarr.open_group(str(path), mode="w"), axes=space_axes()[1:],
                            storage_options={"chunks": (16, 16, 16)})


def test_missing_chunks_are_one_warning_naming_the_store_and_their_count(tmp_path, capsys):
    """An OME-Zarr whose level 0 lost 2 of its 8 chunk files (a copy cut short) read them as zeros with no word;
    now one warning names the store and the count, the render goes on (exit 0). A store whose absent chunks are
    empty by design (zarr writes no chunk that holds only the fill value) gets none; one with no chunk of its level
    is refused."""
    z, y, x = np.mgrid[0:32, 0:32, 0:32].astype(np.float32)
    blob = np.exp(-((x - 16) ** 2 + (y - 16) ** 2 + (z - 16) ** 2) / 120.0)
    args = ["--views", "mono", "--width", "64", "--height", "48", "--samples", "48"]
    chunked_pyramid(tmp_path / "holes.zarr", blob)
    chunks = sorted((tmp_path / "holes.zarr" / "s0" / "c").glob("*/*/*"))
    assert len(chunks) == 8
    for chunk in chunks[:2]:
        chunk.unlink()
    assert main(["render", "--volume", str(tmp_path / "holes.zarr"), *args, "--out", str(tmp_path / "o1")]) == 0
    assert capsys.readouterr().err.splitlines() == [
        f"volren: warning: {tmp_path / 'holes.zarr'}: level 0 is missing 2 of its 8 chunks where level 1 holds data; "
        "zarr reads them as the fill value 0 (holes in the volume)"]
    sparse = np.where(x < 16, 0.0, blob).astype(np.float32)  # half the chunks empty: zarr leaves them out
    chunked_pyramid(tmp_path / "sparse.zarr", sparse)
    assert len(list((tmp_path / "sparse.zarr" / "s0" / "c").glob("*/*/*"))) == 4
    assert main(["render", "--volume", str(tmp_path / "sparse.zarr"), *args, "--out", str(tmp_path / "o2")]) == 0
    assert capsys.readouterr().err == ""
    for chunk in chunks[2:]:
        chunk.unlink()
    assert main(["render", "--volume", str(tmp_path / "holes.zarr"), *args, "--out", str(tmp_path / "o3")]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"volren: error: {tmp_path / 'holes.zarr'}: level 0 has none of its 8 chunks on disk (every voxel would read "
        "as the fill value 0): an incomplete copy?"]


def test_density_validation_by_min_and_max_still_refuses_and_counts():
    """`validate_density` checks a big level by its min and max (two reductions); what it refuses is still counted."""
    from volren.scene import validate_density

    grid = np.zeros((2, 3, 4))
    grid[0, 0, :2] = 1e39  # beyond float32
    with pytest.raises(VolrenError, match="2 value"):
        validate_density(grid)
    grid[0, 0, :2] = -1e-50  # rounds to -0.0 in float32: not negative
    assert validate_density(grid).min() == 0.0
    grid[1, 2, 3] = np.nan
    with pytest.raises(VolrenError, match="1 NaN/Inf"):
        validate_density(grid)


def test_omero_channel_colours_are_the_default_and_the_flag_overrides_them(tmp_path):
    """A file's ``omero`` channel colours (cyan, orange) colour its channels unless --channel-colors is given."""
    path = tmp_path / "p.zarr"
    write_pyramid(path)
    meta = json.loads((path / "zarr.json").read_text())
    meta["attributes"]["ome"]["omero"] = {"channels": [{"color": "00FFFF"}, {"color": "FF8000"}]}
    (path / "zarr.json").write_text(json.dumps(meta))
    assert load_volume(path).channel_colors == ((0.0, 1.0, 1.0), (1.0, 128 / 255, 0.0))
    from volren.plan import render_parser
    from volren.plan.scene import scene_from_args

    for flags, blue0, green1 in (([], 1.0, 128 / 255), (["--channel-colors", "green,magenta"], 0.0, 0.0)):
        vols = scene_from_args(render_parser().parse_args(["render", "--volume", str(path), *flags])).volumes
        assert vols[0].emission[2] == pytest.approx(vols[0].density_scale * blue0)  # cyan / green
        assert vols[1].emission[1] == pytest.approx(vols[1].density_scale * green1)  # orange / magenta


def test_bioformats2raw_tczyx_with_one_time_point_keeps_its_channels(tmp_path):
    """A multi-channel z-stack as bioformats2raw writes it (axes t, c, z, y, x with t = 1, here by ome-zarr's own
    ``write_image``): the single time point is dropped and the 3 channels stay 3 channels, each holding its own
    marker and nothing else; the time axis' scale (60 s) does not leak into the placement (8 x 8 x 12 um box)."""
    data = np.zeros((1, 3, 4, 16, 16), np.uint16)
    markers = [(0, 2, 3), (1, 9, 5), (3, 14, 12)]  # (z, y, x) of channel 0, 1, 2
    for c, zyx in enumerate(markers):
        data[(0, c, *zyx)] = 1000 * (c + 1)
    path = tmp_path / "b2r.zarr"
    writer.write_image(data, zarr.open_group(str(path), mode="w"), axes="tczyx", scale_factors=(2,),
                       scale={"t": 60.0, "c": 1.0, "z": 3.0, "y": 0.5, "x": 0.5},
                       axes_units={"t": "second", "z": "micrometer", "y": "micrometer", "x": "micrometer"})
    axes = json.loads((path / "zarr.json").read_text())["attributes"]["ome"]["multiscales"][0]["axes"]
    assert [a["name"] for a in axes] == list("tczyx")
    loaded = load_volume(path)
    assert len(loaded.channels) == 3 and loaded.density.shape == (4, 16, 16)
    for c, zyx in enumerate(markers):
        assert np.argwhere(loaded.channels[c] > 0).tolist() == [list(zyx)], c  # channel c's marker, in channel c
        assert loaded.channels[c][zyx] == 1.0
    size = loaded.corners_world.max(axis=0) - loaded.corners_world.min(axis=0)
    np.testing.assert_allclose(size, np.array([16 * 0.5, 16 * 0.5, 4 * 3.0]) * UM, rtol=1e-9)


def test_multiscale_transformations_apply_after_the_datasets(tmp_path):
    """NGFF 0.4/0.5: a multiscale's own ``coordinateTransformations`` (here scale 3, 4, 5 and translation 100, 200,
    300 um for z, y, x) apply after each dataset's scale and translation: coordinate = outer_scale * (scale * index
    + translation) + outer_translation. The box's corners (voxel edges at index -0.5 and n - 0.5) land there, as
    world (x, -y, -z) in metres, at level 0 and level 1 alike."""
    path = tmp_path / "outer.zarr"
    write_pyramid(path)
    outer_scale, outer_translation = np.array([3.0, 4.0, 5.0]), np.array([100.0, 200.0, 300.0])  # z, y, x [um]
    meta = json.loads((path / "zarr.json").read_text())
    meta["attributes"]["ome"]["multiscales"][0]["coordinateTransformations"] = [
        {"type": "scale", "scale": [1.0, *outer_scale]},
        {"type": "translation", "translation": [0.0, *outer_translation]}]
    (path / "zarr.json").write_text(json.dumps(meta))
    # dataset coordinates of the box's edges (index -0.5 and n - 0.5): z 9..25, y 3.75..19.75, x -3.25..12.75 um;
    # after the outer scale and translation: z 127..175, y 215..279, x 283.75..363.75 um
    expected_lo, expected_hi = np.array([283.75, -279.0, -175.0]) * UM, np.array([363.75, -215.0, -127.0]) * UM
    for level in (0, 1):
        corners = load_volume(path, level=level).corners_world
        np.testing.assert_allclose(corners.min(axis=0), expected_lo, rtol=1e-9, atol=1e-15, err_msg=str(level))
        np.testing.assert_allclose(corners.max(axis=0), expected_hi, rtol=1e-9, atol=1e-15, err_msg=str(level))


@pytest.mark.parametrize(("unit", "metres"), [("angstrom", 1e-10), ("nanometer", 1e-9), ("micrometer", 1e-6),
                                              ("millimeter", 1e-3)])
def test_axis_units_from_angstrom_to_millimetre_in_metres(tmp_path, unit, metres):
    """Electron microscopy states nanometres (cryo-EM angstroms), light microscopy micrometres, CT millimetres: the
    box of the (8, 32, 32) stack of 2 x 0.5 x 0.5 unit voxels is 16 units on each side, converted by 1 unit = 1e-10,
    1e-9, 1e-6, 1e-3 m, and starts half a voxel before voxel 0's centre (translation -3, 4, 10 units, x, y, z). An
    angstrom box was refused as "degenerate" (an absolute determinant threshold of 1e-30 m^3)."""
    path = tmp_path / f"{unit}.zarr"
    write_pyramid(path, units=(unit,) * 3)
    corners = load_volume(path).corners_world
    np.testing.assert_allclose(corners.max(axis=0) - corners.min(axis=0), [16 * metres] * 3, rtol=1e-9)
    # the far edges of y and z (index n - 0.5) become the world's lowest -y and -z
    lowest = np.array([-3.0 - 0.5 * 0.5, -(4.0 + 31.5 * 0.5), -(10.0 + 7.5 * 2.0)])  # x, -y, -z [units]
    np.testing.assert_allclose(corners.min(axis=0), lowest * metres, rtol=1e-9)


def test_a_time_series_is_refused_naming_the_file_and_the_axis(tmp_path):
    """An OME-Zarr of 3 time points (t, c, z, y, x by ``write_image``) is not silently read as its first one: volren
    reads one volume per file (sequences are numbered files), so it is refused in one line naming the file, the axis
    and its length, before any voxel is read."""
    path = tmp_path / "timelapse.zarr"
    data = np.zeros((3, 2, 4, 16, 16), np.uint16)
    data[1:] = 500  # later time points differ: taking t = 0 would show an empty volume
    writer.write_image(data, zarr.open_group(str(path), mode="w"), axes="tczyx", scale_factors=(2,))
    with pytest.raises(VolrenError) as info:
        load_volume(path)
    assert str(info.value) == (f"{path}: axis 't' has 3 entries; volren reads one volume (a channel axis 'c' and "
                               "z, y, x)")
