"""`volren.plan.spec.RenderSpec`: a render as plain data, which batch jobs and Ray workers receive instead of a command
line to parse again (issue 42 item 1): it round-trips through JSON and pickle typed as the parser types it, and the
plan built from it is the plan of the command line it came from."""

from __future__ import annotations

import io
import json
import pickle
from pathlib import Path

import pytest

from volren.errors import VolrenError
from volren.plan import render_parser
from volren.plan.spec import RenderSpec

pytestmark = pytest.mark.timeout(60)

WIDE = ("animate", "--volume", "sim_####.npy", "--channel-colors", "1,0,0;0,1,0", "--mesh", "a.obj", "--mesh", "b.obj",
        "--mesh-alpha", "0.5", "--mesh-alpha", "0.25", "--rect-light", "1,2,3,4,5,6", "--sphere", "0,0,0,0.3",
        "--camera-pos", "0,1,2", "--no-skip", "--frames", "3", "--switch-tf", "1:ct-bone", "--out", "o/x")


def test_a_spec_round_trips_through_json_and_pickle_typed_as_the_parser_types_it():
    spec = RenderSpec.parse(WIDE)
    parsed = vars(render_parser().parse_args(list(WIDE)))
    assert vars(spec.namespace()) == parsed  # every option, with its type: paths, tuples, lists of repeats
    doc = json.loads(json.dumps(spec.to_json()))  # plain JSON: no path or tuple objects in it
    back = RenderSpec.from_json(doc)
    assert back == spec and vars(back.namespace()) == parsed
    assert pickle.loads(pickle.dumps(spec)) == spec
    ns = back.namespace()
    assert ns.mesh == [Path("a.obj"), Path("b.obj")] and ns.mesh_alpha == [0.5, 0.25]
    assert ns.rect_light == [(1.0, 2.0, 3.0, 4.0, 5.0, 6.0)] and ns.camera_pos == (0.0, 1.0, 2.0)
    assert ns.channel_colors == ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)) and ns.volume == Path("sim_####.npy")
    assert spec.out == Path("o/x") and spec.line == "volren " + " ".join(
        f"'{w}'" if ";" in w or "#" in w else w for w in WIDE)


def test_specs_of_the_same_render_compare_equal_and_changes_are_checked():
    a = RenderSpec.parse(["render", "--width", "32", "--out", "o"])
    b = RenderSpec.parse(["render", "--out", "o", "--width", "32", "--height", "360"])  # another order, a default
    assert a.options == b.options
    assert a != a.replace(width=33) and a.replace(width=33).namespace().width == 33
    assert a.namespace(max_minutes=0).max_minutes == 0 and a.namespace().max_minutes == 60.0  # a fresh object
    with pytest.raises(VolrenError, match="render has no option widht"):
        a.namespace(widht=3)


@pytest.mark.parametrize(("doc", "message"), [
    ({"command": "serve", "options": {}}, "a render spec is one of demo, render, animate, got 'serve'"),
    ({"command": "render", "options": {"width": 3}}, "the render spec's options differ from this volren's"),
])
def test_a_spec_from_another_file_is_refused_in_one_line(doc, message):
    with pytest.raises(VolrenError, match=message):
        RenderSpec.from_json(doc)
    with pytest.raises(VolrenError, match="a render spec is one of demo, render, animate, got 'batch'"):
        RenderSpec.parse(["batch", "x.toml"])


def test_the_worker_renders_the_spec_as_volren_render_does(tmp_path):
    """`UnitWorker` builds its plan from the spec it is handed (no command line), and its files are the in-process
    run's, byte for byte."""
    from volren.cli import main
    from volren.distributed.worker import Unit, UnitWorker

    small = ["--width", "40", "--height", "24", "--resolution", "64", "--samples", "24", "--light-grid", "8",
             "--views", "mono", "--device", "cpu", "--frames", "2"]
    assert main(["render", *small, "--out", str(tmp_path / "cli")]) == 0
    spec = RenderSpec.parse(["render", *small, "--out", str(tmp_path / "unused")])
    result = UnitWorker().run(RenderSpec.from_json(json.loads(json.dumps(spec.to_json()))), Unit(0, 0, 2))
    cli_files = {p.name: p.read_bytes() for p in (tmp_path / "cli").glob("*.png")}
    assert sorted(result["files"]) == sorted(cli_files) == ["frame0000_view0.png", "frame0001_view0.png"]
    assert result["files"] == cli_files
    assert not (tmp_path / "unused").exists()  # a worker writes nothing: the driver does


def test_a_worker_handed_another_spec_renders_that_one():
    """An actor keeps its plan while the job stays the same (scene uploaded once) and builds afresh for another."""
    from PIL import Image

    from volren.distributed.worker import Unit, UnitWorker

    worker = UnitWorker()
    small = ["render", "--height", "24", "--resolution", "64", "--samples", "16", "--light-grid", "8", "--views",
             "mono", "--device", "cpu", "--out", "o"]
    for width in (40, 24, 24):
        result = worker.run(RenderSpec.parse([*small, "--width", str(width)]), Unit(0, 0, 1))
        assert Image.open(io.BytesIO(result["files"]["view0.png"])).size == (width, 24)
    assert result["setup_seconds"] < 0.05  # the third ran the second's plan again: nothing rebuilt


@pytest.mark.timeout(30)
def test_a_replaced_spec_keeps_the_line_its_user_gave():
    """`RenderSpec.replace` changes options, never the command line stats.json and messages quote."""
    a = RenderSpec.parse(["render", "--width", "32", "--out", "o"])
    assert a.replace(width=33).line == a.line == "volren render --width 32 --out o"


@pytest.mark.timeout(120)
def test_a_worker_renders_its_unit_whatever_the_jobs_estimate():
    """The driver checked the whole job against --max-minutes; a worker handed one unit of it renders that unit
    instead of refusing the job again (400 frames of 320x180 is past the probe threshold, 1e-6 min under any)."""
    from PIL import Image

    from volren.distributed.worker import Unit, UnitWorker

    spec = RenderSpec.parse(["render", "--width", "320", "--height", "180", "--resolution", "64", "--samples", "8",
                             "--light-grid", "8", "--views", "mono", "--device", "cpu", "--frames", "400",
                             "--max-minutes", "0.000001", "--out", "o"])
    result = UnitWorker().run(spec, Unit(0, 0, 1))
    assert Image.open(io.BytesIO(result["files"]["frame0000_view0.png"])).size == (320, 180)


@pytest.mark.timeout(180)
def test_a_worker_warms_up_for_another_jobs_unit_that_starts_where_its_last_one_stopped():
    """A temporal method's history belongs to its job: an actor that ran frames 0-1 of one job and is handed frame 2 of
    another renders that job's frames 0-1 first, as a fresh actor does, instead of carrying the first job's history."""
    from volren.distributed.worker import Unit, UnitWorker

    base = ["animate", "--width", "32", "--height", "24", "--resolution", "64", "--device", "cpu", "--views", "mono",
            "--method", "vpt", "--denoise", "ours", "--spp", "1", "--frames", "3", "--out", "o"]
    first, other = RenderSpec.parse([*base, "--orbit", "30"]), RenderSpec.parse([*base, "--orbit", "90"])
    worker = UnitWorker()
    worker.run(first, Unit(0, 0, 2, 0, True))
    got = worker.run(other, Unit(1, 2, 3, 2, True))
    want = UnitWorker().run(other, Unit(1, 2, 3, 2, True))
    assert got["files"] == want["files"] and got["warmup_seconds"] > 0
