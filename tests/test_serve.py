"""`volren serve` in process (aiohttp's test client): the protocol, one render call per tick for every viewer, frame
dropping, disconnects, the token, /health and the light-map cache. A 16^3 smoke at 64x48 keeps each tick ~10 ms."""

from __future__ import annotations

import asyncio
import base64
import json
import os
import socket
import struct
import threading
import time
import types

import numpy as np
import pytest
from aiohttp.test_utils import TestClient, TestServer

from volren.camera import Camera, StereoRig
from volren.data.procedural import smoke_density
from volren.errors import VolrenError
from volren.metrics import psnr
from volren.presets import quality_config
from volren.render import DSSRM, VPT
from volren.scene import DirectionalLight, Environment, Scene, Volume
from volren.serve.app import ACCESS_KEY, _serve, check_bind, make_app, open_line, read_token
from volren.serve.jpeg import decode_jpeg, display_image
from volren.serve.loop import RenderLoop, animator
from volren.serve.protocol import MAX_MESSAGE_BYTES, unpack_frame
from volren.serve.viewers import Limits

SMALL = {"samples": 64, "light_samples": 16, "light_grid": 8}
W, H = 64, 48
SCENE = Scene((Volume(smoke_density(64).reshape(16, 4, 16, 4, 16, 4).mean(axis=(1, 3, 5)), density_scale=13.0,
                      albedo=0.85, g=0.2),),
              (DirectionalLight((-0.5, -1.0, -0.35), (3.0, 3.0, 3.0)),), Environment((0.05, 0.065, 0.09)),
              (0.015, 0.015, 0.02), name="smoke16")
TIMEOUT = 60.0
"""[s] per awaited message: the first tick compiles kernels when the cache is cold"""


def cam_msg(i: int, x: float = 0.0) -> dict:
    return {"type": "camera", "id": i, "position": [x, 0.2, 1.9], "look_at": [0, 0, 0], "up": [0, 1, 0], "fov": 45}


def offline(msg: dict, scene: Scene = SCENE, stereo: bool = False, **config) -> np.ndarray:
    """The same camera rendered by a fresh renderer outside the server, as the server shows it (sRGB uint8)."""
    cam = Camera(position=msg["position"], look_at=msg["look_at"], fov_y=msg["fov"], width=W // 2 if stereo else W,
                 height=H)
    views = StereoRig(cam).eyes() if stereo else [cam]
    r = DSSRM(quality_config("dssrm", "interactive", **SMALL, **config), device="cpu")
    return display_image(r.render(scene, views).images, scene.background)


def db(ref: np.ndarray, image: np.ndarray) -> float:
    return psnr(ref.astype(float), image.astype(float), data_range=255.0)


def run(test, token: str | None = None, **loop_kw) -> None:
    """Run ``test(client, loop)`` against a fresh server."""
    async def main() -> None:
        loop = RenderLoop(SCENE, "dssrm", "interactive", **{"limits": Limits(4, 128, 96), **loop_kw},
                          device="cpu", overrides=SMALL)
        # a failing test leaves sockets open: do not wait a minute for them at shutdown
        async with TestClient(TestServer(make_app(loop, "smoke16", token), shutdown_timeout=1.0)) as client:
            await test(client, loop)
    asyncio.run(main())


async def until(condition, what: str) -> None:
    """Wait (20 s at most: nothing to compile here) for ``condition()``, polling the event loop."""
    for _ in range(2000):
        if condition():
            return
        await asyncio.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


async def connect(client, width: int = W, height: int = H, stereo: bool = False):
    ws = await client.ws_connect("/ws")
    await ws.send_json({"type": "hello", "width": width, "height": height, "stereo": stereo})
    welcome = await ws.receive_json(timeout=TIMEOUT)
    assert welcome["type"] == "welcome"
    return ws, welcome


async def next_frame(ws) -> tuple[dict, np.ndarray]:
    """The next binary frame (text messages before it are returned by `next_text` instead; here they fail)."""
    msg = await ws.receive(timeout=TIMEOUT)
    assert isinstance(msg.data, bytes), f"expected a frame, got {msg.data!r}"
    header, jpeg = unpack_frame(msg.data)
    await ws.send_json({"type": "ack", "tick": header["tick"]})  # drawn, as the page says it
    return header, decode_jpeg(jpeg)


async def frame_for(ws, camera_id: int) -> tuple[dict, np.ndarray]:
    """Frames until the one answering ``camera_id``."""
    while True:
        header, image = await next_frame(ws)
        if header["camera_id"] == camera_id:
            return header, image


def test_camera_in_tagged_jpeg_out_and_light_map_cached():
    """A camera message comes back as a JPEG frame tagged with its id, the size asked for, matching an offline
    render of that camera (JPEG loss only: measured 48 dB). The static scene's light map is computed on the first
    tick only; a light_dir change recomputes it and the frame matches an offline render under the new light."""
    async def test(client, loop):
        ws, welcome = await connect(client)
        assert welcome["method"] == "dssrm" and welcome["limits"]["max_viewers"] == 4
        await ws.send_json(cam_msg(7))
        header, image = await frame_for(ws, 7)
        assert header["type"] == "frame" and (header["width"], header["height"]) == (W, H) and not header["stereo"]
        assert image.shape == (H, W, 3) and image.std() > 10  # not blank: the plume over a dark background
        assert db(offline(cam_msg(7)), image) > 40.0
        assert "light_map" in header["pass_ms"]
        await ws.send_json(cam_msg(8, x=0.5))
        header, image = await frame_for(ws, 8)
        assert "light_map" not in header["pass_ms"], "static scene and light: the light map is reused"
        assert db(offline(cam_msg(8, x=0.5)), image) > 40.0
        light = [0.3, -0.2, 1.0]  # backlit: 27.6 dB from the first light's image
        await ws.send_json({"type": "settings", "light_dir": light})
        await ws.send_json(cam_msg(9, x=0.5))
        header, image = await frame_for(ws, 9)
        assert "light_map" in header["pass_ms"]
        assert "upload_lights" in header["pass_ms"] and "upload" not in header["pass_ms"], "only the lights uploaded"
        lit = Scene(SCENE.volumes, (DirectionalLight(tuple(light), (3.0, 3.0, 3.0)),), SCENE.environment,
                    SCENE.background)
        assert db(offline(cam_msg(9, x=0.5), lit), image) > 40.0
        # the old light's image differs clearly: the test above can tell the lights apart
        assert db(offline(cam_msg(9, x=0.5)), image) < 32.0
        await ws.close()

    run(test)


BAD = [
    ("not json", "not valid JSON"),
    ('{"type": "camera", "id": 1, "position": [NaN, 0, 3], "look_at": [0, 0, 0]}', "NaN"),
    ('{"type": "camera", "id": 1, "position": [Infinity, 0, 3], "look_at": [0, 0, 0]}', "Infinity"),
    ('{"type": "camera", "id": 1, "position": [1e400, 0, 3], "look_at": [0, 0, 0]}', "camera.position[0]"),
    ('{"type": "camera", "id": 1, "position": [1e9, 0, 3], "look_at": [0, 0, 0]}', "camera.position[0]"),
    ('{"type": "camera", "id": 1, "position": [0, 0, 3], "look_at": [0, 0, 0], "fov": 1e9}', "camera.fov"),
    ('{"type": "camera", "id": 1, "position": [0, 0, 3], "look_at": [0, 0, 0], "fov": true}', "camera.fov"),
    ('{"type": "camera", "id": 1, "position": "0,0,3", "look_at": [0, 0, 0]}', "camera.position"),
    ('{"type": "camera", "id": 1.5, "position": [0, 0, 3], "look_at": [0, 0, 0]}', "camera.id"),
    ('{"type": "camera", "id": 1, "position": [0, 0, 3], "look_at": [0, 0, 3]}', "camera:"),
    ('{"type": "camera", "id": 1, "position": [0, 0, 3], "look_at": [0, 0, 0], "evil": 1}', "unknown field(s) evil"),
    ('{"type": "camera", "id": 1, "position": [0, 0, 3]}', "missing field(s) look_at"),
    ('{"type": "launch", "id": 1}', "type must be one of"),
    ('[1, 2, 3]', "JSON object"),
    ('{"type": "resize", "width": -5, "height": 48}', "resize.width"),
    ('{"type": "settings", "method": "rm -rf"}', "settings.method"),
    ('{"type": "settings", "light_dir": [0, 0, 0]}', "settings.light_dir"),
    ('{"type": "settings", "playing": "yes"}', "settings.playing"),
    ('{"type": "hello", "width": 64, "height": 48}', "already received"),
    ("[" * 1000 + "]" * 1000, "too large"),
    ("[" * 500 + "]" * 500, "nested deeper than 2"),
    ('{"type": "settings", "light_dir": [[[[0]]]]}', "nested deeper than 2"),
    ('{"type": "camera", "id": 2147483648, "position": [0, 0, 3], "look_at": [0, 0, 0]}', "camera.id"),
    ('{"type": "ack", "tick": 12345}', "not the frame awaiting"),
    (json.dumps({"type": "settings", "tf": "x" * (MAX_MESSAGE_BYTES + 10)}), "too large"),
]


def test_bad_messages_get_an_error_and_the_connection_still_works():
    """Every malformed message gets one error message naming what is wrong; the connection and the loop go on and
    a good camera afterwards is answered. A camera before hello and a viewer over the limit are refused too."""
    async def test(client, loop):
        ws = await client.ws_connect("/ws")
        await ws.send_json(cam_msg(1))
        assert "send hello first" in (await ws.receive_json(timeout=TIMEOUT))["message"]
        await ws.send_json({"type": "hello", "width": W, "height": H})
        assert (await ws.receive_json(timeout=TIMEOUT))["type"] == "welcome"
        for text, expected in BAD:
            await ws.send_str(text)
            reply = await ws.receive_json(timeout=TIMEOUT)
            assert reply["type"] == "error" and expected in reply["message"], (text[:80], reply)
            assert "\n" not in reply["message"]
        await ws.send_bytes(b"\x00\x01")
        assert "not binary" in (await ws.receive_json(timeout=TIMEOUT))["message"]
        await ws.send_json(cam_msg(5))
        await frame_for(ws, 5)
        assert loop.tick >= 1 and not loop._task.done()
        others = [(await connect(client))[0] for _ in range(3)]  # 4 viewers: the limit
        extra = await client.ws_connect("/ws")
        await extra.send_json({"type": "hello", "width": W, "height": H})  # a slot is taken only by a hello
        assert "server full" in (await extra.receive_json(timeout=TIMEOUT))["message"]
        assert (await extra.receive(timeout=TIMEOUT)).type.name in ("CLOSE", "CLOSED")
        for w in [ws, *others]:
            await w.close()

    run(test)


def test_four_viewers_one_render_call_per_tick():
    """Four viewers (the third stereo) are rendered by ONE render call per tick: 5 views, the stereo eyes first (views
    0 and 1, the pair CACRM couples); each viewer gets its own camera's image, the stereo one both eyes side by
    side."""
    async def test(client, loop):
        widths = []
        render = loop.renderer.render

        def recorded(scene, views, frame=0):
            widths.append([c.width for c in views])
            return render(scene, views, frame)

        loop.renderer.render = recorded
        viewers = [await connect(client, stereo=(i == 2)) for i in range(4)]
        xs = [-0.6, -0.2, 0.2, 0.6]
        for i, (ws, _) in enumerate(viewers):
            await ws.send_json(cam_msg(10 + i, xs[i]))
        for i, (ws, _) in enumerate(viewers):
            await frame_for(ws, 10 + i)
        # every viewer now has a camera: each further tick renders all of them
        for i, (ws, _) in enumerate(viewers):
            await ws.send_json(cam_msg(20 + i, xs[i]))
        images = [await frame_for(ws, 20 + i) for i, (ws, _) in enumerate(viewers)]
        assert loop.renders == loop.tick == len(widths), "one render call per tick"
        assert loop.views_last == 5 and widths[-1] == [W // 2, W // 2, W, W, W], "the stereo eyes first, a pair"
        for i, (header, image) in enumerate(images):
            stereo = i == 2
            assert header["stereo"] == stereo and image.shape == (H, W, 3) and header["viewers"] == 4
            ref = offline(cam_msg(20 + i, xs[i]), stereo=stereo)
            assert db(ref, image) > 40.0, i
        health = await (await client.get("/health")).json()
        assert health["renders"] == health["tick"] == loop.tick and health["views"] == 5
        for ws, _ in viewers:
            await ws.close()

    run(test)


def test_disconnect_during_a_frame():
    """A viewer that leaves while its frame is being rendered is dropped cleanly: the others get their frames, the
    loop keeps serving, and with every viewer gone it renders nothing more."""
    async def test(client, loop):
        started, release = threading.Event(), threading.Event()
        render = loop._render_encode

        def slow(*args):
            started.set()
            release.wait(TIMEOUT)
            return render(*args)

        a, _ = await connect(client)
        b, _ = await connect(client)
        loop._render_encode = slow
        await a.send_json(cam_msg(1))
        await b.send_json(cam_msg(2, 0.3))
        await asyncio.to_thread(started.wait, TIMEOUT)
        await a.close()  # mid-frame
        await until(lambda: len(loop.viewers) == 1, "the closed viewer's removal")
        release.set()
        await frame_for(b, 2)
        await b.send_json(cam_msg(3, 0.4))
        header, _ = await frame_for(b, 3)
        assert header["viewers"] == 1 and not loop._task.done()
        health = await (await client.get("/health")).json()
        assert health["viewers"] == 1
        await b.close()
        await until(lambda: not len(loop.viewers), "every viewer's removal")
        ticks = loop.tick
        await asyncio.sleep(0.3)
        assert loop.tick == ticks, "no viewers: no rendering"

    run(test)


def test_a_client_that_never_reads_does_not_stall_the_others():
    """Viewer A's socket never drains (its send never completes, as for a client that stopped reading): A holds one
    frame in flight and every later frame for it is dropped, never queued; viewer B keeps getting every frame."""
    async def test(client, loop):
        a, _ = await connect(client)
        b, _ = await connect(client)
        stuck = asyncio.Event()
        sends = []

        async def never_drains(payload: bytes) -> None:
            sends.append(len(payload))
            await stuck.wait()

        viewer_a = next(v for v in loop.viewers.viewers.values() if v.id == 1)
        viewer_a.send = never_drains
        await a.send_json(cam_msg(1))
        for i in range(5):
            await b.send_json(cam_msg(10 + i, 0.1 * i))
            await frame_for(b, 10 + i)
        assert len(sends) == 1, "one frame in flight for the stalled viewer, none queued"
        assert viewer_a.dropped >= 4
        health = await (await client.get("/health")).json()
        assert health["frames_dropped"] == viewer_a.dropped and health["frames_sent"] >= 5
        stuck.set()
        for w in (a, b):
            await w.close()

    run(test)


def test_token_required_off_loopback_and_checked():
    """A non-loopback bind needs a token (the CLI refuses in one line); with a token, /ws without it or with a wrong
    one is refused with 403 before the upgrade, and the right one connects."""
    from volren.cli import main

    with pytest.raises(VolrenError, match="--token"):
        check_bind("0.0.0.0", None)
    check_bind("127.0.0.1", None)
    check_bind("::1", None)
    check_bind("0.0.0.0", "s3cret-token-0123")
    assert main(["serve", "--host", "192.168.1.5", "--port", "8123"]) == 2

    async def test(client, loop):
        for query in ("", "?token=wrong-token"):
            resp = await client.get("/ws" + query)
            assert resp.status == 403
        ws = await client.ws_connect("/ws?token=s3cret-token-0123")
        await ws.send_json({"type": "hello", "width": W, "height": H})
        assert (await ws.receive_json(timeout=TIMEOUT))["type"] == "welcome"
        await ws.close()

    run(test, token="s3cret-token-0123")


def test_token_sources_file_environment_and_flag(tmp_path):
    """Issue 44 item 5: the token comes from --token-file (its content, whitespace and the newline stripped), from
    VOLREN_TOKEN when neither flag is given, or from --token; both flags at once, a missing, empty or overlong file,
    an empty VOLREN_TOKEN and a token breaking the rules are one-line errors naming their source. The line `serve`
    prints shows the token only when --token gave it."""
    good = tmp_path / "token"
    good.write_text("  file-token-0123456789\n")
    env = {"VOLREN_TOKEN": "env-token-0123456789"}
    assert read_token(None, str(good), {}) == ("file-token-0123456789", f"--token-file {good}")
    assert read_token(None, str(good), env) == ("file-token-0123456789", f"--token-file {good}")
    assert read_token(None, None, env) == ("env-token-0123456789", "VOLREN_TOKEN")
    assert read_token("flag-token-0123456789", None, env) == ("flag-token-0123456789", "--token")
    assert read_token(None, None, {}) == (None, None)
    (tmp_path / "empty").write_text(" \n")
    (tmp_path / "short").write_text("short\n")
    (tmp_path / "long").write_bytes(b"x" * 5000)
    (tmp_path / "binary").write_bytes(b"\xff" * 20)
    for flag, path, environ, error in [
            ("flag-token-0123456789", str(good), {}, f"^give either --token or --token-file {good}, not both$"),
            (None, str(tmp_path / "missing"), {}, f"^--token-file {tmp_path / 'missing'}: cannot read it \\(No such"),
            (None, str(tmp_path), {}, f"^--token-file {tmp_path}: cannot read it"),
            (None, str(tmp_path / "empty"), env, f"^--token-file {tmp_path / 'empty'}: the file is empty"),
            (None, str(tmp_path / "short"), {}, f"^the token in --token-file {tmp_path / 'short'} must be 16-256"),
            (None, str(tmp_path / "long"), {}, f"^--token-file {tmp_path / 'long'}: longer than 4096 bytes"),
            (None, str(tmp_path / "binary"), {}, f"^--token-file {tmp_path / 'binary'}: not UTF-8"),
            (None, None, {"VOLREN_TOKEN": ""}, "^VOLREN_TOKEN is set but empty"),
            (None, None, {"VOLREN_TOKEN": "a token with spaces"}, "^the token in VOLREN_TOKEN must be 16-256"),
            ("short", None, env, "^--token must be 16-256")]:
        with pytest.raises(VolrenError, match=error) as exc:
            read_token(flag, path, environ)
        assert "\n" not in str(exc.value)
    assert open_line("0.0.0.0", 8000, "flag-token-0123456789") == \
        "volren serve: open http://0.0.0.0:8000/?token=flag-token-0123456789 (Ctrl-C stops)"
    line = open_line("::", 8000, "file-token-0123456789", f"--token-file {good}")
    assert line == f"volren serve: open http://[::]:8000/?token=<the token in --token-file {good}> (Ctrl-C stops)"
    assert "file-token" not in open_line("h", 1, "env-token-0123456789", "VOLREN_TOKEN")
    assert open_line("127.0.0.1", 8000, None, None) == "volren serve: open http://127.0.0.1:8000/ (Ctrl-C stops)"


def test_serve_cli_takes_the_token_from_a_file_or_the_environment(tmp_path, monkeypatch, capsys):
    """`volren serve --token-file PATH` (and VOLREN_TOKEN) guard the server with the file's token and print no
    warning; --token works too but warns that the process list shows it; a bad source stops the CLI in one line."""
    from volren.cli import main

    served: list[tuple] = []
    # no scene: the token is the test (make_app reads only the loop's limits)
    monkeypatch.setattr("volren.serve.app.build_loop", lambda *args, **kw: types.SimpleNamespace(limits=args[5]))
    monkeypatch.setattr("volren.serve.app.serve", lambda app, host, port, token, source="--token":
                        served.append((app[ACCESS_KEY].token, token, source)))
    monkeypatch.delenv("VOLREN_TOKEN", raising=False)
    path = tmp_path / "token"
    path.write_text("file-token-0123456789\n")
    assert main(["serve", "--host", "0.0.0.0", "--token-file", str(path)]) == 0
    assert served.pop() == ("file-token-0123456789", "file-token-0123456789", f"--token-file {path}")
    assert capsys.readouterr().err == ""
    monkeypatch.setenv("VOLREN_TOKEN", "env-token-0123456789")
    assert main(["serve", "--host", "0.0.0.0"]) == 0
    assert served.pop() == ("env-token-0123456789", "env-token-0123456789", "VOLREN_TOKEN")
    assert capsys.readouterr().err == ""
    assert main(["serve", "--token", "flag-token-0123456789"]) == 0
    assert served.pop()[0] == "flag-token-0123456789"
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "warning: --token is visible to every local user" in err and "--token-file" in err
    for argv, error in [(["--token", "flag-token-0123456789", "--token-file", str(path)], "not both"),
                        (["--token-file", str(tmp_path / "missing")], f"--token-file {tmp_path / 'missing'}: cannot")]:
        assert main(["serve", *argv]) == 2
        err = capsys.readouterr().err
        assert err.startswith("volren: error: ") and error in err and err.count("\n") == 1, err
    assert not served


def test_health_fields_and_port_in_use():
    async def test(client, loop):
        page = await client.get("/")
        assert page.status == 200 and "<html" in (await page.text()).lower()
        health = await (await client.get("/health")).json()
        assert health == {**health, "viewers": 0, "method": "dssrm", "scene": "smoke16", "fps": 0.0, "tick": 0,
                          "renders": 0, "pass_ms": {}}
        ws, _ = await connect(client, width=5000, height=3)  # clamped to the limits
        await ws.send_json(cam_msg(1))
        header, image = await frame_for(ws, 1)
        assert (header["width"], header["height"]) == (128, 16) and image.shape == (16, 128, 3)
        health = await (await client.get("/health")).json()
        assert health["viewers"] == 1 and health["renders"] == health["tick"] == 1
        assert {"march", "light_map"} <= set(health["pass_ms"])
        await ws.close()

    run(test)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        loop = RenderLoop(SCENE, "dssrm", device="cpu", overrides=SMALL)
        with pytest.raises(VolrenError, match=f"--port {port}: address already in use"):
            asyncio.run(_serve(make_app(loop, "smoke16"), "127.0.0.1", port, ""))


def test_playing_advances_the_advected_smoke():
    """While playing, every tick advects the smoke one step (`volren.simulate`) and renders it without any new
    camera: successive frames differ; paused, the loop stops rendering."""
    async def test(client, loop):
        ws, welcome = await connect(client)
        assert welcome["animated"] and not welcome["playing"]
        await ws.send_json(cam_msg(1))
        _, still = await frame_for(ws, 1)
        await ws.send_json({"type": "settings", "playing": True})
        frames = [(await next_frame(ws))[1] for _ in range(3)]
        assert not any(np.array_equal(a, b) for a, b in zip([still, *frames], frames, strict=False)), "steps move"
        assert db(still, frames[0]) > db(still, frames[2]) + 3.0, "and the motion adds up"  # 48.5, 42.6 dB
        await ws.send_json({"type": "settings", "playing": False})
        for _ in range(20):  # a tick under way when the pause arrived still finishes
            ticks = loop.tick
            await asyncio.sleep(0.3)
            if loop.tick == ticks:
                break
        assert loop.tick == ticks, "paused: no rendering"
        await ws.close()

    run(test, animate=animator(SCENE, None, "cpu"))


def test_settings_switch_the_method_for_everyone():
    """A method switch from one viewer changes the shared renderer (a coupled CACRM pair for the stereo viewer) and
    the other viewer is told; both then get frames of the new method."""
    async def test(client, loop):
        a, _ = await connect(client, stereo=True)
        b, _ = await connect(client)
        await a.send_json({"type": "settings", "method": "cacrm"})
        note = await b.receive_json(timeout=TIMEOUT)
        assert note["type"] == "settings" and note["method"] == "cacrm" and note["quality"] == "interactive"
        await a.send_json(cam_msg(1))
        await b.send_json(cam_msg(2, 0.4))
        header, image = await frame_for(a, 1)
        await frame_for(b, 2)
        assert type(loop.renderer).__name__ == "CACRM" and loop.renderer.config.reuse_light_map
        assert header["stereo"] and image.shape == (H, W, 3) and image.std() > 10
        health = await (await client.get("/health")).json()
        assert health["method"] == "cacrm" and health["views"] == 3
        for w in (a, b):
            await w.close()

    run(test)


def test_majorants_rebuilt_only_for_a_new_transfer_function():
    """VPT's majorant octrees are built on the first tick, reused while the transfer function stays, and rebuilt
    when a viewer switches it."""
    async def test(client, loop):
        ws, _ = await connect(client)
        await ws.send_json({"type": "settings", "method": "vpt"})
        passes = []
        for i, tf in enumerate((None, None, "smoke", None)):
            if tf is not None:
                await ws.send_json({"type": "settings", "tf": tf})
            await ws.send_json(cam_msg(i + 1, 0.1 * i))
            header, image = await frame_for(ws, i + 1)
            passes.append("majorants" in header["pass_ms"])
        assert passes == [True, False, True, False]
        assert loop.renderer.config.transfer == "smoke" and image.std() > 5
        await ws.close()

    run(test)


def test_naive_mode_renders_each_viewer_alone():
    """shared=False (the benchmark's naive server): one render call per viewer and tick, each viewer with its own
    renderer; the images are the same."""
    async def test(client, loop):
        viewers = [(await connect(client))[0] for _ in range(2)]
        for i, ws in enumerate(viewers):
            await ws.send_json(cam_msg(1 + i, 0.3 * i))
        for i, ws in enumerate(viewers):
            await frame_for(ws, 1 + i)
        renders, ticks = loop.renders, loop.tick  # from here on every tick has both viewers
        for i, ws in enumerate(viewers):
            await ws.send_json(cam_msg(3 + i, 0.3 * i + 0.1))
        images = [(await frame_for(ws, 3 + i))[1] for i, ws in enumerate(viewers)]
        assert loop.tick > ticks and loop.renders - renders == 2 * (loop.tick - ticks)
        for i, image in enumerate(images):
            assert db(offline(cam_msg(3 + i, 0.3 * i + 0.1)), image) > 40.0
        assert len(loop._own) == 2 and loop._own[1] is not loop._own[2]
        for ws in viewers:
            await ws.close()

    run(test, shared=False)


def test_a_failing_render_is_reported_and_the_loop_goes_on():
    """An unexpected error in a tick reaches every viewer as one error message; the next camera is rendered."""
    async def test(client, loop):
        ws, _ = await connect(client)
        render = loop.renderer.render
        calls = []

        def fails_once(scene, views, frame=0):
            calls.append(frame)
            if len(calls) == 1:
                raise RuntimeError("boom\nsecond line")
            return render(scene, views, frame)

        loop.renderer.render = fails_once
        await ws.send_json(cam_msg(1))
        reply = asyncio.ensure_future(ws.receive_json())
        await asyncio.wait({reply, loop._task}, timeout=TIMEOUT, return_when=asyncio.FIRST_COMPLETED)
        assert not loop._task.done(), "the loop died"
        assert reply.result() == {"type": "error", "message": "render failed: boom"}
        await ws.send_json(cam_msg(2))
        _, image = await frame_for(ws, 2)
        assert image.std() > 10 and not loop._task.done()
        await ws.close()

    run(test)


def masked_text_frame(text: str) -> bytes:
    """A client's WebSocket text frame (RFC 6455 §5.2: clients mask), for a raw-socket client."""
    data, mask = text.encode(), os.urandom(4)
    size = bytes([0x80 | len(data)]) if len(data) < 126 else bytes([0x80 | 126]) + struct.pack(">H", len(data))
    return bytes([0x81]) + size + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data))


def test_a_real_client_that_never_reads_gets_one_frame_then_is_parked():
    """A raw TCP client with a 4 KiB receive buffer says hello at 640x480 and never reads (nor acknowledges) again.
    Flow control: it is handed one frame, never a second (without acknowledgements the kernel buffers swallowed 41
    frames); after PARK_AFTER_S it is parked and left out of the render, while the other viewer is served every
    frame throughout."""
    from volren.serve.loop import PARK_AFTER_S

    async def test(client, loop):
        raw = socket.socket()
        raw.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        raw.connect((client.server.host, client.server.port))
        key = base64.b64encode(os.urandom(16))
        raw.sendall(b"GET /ws HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                    b"Sec-WebSocket-Key: " + key + b"\r\nSec-WebSocket-Version: 13\r\n\r\n")
        raw.sendall(masked_text_frame(json.dumps({"type": "hello", "width": 640, "height": 480})))
        raw.sendall(masked_text_frame(json.dumps(cam_msg(1))))
        await until(lambda: any(v.ready and v.width == 640 for v in loop.viewers.viewers.values()), "the raw hello")
        stalled = next(v for v in loop.viewers.viewers.values() if v.width == 640)
        b, _ = await connect(client)
        for i in range(400):
            await b.send_json(cam_msg(10 + i, 0.001 * i))
            header, _ = await frame_for(b, 10 + i)  # every frame reaches the reading viewer
            if stalled.parked and header["viewers"] == 2 and loop.views_last == 1:
                break
            await asyncio.sleep(0.02)
        assert stalled.parked and loop.views_last == 1, "parked: no longer rendered"
        assert stalled.frames <= 1 and stalled.sending is not None and stalled.dropped >= 1, \
            (stalled.frames, stalled.dropped)
        assert time.monotonic() - stalled.unacked_since >= PARK_AFTER_S
        raw.close()
        await b.close()

    run(test, limits=Limits(4, 640, 480), jpeg_quality=100)


def test_refine_frames_per_method_and_quality():
    """The refinement budget (docs/SERVE.md): VPT 256 paths per pixel, fog until the first frame weighs < 1% of its
    exponential history (0.9^44 = 0.97%, 0.9^43 = 1.08%), accumulating GI its convergence frame count per update of
    every volume (one volume a frame), deterministic methods and precomputed GI 1."""
    from volren.render.gi.ambient import GIConfig
    from volren.serve.loop import refine_frames

    assert [refine_frames(quality_config("vpt", q)) for q in ("interactive", "default", "high")] == [256, 32, 8]
    assert refine_frames(quality_config("fog", "interactive")) == 44
    assert refine_frames(quality_config("fog", "default", temporal=False)) == 1
    assert refine_frames(quality_config("dssrm", "interactive")) == 1
    assert refine_frames(quality_config("dssrm", "interactive", gi=GIConfig(method="sresir"))) == 32
    assert refine_frames(quality_config("dssrm", "interactive", gi=GIConfig(method="sresir")), volumes=3) == 96
    assert refine_frames(quality_config("dssrm", "interactive", gi=GIConfig(method="prt"))) == 1


async def settle(loop) -> None:
    """Until the loop has rendered nothing for 0.3 s (a few ticks at this size)."""
    for _ in range(100):
        renders = loop.renders
        await asyncio.sleep(0.3)
        if loop.renders == renders and not loop.viewers.viewers[1].busy:
            return
    raise AssertionError("the loop never went idle")


def test_vpt_refines_a_still_view_then_idles():
    """Progressive refinement: with a still camera the loop keeps rendering VPT (1 path a frame) and sends the running
    mean, up to the budget (16 frames here), then stops rendering; a camera change starts again from one frame. The
    refined image is closer to a 256-path offline render than the first frame: measured 22.7 -> 32.9 dB. The client
    reads and acknowledges every frame meanwhile (the next frame waits for the acknowledgement)."""
    budget = 16
    cam = Camera(position=cam_msg(1)["position"], look_at=(0, 0, 0), fov_y=45, width=W, height=H)
    ref = display_image(VPT(quality_config("vpt", "interactive", spp=256, seed=99), device="cpu")
                        .render(SCENE, [cam]).images, SCENE.background)

    async def test(client, loop):
        ws, _ = await connect(client)
        await ws.send_json({"type": "settings", "method": "vpt"})
        frames: list[tuple[dict, np.ndarray]] = []

        async def reader() -> None:
            while True:
                frames.append(await next_frame(ws))

        for i in (1, 2):
            renders = loop.renders
            frames.clear()
            await ws.send_json(cam_msg(i, 0.0 if i == 1 else 0.3))
            task = asyncio.create_task(reader())
            await settle(loop)
            task.cancel()
            answered = [f for f in frames if f[0]["camera_id"] == i]
            (header, first), (last_header, last) = answered[0], answered[-1]
            assert header["refine"] == 1, "a change starts the refinement again"
            assert loop.renders - renders == budget, "refines up to the budget, then idles"
            assert last_header["refine"] == budget
            if i == 1:
                gain = db(ref, last) - db(ref, first)
                assert gain > 8.0 and db(ref, last) > 30.0, (db(ref, first), db(ref, last))
        assert loop.tick == loop.renders
        await ws.close()

    run(test, refine=budget, jpeg_quality=95)


def test_a_light_change_uploads_only_the_lights():
    """`upload_lights`: a scene that differs only in its lights keeps the uploaded densities, volume structs and BVH
    (a new DeviceScene with the new lights, so the light map is recomputed) and renders exactly what a fresh upload
    renders; a scene with other volumes, or another number of lights, is uploaded in full."""
    from volren.serve.loop import with_light
    from volren.upload import upload_lights

    cam = Camera(position=(0.3, 0.2, 1.9), look_at=(0, 0, 0), width=W, height=H)
    config = quality_config("dssrm", "interactive", **SMALL)
    r = DSSRM(config, device="cpu")
    r.render(SCENE, [cam])
    ds = r._device_scene
    lit = with_light(SCENE, (0.3, -0.2, 1.0))
    frame = r.render(lit, [cam])
    new = r._device_scene
    assert new is not ds and new.scene is lit
    assert all(getattr(new, f) is getattr(ds, f) for f in ("density", "volumes", "lightmap", "volume_bvh"))
    assert {"upload_lights", "light_map"} <= set(frame.stats.times_ms) and "upload" not in frame.stats.times_ms
    fresh = DSSRM(config, device="cpu").render(lit, [cam])
    assert np.array_equal(frame.images[0], fresh.images[0])
    assert np.abs(frame.images[0] - r.render(SCENE, [cam]).images[0]).max() > 0.05, "the lights differ"
    other = Scene((Volume(SCENE.volumes[0].density, density_scale=5.0),), lit.lights, SCENE.environment)
    two = Scene(SCENE.volumes, (*lit.lights, DirectionalLight()), SCENE.environment)
    assert upload_lights(new, other) is None and upload_lights(new, two) is None


def test_a_frame_dropped_while_busy_is_rendered_again_when_free():
    """Viewer A's frame for its newest camera is dropped because A is still receiving an older one (another viewer's
    camera made the tick); once A is free the loop renders that camera again, so A's last frame shows its newest
    view, never a stale one."""
    async def test(client, loop):
        a, _ = await connect(client)
        b, _ = await connect(client)
        await a.send_json(cam_msg(1))
        await b.send_json(cam_msg(2, 0.4))
        await frame_for(a, 1)
        await frame_for(b, 2)
        viewer = loop.viewers.viewers[1]
        gate, send = asyncio.Event(), viewer.send

        async def held(payload):
            await gate.wait()
            await send(payload)

        viewer.send = held
        await a.send_json(cam_msg(3, 0.2))
        # (not just busy: A's acknowledgement of frame 1 may still be on its way)
        await until(lambda: viewer.shown[0] == 3 and not viewer.sending.done(), "A's frame 3 on its way")
        await a.send_json(cam_msg(4, -0.3))
        await until(lambda: viewer.camera_id == 4, "A's camera 4")
        await b.send_json(cam_msg(5, 0.5))
        await frame_for(b, 5)
        assert viewer.dropped >= 1 and viewer.busy, "A's frame for camera 4 was dropped"
        gate.set()
        _, image = await asyncio.wait_for(frame_for(a, 4), 10.0)
        assert db(offline(cam_msg(4, -0.3)), image) > 40.0
        for ws in (a, b):
            await ws.close()

    run(test)


def test_a_resize_alone_gets_a_frame_of_the_new_size():
    """A window resize sends only {"type": "resize"} (the camera stays): the viewer gets a frame of its unchanged
    camera at the new size, within a few seconds and without any camera message; a stereo viewer's resize keeps both
    eyes side by side; a size over the limits is clamped (128 x 96 here)."""
    def decoded(header, image) -> tuple[int, int]:
        assert image.shape[:2] == (header["height"], header["width"]), "the header tells the JPEG's size"
        return image.shape[1], image.shape[0]

    async def test(client, loop):
        ws, _ = await connect(client)
        await ws.send_json(cam_msg(1))
        header, image = await asyncio.wait_for(frame_for(ws, 1), TIMEOUT)
        assert decoded(header, image) == (W, H)
        for size, want in (((96, 64), (96, 64)), ((5000, 3), (128, 16)), ((W, H), (W, H))):
            await ws.send_json({"type": "resize", "width": size[0], "height": size[1]})
            header, image = await asyncio.wait_for(next_frame(ws), 5.0)
            assert header["camera_id"] == 1 and decoded(header, image) == want, (size, header)
        # the new size renders the same camera: the offline render of camera 1 at 96 x 64
        await ws.send_json({"type": "resize", "width": 96, "height": 64})
        _, image = await asyncio.wait_for(next_frame(ws), 5.0)
        cam = Camera(position=cam_msg(1)["position"], look_at=(0, 0, 0), fov_y=45, width=96, height=64)
        r = DSSRM(quality_config("dssrm", "interactive", **SMALL), device="cpu")
        assert db(display_image(r.render(SCENE, [cam]).images, SCENE.background), image) > 40.0
        await ws.send_json({"type": "settings", "stereo": True})
        header, image = await asyncio.wait_for(next_frame(ws), 5.0)
        assert header["stereo"] and decoded(header, image) == (96, 64)
        await ws.send_json({"type": "resize", "width": 80, "height": 40})
        header, image = await asyncio.wait_for(next_frame(ws), 5.0)
        assert header["stereo"] and header["camera_id"] == 1 and decoded(header, image) == (80, 40)
        await ws.close()

    run(test)


def test_bench_mixed_run_counts_and_goals():
    """`volren bench serve`'s mixed run (issue 20): small clients and a slow reader with and without a big client;
    the pixel budget (1.5x the small run's pixels) gives the big client a smaller frame than it asked for, the slow
    reader gets about one frame per read interval, and the ratios and goals follow from the rows."""
    from volren.bench.serve import GOAL_MIXED_AGE, GOAL_MIXED_P95, run_mixed

    mixed = {"small": 2, "small_size": (48, 32), "big_size": (128, 96), "read_every": 0.3, "budget_factor": 1.5}
    cfg = {"cases": [("fog", "dynamic"), ("dssrm", "smoke")], "resolution": 64, "size": (48, 32), "counts": [3],
           "seconds": 1.0, "min_ticks": 3, "repeats": 1, "camera_hz": 30.0, "mixed": mixed,
           "overrides": {"samples": 32, "light_samples": 8, "light_grid": 8}}
    r = asyncio.run(run_mixed(cfg, "cpu"))
    assert r["method"] == "dssrm" and r["pixel_budget"] == int(1.5 * 3 * 48 * 32)
    without, with_big = r["rows"]
    assert (without["clients"], with_big["clients"]) == (3, 4)
    share = r["pixel_budget"] - 3 * 48 * 32
    assert 0 < with_big["big_pixels"] <= share < 128 * 96, "the big client's frame fits its share"
    assert with_big["big_frames"] > 0
    assert r["p95_ratio"] == with_big["small_p95_ms"] / without["small_p95_ms"]
    assert r["age_tick_times"] == with_big["max_age_ms"] / with_big["tick_ms"]
    assert r["goals"] == ("pass" if r["p95_ratio"] <= GOAL_MIXED_P95 and r["age_tick_times"] <= GOAL_MIXED_AGE
                          else "fail")
