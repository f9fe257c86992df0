"""HTTP and WebSocket routes of `volren serve` (aiohttp): the viewer page, /static, /health and /ws.

The page and its scripts are files of the package (static/); /ws speaks the protocol of docs/SERVE.md
(`volren.serve.protocol`) with one `RenderLoop` behind every connection.
"""

from __future__ import annotations

import asyncio
import errno
import hmac
import ipaddress
import json
import socket
from pathlib import Path
from typing import Any

from aiohttp import WSMsgType, web

from volren.camera import Camera
from volren.device import resolve_device
from volren.errors import VolrenError
from volren.serve.loop import RenderLoop, animator, scene_methods
from volren.serve.protocol import (
    MAX_MESSAGE_BYTES,
    CameraMessage,
    Hello,
    ProtocolError,
    Resize,
    Settings,
    error_message,
    parse_message,
)
from volren.serve.viewers import Limits, Viewer

STATIC = Path(__file__).parent / "static"
LOOP_KEY = web.AppKey("loop", RenderLoop)
SCENE_KEY = web.AppKey("scene", str)
TOKEN_KEY = web.AppKey("token", str)
CLOSE_TRY_AGAIN = 1013
"""WebSocket close code: the server is full, try again later"""
SEND_BUFFER_BYTES = 128 * 1024
"""SO_SNDBUF of each viewer's socket (Linux doubles it): bounded, so a slow reader's frames wait in our send (and the
next ones are dropped) instead of piling up seconds deep in an autotuned kernel buffer (measured: 41 frames of
640x480 vanished into a non-reading client's unbounded buffers without one drop)"""


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name: it may resolve anywhere
        return False


def check_bind(host: str, token: str | None) -> None:
    """A server reachable from other machines must ask for a token (issue 15 item 5)."""
    if token is not None and not (token.isascii() and token.isprintable() and 8 <= len(token) <= 256):
        raise VolrenError("--token must be 8-256 printable ASCII characters")
    if token is None and not is_loopback(host):
        raise VolrenError(f"--host {host} is reachable from other machines: give --token T too (viewers then "
                          "open http://HOST:PORT/?token=T)")


def camera_json(cam: Camera) -> dict[str, Any]:
    return {"position": list(cam.position), "look_at": list(cam.look_at), "up": list(cam.up), "fov": cam.fov_y}


def welcome(loop: RenderLoop, viewer: Viewer, scene: str) -> dict[str, Any]:
    limits = loop.limits
    return {
        "type": "welcome", "viewer": viewer.id, "scene": scene, "methods": list(loop.methods),
        "qualities": list(loop.choices.qualities), "tfs": list(loop.choices.tfs),
        "limits": {"max_width": limits.max_width, "max_height": limits.max_height,
                   "max_viewers": limits.max_viewers},
        "camera": camera_json(loop.camera), "width": viewer.width, "height": viewer.height, "stereo": viewer.stereo,
        "animated": loop.animated, "walk": loop.scene.fog is not None, **loop.shared_settings(),
    }


async def handle_text(loop: RenderLoop, viewer: Viewer, data: Any, scene: str) -> None:
    """One client message; a `ProtocolError` goes back to this client only."""
    msg = parse_message(data, loop.choices)
    if isinstance(msg, Hello):
        if viewer.width:
            raise ProtocolError("hello: already received (send resize or settings to change size or stereo)")
        viewer.resize(msg.width, msg.height, msg.stereo, loop.limits)
        await viewer.text(json.dumps(welcome(loop, viewer, scene)))
        return
    if not viewer.width:
        raise ProtocolError(f"{type(msg).__name__.lower()}: send hello first")
    if isinstance(msg, CameraMessage):
        viewer.set_camera(msg)
    elif isinstance(msg, Resize):
        viewer.resize(msg.width, msg.height, viewer.stereo, loop.limits)
    elif isinstance(msg, Settings) and loop.apply(msg, viewer):
        loop.broadcast(json.dumps({"type": "settings", **loop.shared_settings()}), skip=viewer)
    loop.wake()


async def websocket(request: web.Request) -> web.StreamResponse:
    app = request.app
    token = app.get(TOKEN_KEY)
    if token is not None and not hmac.compare_digest(request.query.get("token", "").encode(), token.encode()):
        raise web.HTTPForbidden(text="missing or wrong token (open the page as /?token=T)")
    loop = app[LOOP_KEY]
    # aiohttp closes the socket on messages over max_msg_size; those between our limit and it get an error message
    ws = web.WebSocketResponse(max_msg_size=4 * MAX_MESSAGE_BYTES, heartbeat=30.0)
    await ws.prepare(request)
    sock = request.transport.get_extra_info("socket") if request.transport is not None else None
    if sock is not None:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER_BYTES)
    try:
        viewer = loop.viewers.add(ws.send_bytes, ws.send_str)
    except ProtocolError as exc:
        await ws.send_str(error_message(str(exc)))
        await ws.close(code=CLOSE_TRY_AGAIN, message=b"server full")
        return ws
    try:
        async for msg in ws:
            if msg.type not in (WSMsgType.TEXT, WSMsgType.BINARY):
                break
            try:
                await handle_text(loop, viewer, msg.data, app[SCENE_KEY])
            except ProtocolError as exc:
                await ws.send_str(error_message(str(exc)))
    except (ConnectionError, RuntimeError):
        pass  # the client went away while we answered it
    finally:
        loop.viewers.remove(viewer)
        loop.wake()
    return ws


async def health(request: web.Request) -> web.Response:
    loop = request.app[LOOP_KEY]
    viewers = list(loop.viewers.viewers.values())
    return web.json_response({
        "viewers": len(viewers), "method": loop.method, "quality": loop.quality, "scene": request.app[SCENE_KEY],
        "fps": round(loop.fps, 3), "tick": loop.tick, "renders": loop.renders, "views": loop.views_last,
        "shared": loop.shared, "render_ms": round(loop.render_ms, 3), "encode_ms": round(loop.encode_ms, 3),
        "pass_ms": {k: round(v, 3) for k, v in loop.pass_ms.items()},
        "frames_sent": sum(v.frames for v in viewers), "frames_dropped": sum(v.dropped for v in viewers),
    })


async def index(request: web.Request) -> web.StreamResponse:
    return web.FileResponse(STATIC / "index.html")


def make_app(loop: RenderLoop, scene: str, token: str | None = None) -> web.Application:
    """The application; the render loop starts and stops with it."""
    app = web.Application(client_max_size=MAX_MESSAGE_BYTES)
    app[LOOP_KEY], app[SCENE_KEY] = loop, scene
    if token is not None:
        app[TOKEN_KEY] = token
    app.router.add_get("/", index)
    app.router.add_get("/health", health)
    app.router.add_get("/ws", websocket)
    app.router.add_static("/static", STATIC)

    async def start(_: web.Application) -> None:
        loop.start()

    async def stop(_: web.Application) -> None:
        await loop.stop()

    app.on_startup.append(start)
    app.on_shutdown.append(stop)
    return app


async def _serve(app: web.Application, host: str, port: int, ready: str) -> None:
    runner = web.AppRunner(app)
    await runner.setup()
    try:
        await web.TCPSite(runner, host, port).start()
    except OSError as exc:
        await runner.cleanup()
        if exc.errno == errno.EADDRINUSE:
            raise VolrenError(f"--port {port}: address already in use on {host} (pick another --port)") from None
        if isinstance(exc, socket.gaierror) or exc.errno in (errno.EADDRNOTAVAIL, errno.EACCES):
            raise VolrenError(f"--host {host} --port {port}: cannot listen there ({exc.strerror})") from None
        raise
    print(ready, flush=True)
    try:
        await asyncio.Event().wait()
    finally:
        await runner.cleanup()


def build_loop(scene_name: str, method: str | None, quality: str, resolution: int, device: str,
               limits: Limits) -> RenderLoop:
    """The render loop of a built-in scene: a volume scene at ``resolution`` seen from the CLI's default camera, or
    a fog scene from its own viewpoint; ``method`` None = the first live method that can render it."""
    from volren.data import BUILTIN_SCENES, builtin_scene
    from volren.data.fog_scenes import FOG_SCENES, fog_scene, fog_scene_camera

    if scene_name in FOG_SCENES:
        scene = fog_scene(scene_name)
        view = fog_scene_camera(scene_name)
        camera = Camera(position=view["position"], look_at=view["look_at"])
    elif scene_name in BUILTIN_SCENES:
        scene = builtin_scene(scene_name, resolution)
        camera = Camera(position=(0.0, 0.4, 3.2))
    else:
        raise VolrenError(f"--scene: unknown scene '{scene_name}': choose from "
                          f"{', '.join([*BUILTIN_SCENES, *FOG_SCENES])}")
    device = resolve_device(device)
    return RenderLoop(scene, method or scene_methods(scene)[0], quality, limits=limits, camera=camera,
                      device=device, animate=animator(scene, scene_name, device))


def serve(app: web.Application, host: str, port: int, token: str | None) -> None:
    """Run until interrupted (KeyboardInterrupt propagates to the CLI)."""
    shown = f"[{host}]" if ":" in host else host
    url = f"http://{shown}:{port}/" + (f"?token={token}" if token else "")
    asyncio.run(_serve(app, host, port, f"volren serve: open {url} (Ctrl-C stops)"))
