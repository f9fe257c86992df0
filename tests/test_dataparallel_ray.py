"""Data-parallel rendering on Ray (issue 43): `volren render --data-parallel N` and `RegionEngine` against the
one-process render of the same file, a killed region actor, the driver's bytes, and the refusals."""

from __future__ import annotations

import dataclasses
import json
import os
import signal

import numpy as np
import pytest

import volren.cli as cli
from volren.metrics import psnr

pytestmark = [pytest.mark.xdist_group("ray"), pytest.mark.timeout(240)]

LIGHT = ["--light-dir", "0.6,-0.7,0.4"]


@pytest.fixture(scope="module")
def ball(tmp_path_factory):
    """A 64^3 noisy ball (4^3 bricks) in a .npy file."""
    n = 64
    rng = np.random.default_rng(0)
    z, y, x = np.mgrid[0:n, 0:n, 0:n] / (n - 1) * 2 - 1
    d = np.clip(1 - np.sqrt(x**2 + y**2 + z**2) / 0.9, 0, None) * (0.5 + rng.random((n, n, n)))
    path = tmp_path_factory.mktemp("dp") / "ball.npy"
    np.save(path, d.astype(np.float32))
    return path


def render(path, out, *extra, lit: bool = True):
    argv = ["render", "--volume", str(path), "--width", "48", "--height", "32", "--views", "stereo", "--device",
            "cpu", "--save-linear", *(LIGHT if lit else []), *extra, "--out", str(out)]
    assert cli.main(argv) == 0
    return [np.load(out / f"view{v}.npy") for v in (0, 1)]


@pytest.fixture(scope="module")
def one_process(ball, tmp_path_factory):
    out = tmp_path_factory.mktemp("one")
    return {mode: render(ball, out / mode, "--mode", mode, *(["--iso-value", "0.4"] if mode == "iso" else []))
            for mode in ("dvr", "mip", "iso")}


@pytest.mark.parametrize("mode", ["dvr", "mip", "iso"])
def test_three_region_actors_render_the_one_process_picture(ray_cluster, ball, one_process, tmp_path, mode, capsys):
    iso = ["--iso-value", "0.4"] if mode == "iso" else []
    images = render(ball, tmp_path / "dp", "--mode", mode, *iso, "--data-parallel", "3")
    for got, want in zip(images, one_process[mode], strict=True):
        assert want[..., 3].max() > 0.5  # the ball is in the picture
        if mode == "dvr":
            assert psnr(want[..., :3], got[..., :3]) >= 50 and np.abs(got - want).max() < 2e-3
        else:
            np.testing.assert_array_equal(got, want)
    doc = json.loads((tmp_path / "dp" / "stats.json").read_text())
    assert doc["regions"] == 3
    assert "regions (last frame): 0 " in capsys.readouterr().out
    info = doc["frames"][0]["info"]
    assert info["regions"] == 3 and info["compositing"] == "direct-send"
    held = [r["bytes"] for r in info["region_stats"]]
    assert sum(r["bricks"] for r in info["region_stats"]) == 4**3  # the regions tile the bricks
    # no actor holds the whole volume's bricks (iso holds a ring of one brick more, read by its crossing search)
    assert max(held) < (1.0 if mode == "iso" else 0.6) * (4**3 * 17**3 * 4)


def test_a_killed_region_actor_is_replaced_and_the_frame_redone(ray_cluster, ball, one_process):
    from volren.distributed.regions import PlannedScene, RegionEngine
    from volren.plan import plan_render
    from volren.plan.spec import RenderSpec

    spec = RenderSpec.parse(["render", "--volume", str(ball), "--width", "48", "--height", "32", "--views", "stereo",
                             "--device", "cpu", *LIGHT])
    plan = plan_render(spec.namespace(), "dssrm")
    with RegionEngine(PlannedScene(spec), plan.scene, 2, plan.renderer) as engine:
        first = engine.render(plan.views, 0)
        os.kill(engine.pids()[1], signal.SIGKILL)
        again = engine.render(plan.views, 0)
        assert again.stats.info["replaced"] == 1
    for a, b, want in zip(first.images, again.images, one_process["dvr"], strict=True):
        np.testing.assert_array_equal(a, b)
        assert psnr(want[..., :3], b[..., :3]) >= 50


def test_direct_send_brings_the_driver_one_image_and_gather_n(ray_cluster, ball):
    from volren.distributed.regions import PlannedScene, RegionEngine
    from volren.plan import plan_render
    from volren.plan.spec import RenderSpec

    spec = RenderSpec.parse(["render", "--volume", str(ball), "--width", "48", "--height", "32", "--views", "mono",
                             "--device", "cpu", "--mode", "mip"])
    plan = plan_render(spec.namespace(), "dssrm")
    image_bytes = 48 * 32 * (16 + 4)  # RGBA and depth, float32
    frames = {}
    for how in ("direct-send", "gather"):
        with RegionEngine(PlannedScene(spec), plan.scene, 2, plan.renderer, compositing=how) as engine:
            frames[how] = engine.render(plan.views, 0)
    assert frames["direct-send"].stats.info["driver_bytes"] == image_bytes
    assert frames["gather"].stats.info["driver_bytes"] == 2 * image_bytes
    np.testing.assert_array_equal(frames["direct-send"].images[0], frames["gather"].images[0])


@pytest.mark.timeout(60)
@pytest.mark.parametrize(("extra", "message"), [
    (["--method", "cmsrm"], "--data-parallel renders with dssrm only"),
    (["--mode", "mida"], "mode mida's running maximum"),
    (["--data-parallel", "0"], "--data-parallel must be >= 1"),
    (["--workers", "2"], "give one of them"),
    (["--data-parallel", "65"], "--data-parallel 65: cannot split a grid of 64 bricks into 65 regions"),
])
def test_what_does_not_split_is_refused_in_one_line(ball, tmp_path, capsys, extra, message):
    argv = ["render", "--volume", str(ball), "--width", "8", "--height", "8", "--device", "cpu", "--data-parallel",
            "2", *extra, "--out", str(tmp_path / "o")]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert any(message in line for line in err), err
    assert not (tmp_path / "o").exists()


def test_a_pyramid_over_the_budget_renders_from_its_finest_bricks_read_per_region(ray_cluster, tmp_path, capsys):
    """The driver streams the pyramid (its coarsest level in memory); each actor reads its region's level-0 bricks
    from the store: the picture is the dense finest level's, and a region over the budget is refused."""
    from tests.test_stream_render import write_pyramid

    write_pyramid(tmp_path / "p.zarr", levels=3)
    base = ["render", "--volume", str(tmp_path / "p.zarr"), "--width", "48", "--height", "32", "--device", "cpu",
            "--save-linear", *LIGHT, "--views", "mono"]
    assert cli.main([*base, "--level", "0", "--out", str(tmp_path / "dense")]) == 0
    # level 0 is 1 MiB of float32 densities, over the 0.6 MiB budget: streamed, each of 2 regions holds 0.6 MiB
    assert cli.main([*base, "--memory-budget", "0.0006", "--data-parallel", "2", "--out", str(tmp_path / "dp")]) == 0
    want, got = np.load(tmp_path / "dense" / "view0.npy"), np.load(tmp_path / "dp" / "view0.npy")
    assert want[..., 3].max() > 0.5 and np.abs(got - want).max() < 1e-5
    capsys.readouterr()
    assert cli.main([*base, "--memory-budget", "0.0004", "--data-parallel", "2", "--out", str(tmp_path / "o")]) == 2
    assert "region 0 of 2 holds 0.6 MiB of bricks, above --memory-budget" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_serve_renders_through_the_regions_with_the_viewers_settings_and_light(ray_cluster, ball):
    """A render loop over region actors (``serve --data-parallel``): its frames equal an in-process renderer of the
    loop's config, after a mode switch (iso reads a ring of bricks more: the regions are cut again) and a light
    drag (the lights travel to the actors, the light map is summed again)."""
    from volren.distributed.regions import PlannedScene, RegionEngine
    from volren.plan import plan_render
    from volren.plan.spec import RenderSpec
    from volren.render import DSSRM
    from volren.serve.loop import RenderLoop, with_light

    spec = RenderSpec.parse(["render", "--volume", str(ball), "--width", "40", "--height", "30", "--views", "mono",
                             "--device", "cpu"])
    plan = plan_render(spec.namespace(), "dssrm")
    cam = plan.views[0]
    with RegionEngine(PlannedScene(spec), plan.scene, 2, plan.renderer) as engine:
        loop = RenderLoop(plan.scene, "dssrm", device="cpu", data_parallel=engine)
        assert loop.choices.methods == ("dssrm",) and "mida" not in loop.choices.modes
        for mode, light in (("dvr", None), ("iso", None), ("dvr", (0.7, -0.5, -0.5))):
            loop.mode = mode
            loop.light_dir = light
            loop._build_renderer()
            scene = with_light(plan.scene, light)
            got = loop.renderer.render(scene, [cam], 0).images[0]
            want = DSSRM(loop._config, device="cpu").render(scene, [cam]).images[0]
            assert want[..., 3].max() > 0.5
            # the one-process march stops below the interactive preset's min_transmittance; the regions march on
            alpha = np.abs(got[..., 3] - want[..., 3]).max()
            assert psnr(want[..., :3], got[..., :3]) >= 50 and alpha <= loop._config.min_transmittance, (mode, light)


@pytest.mark.timeout(60)
@pytest.mark.parametrize(("extra", "message"), [
    (["--shards", "2"], "give one of them"),
    (["--method", "vpt"], "--data-parallel renders with dssrm only"),
])
def test_serve_data_parallel_refusals_are_one_line(ball, capsys, extra, message):
    assert cli.main(["serve", "--volume", str(ball), "--data-parallel", "2", *extra]) == 2
    assert message in capsys.readouterr().err


def test_a_multi_channel_file_splits_each_channel_alike(ray_cluster, tmp_path):
    """Two channels of one grid (green and magenta by default): each region holds both, each channel composited over
    the regions, then tinted (MIP) and added as the one-process render adds them."""
    n = 48
    z, y, x = np.mgrid[0:n, 0:n, 0:n] / (n - 1) * 2 - 1
    blobs = [np.exp(-((x - c) ** 2 + y**2 + z**2) / 0.1) for c in (0.4, -0.4)]
    path = tmp_path / "two.npy"
    np.save(path, np.stack(blobs).astype(np.float32))
    for mode in ("dvr", "mip"):
        want = render(path, tmp_path / f"one-{mode}", "--mode", mode, lit=False)[0]
        got = render(path, tmp_path / f"dp-{mode}", "--mode", mode, "--data-parallel", "2", lit=False)[0]
        right, left = want[16, 30], want[16, 18]  # the +x blob (channel 0, green), the -x one (1, magenta)
        assert right[1] > 0.3 > right[0] and left[0] > 0.3 > left[1]
        if mode == "mip":
            np.testing.assert_array_equal(got, want)
        else:
            assert np.abs(got - want).max() < 1e-4


def test_the_python_api_renders_data_parallel_as_the_cli(ray_cluster, ball):
    """``vr.render(path, data_parallel=2)``: each actor reads the file; the picture is the one-process one (MIP
    bit-exact, DVR within early termination's threshold); a sequence is refused in one line."""
    import volren as vr

    for mode in ("mip", "dvr"):
        want = vr.render(str(ball), "stereo", width=40, height=30, device="cpu", mode=mode)
        got = vr.render(str(ball), "stereo", width=40, height=30, device="cpu", mode=mode, data_parallel=2)
        assert got.stats.info["regions"] == 2 and got.scene_name == "ball"
        for a, b in zip(want.images, got.images, strict=True):
            assert a[..., 3].max() > 0.5
            if mode == "mip":
                np.testing.assert_array_equal(a, b)
            else:
                assert psnr(a[..., :3], b[..., :3]) >= 50 and np.abs(a[..., 3] - b[..., 3]).max() <= 0.01


def test_animate_orbits_the_regions_as_in_process(ray_cluster, ball, tmp_path):
    """``volren animate --data-parallel 2``: each frame's orbiting view composited in its own visibility order, the
    light map exchanged once (the light stands still), the frames the in-process run's."""
    argv = ["animate", "--volume", str(ball), "--frames", "3", "--width", "40", "--height", "30", "--views", "mono",
            "--device", "cpu", "--save-linear", "--mode", "mip"]
    assert cli.main([*argv, "--out", str(tmp_path / "one")]) == 0
    assert cli.main([*argv, "--data-parallel", "2", "--out", str(tmp_path / "dp")]) == 0
    for i in range(3):
        want = np.load(tmp_path / "one" / f"frame{i:04d}_view0.npy")
        assert want[..., 3].max() > 0.5
        np.testing.assert_array_equal(np.load(tmp_path / "dp" / f"frame{i:04d}_view0.npy"), want)
    frames = json.loads((tmp_path / "dp" / "stats.json").read_text())["frames"]
    assert len({tuple(f["info"]["orders"][0]) for f in frames}) == 2  # the orbit crosses the split plane


def test_sigterm_stops_a_data_parallel_run_as_ctrl_c_does(ray_cluster, ball, tmp_path):
    """SIGTERM once the regions are loaded and frames are rendering: one line, exit 143, no native stack dump, no
    --out (it is written beside and moved in when complete), and the region actors gone from the cluster."""
    import subprocess
    import sys
    import time

    address = ray_cluster.get_runtime_context().gcs_address
    out = tmp_path / "o"
    proc = subprocess.Popen([sys.executable, "-m", "volren.cli", "animate", "--volume", str(ball), "--frames", "400",
                             "--width", "64", "--height", "48", "--views", "mono", "--device", "cpu",
                             "--data-parallel", "2", "--ray-address", address, "--out", str(out)],
                            cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        seen = ""
        while "region 1:" not in seen and proc.poll() is None:
            seen += proc.stderr.readline()
        assert proc.poll() is None, seen
        time.sleep(3.0)  # frames under way
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, (seen + err)[-3000:]
    assert err.strip().splitlines()[-1] == "volren: terminated", err[-3000:]
    for native in ("Fatal Python error", "Aborted", "core dumped", "Traceback"):
        assert native not in err, err[-3000:]
    assert list(tmp_path.iterdir()) == []
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and ray_cluster.available_resources().get("CPU", 0) < 2:
        time.sleep(0.5)  # the actors' CPUs come back as they go
    assert ray_cluster.available_resources().get("CPU", 0) == 2


def test_an_actors_error_reaches_the_driver_as_its_one_line(ray_cluster, ball, tmp_path):
    """A switch to iso cuts the regions again from the file; the file gone meanwhile, the actors' error is the
    driver's VolrenError naming it (not a RayTaskError's traceback)."""
    import shutil

    from volren.distributed.regions import PlannedScene, RegionEngine
    from volren.errors import VolrenError
    from volren.plan import plan_render
    from volren.plan.spec import RenderSpec

    copy = tmp_path / "gone.npy"
    shutil.copy(ball, copy)
    spec = RenderSpec.parse(["render", "--volume", str(copy), "--width", "16", "--height", "12", "--views", "mono",
                             "--device", "cpu", "--mode", "mip"])
    plan = plan_render(spec.namespace(), "dssrm")
    with RegionEngine(PlannedScene(spec), plan.scene, 2, plan.renderer) as engine:
        assert engine.render(plan.views, 0).images[0][..., 3].max() > 0.5
        copy.unlink()
        with pytest.raises(VolrenError, match=r"gone\.npy") as e:
            engine.render(plan.views, 1, config=dataclasses.replace(plan.renderer.config, mode="iso"))
        assert "\n" not in str(e.value)


def test_serve_data_parallel_builds_its_loop_on_region_actors(ray_cluster, ball, monkeypatch):
    """``volren serve --volume F --data-parallel 2``: the app's loop renders the file through two region actors, the
    picture the in-process renderer's of the loop's config and framing."""
    from volren.render import DSSRM
    from volren.serve.app import LOOP_KEY

    apps = []
    monkeypatch.setattr("volren.serve.app.serve", lambda app, *args, **kwargs: apps.append(app))
    assert cli.main(["serve", "--volume", str(ball), "--data-parallel", "2", "--device", "cpu"]) == 0
    loop = apps[0][LOOP_KEY]
    try:
        cam = dataclasses.replace(loop.camera, width=40, height=30)
        got = loop.renderer.render(loop.scene, [cam]).images[0]
        want = DSSRM(loop._config, device="cpu").render(loop.scene, [cam]).images[0]
        assert loop.data_parallel.n == 2 and want[..., 3].max() > 0.5
        assert psnr(want[..., :3], got[..., :3]) >= 50
        assert np.abs(got[..., 3] - want[..., 3]).max() <= loop._config.min_transmittance
    finally:
        loop.data_parallel.close()
