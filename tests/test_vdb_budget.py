"""A ``.vdb`` held to ``--memory-budget`` (issue 41): the bricks its leaves and tiles will take are estimated from
the tree topology before any leaf is read, and a file over the budget is refused in one line naming the file, the
estimate and the budget, at once and with nothing allocated; within the budget it loads as before."""

from __future__ import annotations

import time
import tracemalloc

import numpy as np
import pytest

from volren.bench.load import openvdb_available, write_with_openvdb
from volren.data.loaders import load_volume
from volren.errors import VolrenError

pytestmark = [pytest.mark.timeout(120),
              pytest.mark.skipif(not openvdb_available(), reason="pyopenvdb (python3-openvdb) writes the files")]

BRICK_BYTES = 17**3 * 4
"""a 16^3 brick with its one-voxel apron, float32"""


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    """96^3 active voxels at index 0..95 (1728 leaves): 6^3 = 216 bricks, 4.05 MiB of pool; a temperature grid
    beside it takes as many."""
    folder = tmp_path_factory.mktemp("budget")
    field = np.random.default_rng(4).uniform(0.1, 1.0, (96, 96, 96)).astype(np.float32)
    write_with_openvdb({"smoke.vdb": [{"name": "density", "array": field},
                                      {"name": "temperature", "array": 300.0 + field}]}, folder)
    return folder / "smoke.vdb", field


def test_a_vdb_over_the_budget_is_refused_from_its_topology_at_once(smoke, monkeypatch):
    import volren.data.vdb as vdb

    path, _ = smoke

    def no_read(path):
        raise AssertionError("tinyvdb decoded the leaves of a file over the budget")

    monkeypatch.setattr(vdb, "_open", no_read)
    with pytest.raises(VolrenError):
        load_volume(path, memory_budget=2**20)  # once before the trace: the lazy imports are no load's memory
    tracemalloc.start()
    start = time.perf_counter()
    with pytest.raises(VolrenError) as caught:
        load_volume(path, memory_budget=2**20)
    took = time.perf_counter() - start
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert str(caught.value) == (f"{path}: its bricks would take 4.05 MiB (estimated from the tree topology: 216 "
                                 "bricks of 17^3 float32), over the memory budget of 1 MiB; raise memory_budget "
                                 "(CLI: --memory-budget GIB)")
    assert took < 1.0 and peak < 2**20  # no pool (4 MiB), no leaf values (3.4 MiB): the topology's arrays
    with pytest.raises(VolrenError, match=r"8\.1 MiB .*: 432 bricks"):  # the emission grid's bricks count too
        load_volume(path, emission_grid="temperature", memory_budget=2**23)


def test_the_same_vdb_loads_within_a_normal_budget_and_at_its_estimate(smoke):
    path, field = smoke
    for budget in (None, 2**23, 216 * BRICK_BYTES):  # None: no budget checked (a .vdb has no coarser level)
        loaded = load_volume(path, memory_budget=budget)
        np.testing.assert_array_equal(loaded.density.to_dense(), field)
    both = load_volume(path, emission_grid="temperature", memory_budget=432 * BRICK_BYTES)
    assert both.emission_source is not None


def test_the_cli_refuses_a_vdb_over_its_memory_budget_in_one_line(smoke, tmp_path, capsys):
    from volren.cli import main

    path, _ = smoke
    assert main(["render", "--volume", str(path), "--memory-budget", "0.002", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and str(path) in err[0] and "over the memory budget of 2.05 MiB" in err[0]


def test_without_a_budget_a_vdb_must_fit_the_machines_free_memory(smoke, monkeypatch):
    """No budget given: the bricks are held to the free memory (a .vdb has no coarser level to fall back to), here a
    machine with 2 MiB free."""
    import os

    path, _ = smoke
    sysconf = os.sysconf
    monkeypatch.setattr(os, "sysconf", lambda name: 512 if name == "SC_AVPHYS_PAGES" else sysconf(name))
    with pytest.raises(VolrenError, match=r"smoke\.vdb: its bricks \(estimated from the tree topology\) needs") as e:
        load_volume(path)
    assert "\n" not in str(e.value)
    monkeypatch.setattr(os, "sysconf", sysconf)
    assert load_volume(path).density.max() > 0.9
