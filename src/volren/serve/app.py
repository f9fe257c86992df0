"""HTTP and WebSocket routes of `volren serve` (aiohttp): the viewer page, /static, /health and /ws.

The page and its scripts are files of the package (static/); /ws speaks the protocol of docs/SERVE.md
(`volren.serve.protocol`) with one `RenderLoop` behind every connection.

Every request passes `guard` first (issue 20 items 1-2): its Host must name the server (the address the connection
came in on, `localhost` on loopback, a --host or --allow-host name: a DNS-rebound name is refused), a WebSocket
upgrade's Origin must be the server's own or an --allow-origin (a page of another site cannot drive the server), and
with a token every route needs it (in the query, or in the cookie the page got with it: issue 44 item 5). Refusals
are answered 403, slowed down once they repeat, and logged one line at a time, rate-limited (`OneLineLog`), like
malformed HTTP requests (`QuietServerLog`) instead of a traceback each.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import hmac
import ipaddress
import json
import logging
import os
import re
import signal
import socket
import sys
import time
from collections import deque
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from aiohttp import WSMsgType, web
from aiohttp.http_exceptions import HttpProcessingError

from volren.camera import Camera
from volren.device import resolve_device
from volren.errors import VolrenError
from volren.scene import Scene
from volren.serve.loop import RenderLoop, animator, log, scene_methods
from volren.serve.protocol import (
    MAX_MESSAGE_BYTES,
    Ack,
    CameraMessage,
    Hello,
    ProtocolError,
    Resize,
    Settings,
    error_message,
    parse_message,
)
from volren.serve.rates import (
    CONNECTS_PER_S,
    ERROR_LIMIT,
    ERROR_WINDOW_S,
    MESSAGE_BURST,
    MESSAGES_PER_S,
    ConnectRates,
    ErrorCount,
    TokenBucket,
)
from volren.serve.viewers import Limits, Viewer

STATIC = Path(__file__).parent / "static"
CLOSE_TRY_AGAIN = 1013
"""WebSocket close code: the server is full, try again later"""
CLOSE_POLICY = 1008
"""WebSocket close code: policy violation (no hello in time)"""
CLOSE_GOING_AWAY = 1001
"""WebSocket close code: the server is shutting down"""
HELLO_TIMEOUT_S = 5.0
"""[s] an upgraded socket must say hello within this, else it is closed; it holds no viewer slot meanwhile (issue 20
item 3: 16 sockets that never said hello locked every viewer out)"""
CAMERA_TIMEOUT_S = 5.0
"""[s] a viewer that said hello must send its first camera within this, else it is closed (1008) and its slot freed
(issue 44 item 2: 16 sockets that said hello and never sent a camera refused 32 of 32 real viewers over 20 s)"""
KEEPALIVE_S = 10.0
"""[s] an HTTP connection with no complete request for this long is closed: idle sockets, slow headers, 1-byte drips
(aiohttp's keepalive timeout runs from the connection's start)"""
TOKEN_CHARS = re.compile(r"[A-Za-z0-9._~-]{16,256}")
"""URL-safe (RFC 3986 unreserved; cookie-safe too) and long enough not to be guessed at the refusal rate below"""
TOKEN_ENV = "VOLREN_TOKEN"
"""the environment variable that gives the token when neither --token nor --token-file does"""
TOKEN_FILE_MAX_BYTES = 4096
"""a --token-file longer than this is refused unread (a token has at most 256 characters; not /dev/zero for ever)"""
TOKEN_COOKIE = "volren_token_{port}"
"""the cookie `index` sets for GET /?token=T; cookies are not port-scoped, so each server's (by its local port) has
its own name: another volren on the same host neither overwrites nor accepts it"""
FREE_REFUSALS, REFUSAL_WINDOW_S, REFUSAL_DELAY_S = 5, 60.0, 0.25
"""past FREE_REFUSALS refusals within REFUSAL_WINDOW_S, each further one is answered after REFUSAL_DELAY_S, one at
a time: at most 4 guesses a second however many connections guess (measured before: 1,176 a second)"""
LOG_INTERVAL_S = 5.0
"""[s] at most one log line per kind of refusal this often; the next one counts those left out"""
SHUTDOWN_S = 2.0
"""[s] from SIGINT or SIGTERM to exit"""
LINGER_S = 1.0
"""[s] a closed socket keeps reading (and dropping) what its client still sends for up to this, until the client
closes its end (`ViewerSocket`)"""


@dataclass(frozen=True)
class Access:
    """Who may talk to the server: the ``token`` every route needs (None: none), the names a request's Host may give
    besides the connection's own address (``hosts``) and the origins besides its own whose pages may open /ws."""

    token: str | None = None
    hosts: tuple[str, ...] = ()
    origins: tuple[str, ...] = ()


LOOP_KEY = web.AppKey("loop", RenderLoop)
SCENE_KEY = web.AppKey("scene", str)
ACCESS_KEY = web.AppKey("access", Access)
SOCKETS_KEY = web.AppKey("sockets", set)
REFUSALS_KEY = web.AppKey("refusals", object)
CONNECTS_KEY = web.AppKey("connects", ConnectRates)


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name: it may resolve anywhere
        return False


ORIGIN = re.compile(r"https?://(\[[0-9a-f:.]+\]|[a-z0-9.-]+)(:\d{1,5})?")
HOST = re.compile(r"(\[[0-9a-f:.]+\]|[a-z0-9.-]+)(:\d{1,5})?")


def check_token(token: str, source: str = "--token") -> None:
    """The token must survive a URL and a cookie unquoted and resist guessing; the error names its ``source``."""
    if not TOKEN_CHARS.fullmatch(token):
        what = "--token" if source == "--token" else f"the token in {source}"
        raise VolrenError(f"{what} must be 16-256 URL-safe characters (letters, digits, - . _ ~), got {len(token)} "
                          "characters" + ("" if len(token) < 16 else " with others among them"))


def read_token(flag: str | None, path: str | None, environ: Mapping[str, str] = os.environ) \
        -> tuple[str | None, str | None]:
    """The server's token and where it came from: ``flag`` (--token: "--token", visible to every local user in the
    process list), the content of the file at ``path`` (--token-file: "--token-file PATH", surrounding whitespace
    and the trailing newline stripped) or ``environ``'s VOLREN_TOKEN (used when neither flag is given: "VOLREN_TOKEN");
    (None, None) when none gives one. Both flags at once, an unreadable, empty or overlong file, an empty
    VOLREN_TOKEN or a token breaking `check_token`'s rules: a one-line `VolrenError` naming the source."""
    if flag is not None and path is not None:
        raise VolrenError(f"give either --token or --token-file {path}, not both")
    if flag is not None:
        token, source = flag, "--token"
    elif path is not None:
        source = f"--token-file {path}"
        try:
            with open(path, "rb") as f:
                data = f.read(TOKEN_FILE_MAX_BYTES + 1)
            text = data.decode()
        except OSError as exc:
            raise VolrenError(f"{source}: cannot read it ({exc.strerror or exc})") from None
        except UnicodeDecodeError:
            raise VolrenError(f"{source}: not UTF-8 text (the token is 16-256 URL-safe characters)") from None
        if len(data) > TOKEN_FILE_MAX_BYTES:
            raise VolrenError(f"{source}: longer than {TOKEN_FILE_MAX_BYTES} bytes (the token is 16-256 URL-safe "
                              "characters)")
        token = text.strip()
        if not token:
            raise VolrenError(f"{source}: the file is empty (write the token in it, 16-256 URL-safe characters)")
    elif TOKEN_ENV in environ:
        token, source = environ[TOKEN_ENV], TOKEN_ENV
        if not token:
            raise VolrenError(f"{TOKEN_ENV} is set but empty: unset it, or set it to a token of 16-256 URL-safe "
                              "characters")
    else:
        return None, None
    check_token(token, source)
    return token, source


def check_bind(host: str, token: str | None, origins: tuple[str, ...] = (), source: str = "--token") -> None:
    """A server reachable from other machines must ask for a token (issue 15 item 5); the token must survive a URL
    unquoted and resist guessing (`check_token`, its error naming ``source``); an allowed origin must be one
    (scheme://host[:port], as browsers send it)."""
    if token is not None:
        check_token(token, source)
    for origin in origins:
        if not ORIGIN.fullmatch(origin.lower()):
            raise VolrenError(f"--allow-origin must be an origin like http://host:port (no path), got {origin[:80]}")
    if token is None and not is_loopback(host):
        raise VolrenError(f"--host {host} is reachable from other machines: give a token too (--token-file FILE, "
                          f"{TOKEN_ENV}=T or --token T; viewers then open http://HOST:PORT/?token=T)")


def camera_json(cam: Camera) -> dict[str, Any]:
    return {"position": list(cam.position), "look_at": list(cam.look_at), "up": list(cam.up), "fov": cam.fov_y}


def welcome(loop: RenderLoop, viewer: Viewer, scene: str) -> dict[str, Any]:
    limits = loop.limits
    return {
        "type": "welcome", "viewer": viewer.id, "scene": scene, "methods": list(loop.methods),
        "qualities": list(loop.choices.qualities), "tfs": list(loop.choices.tfs),
        "limits": {"max_width": limits.max_width, "max_height": limits.max_height,
                   "max_viewers": limits.max_viewers, "pixel_budget": limits.pixel_budget},
        "camera": camera_json(loop.camera), "width": viewer.width, "height": viewer.height, "stereo": viewer.stereo,
        "animated": loop.animated, "walk": loop.scene.fog is not None, "locked": loop.lock_settings,
        **loop.shared_settings(),
    }


async def handle_text(loop: RenderLoop, viewer: Viewer, data: Any) -> None:
    """One client message after the hello; a `ProtocolError` goes back to this client only."""
    msg = parse_message(data, loop.choices)
    if isinstance(msg, Hello):
        raise ProtocolError("hello: already received (send resize or settings to change size or stereo)")
    if isinstance(msg, Ack):
        viewer.ack(msg.tick)
    elif isinstance(msg, CameraMessage):
        viewer.set_camera(msg)
    elif isinstance(msg, Resize):
        viewer.resize(msg.width, msg.height, viewer.stereo, loop.limits)
    elif isinstance(msg, Settings):
        loop.offer(msg, viewer)
    loop.wake()


async def over_rate(ws: web.WebSocketResponse, messages: TokenBucket) -> bool:
    """A message arrived: past MESSAGES_PER_S (after MESSAGE_BURST) close the socket (1008) before parsing it. True
    when it is closed."""
    if messages.take():
        return False
    await ws.close(code=CLOSE_POLICY, message=f"over {MESSAGES_PER_S:g} messages a second".encode())
    return True


async def refuse_message(ws: web.WebSocketResponse, errors: ErrorCount, text: str) -> bool:
    """Send a refused message's error; past ERROR_LIMIT within ERROR_WINDOW_S close the socket (1008) instead. True
    when it is closed."""
    if errors.add():
        await ws.close(code=CLOSE_POLICY, message=f"over {ERROR_LIMIT} refused messages in {ERROR_WINDOW_S:g} s"
                       .encode())
        return True
    await ws.send_str(error_message(text))
    return False


async def greet(ws: web.WebSocketResponse, loop: RenderLoop, scene: str, client: str) -> Viewer | None:
    """The viewer of a socket once it said a valid hello (within HELLO_TIMEOUT_S of the upgrade, anything before it
    refused), welcomed; None when the socket is closed instead (no hello in time, too many refused messages, the
    server full or ``client``'s share of it taken, gone)."""
    errors, messages = ErrorCount(), TokenBucket(MESSAGES_PER_S, MESSAGE_BURST)
    deadline = time.monotonic() + HELLO_TIMEOUT_S
    while (left := deadline - time.monotonic()) > 0:
        try:
            msg = await ws.receive(timeout=left)
        except TimeoutError:
            break
        if msg.type not in (WSMsgType.TEXT, WSMsgType.BINARY) or await over_rate(ws, messages):
            return None
        try:
            hello = parse_message(msg.data, loop.choices)
            if not isinstance(hello, Hello):
                raise ProtocolError(f"{type(hello).__name__.lower()}: send hello first (within "
                                    f"{HELLO_TIMEOUT_S:g} s of connecting)")
        except ProtocolError as exc:
            if await refuse_message(ws, errors, str(exc)):
                return None
            continue
        try:
            viewer = loop.viewers.add(ws.send_bytes, ws.send_str, client)
        except ProtocolError as exc:
            await ws.send_str(error_message(str(exc)))
            await ws.close(code=CLOSE_TRY_AGAIN, message=b"server full")
            return None

        async def close(code: int, reason: str) -> None:
            await ws.close(code=code, message=reason.encode())

        viewer.close, viewer.errors, viewer.messages = close, errors, messages
        viewer.resize(hello.width, hello.height, hello.stereo, loop.limits)
        await ws.send_str(json.dumps(welcome(loop, viewer, scene)))
        return viewer
    await ws.close(code=CLOSE_POLICY, message=f"no hello within {HELLO_TIMEOUT_S:g} s".encode())
    return None


class ViewerSocket(web.WebSocketResponse):
    """aiohttp's WebSocket with a lingering close: aiohttp closes a socket on a message over max_msg_size (1009) as
    soon as its header is read, and the rest of the message, still arriving, made the kernel answer with a reset that
    could discard the close frame before the client read it (issue 44 item 6: a 1 MiB message dropped the socket
    without a close code). Here the close frame is followed by a half-close (FIN), the client's bytes are read on and
    dropped, and the connection ends once the client closes its end or `linger` gives up after LINGER_S."""

    def _close_transport(self) -> None:  # aiohttp's (private) step of every close: a rename brings the reset back,
        # as test_a_message_over_the_size_limit_gets_close_1009_not_a_reset would show
        transport = self._req.transport if self._req is not None else None
        if transport is not None and not transport.is_closing() and transport.can_write_eof():
            with contextlib.suppress(OSError):  # the peer gone already: close
                transport.write_eof()
                return
        super()._close_transport()

    async def linger(self) -> None:
        """Wait (at most LINGER_S) for the client to close its end of a half-closed connection."""
        transport = self._req.transport if self._req is not None else None
        deadline = time.monotonic() + LINGER_S
        while transport is not None and not transport.is_closing() and time.monotonic() < deadline:
            await asyncio.sleep(0.02)


async def websocket(request: web.Request) -> web.StreamResponse:
    app = request.app
    loop = app[LOOP_KEY]
    client = request.remote or ""
    if not app[CONNECTS_KEY].take(client):  # 429, slowed down like every refusal: churn costs a few a second
        await app[REFUSALS_KEY].refuse(request, "connects", f"too many connections from {client}: at most "
                                       f"{CONNECTS_PER_S:g} a second after a burst; try again shortly",
                                       web.HTTPTooManyRequests)
    # aiohttp closes the socket (1009) on messages over max_msg_size (lingering: `ViewerSocket`); those between our
    # limit and it get an error message. No permessage-deflate: JPEG frames do not shrink (see COMPRESS_NOTE in
    # docs/SERVE.md).
    ws = ViewerSocket(max_msg_size=4 * MAX_MESSAGE_BYTES, heartbeat=30.0, compress=False)
    await ws.prepare(request)
    app[SOCKETS_KEY].add(ws)
    viewer = None
    try:
        viewer = await greet(ws, loop, app[SCENE_KEY], client)
        if viewer is None:
            return ws
        camera_by = time.monotonic() + CAMERA_TIMEOUT_S
        while True:
            try:  # until its first camera a viewer holds a slot on a deadline; after it, for as long as it stays
                msg = await ws.receive(timeout=None if viewer.camera is not None else camera_by - time.monotonic())
            except TimeoutError:
                await ws.close(code=CLOSE_POLICY, message=f"no camera within {CAMERA_TIMEOUT_S:g} s".encode())
                break
            if msg.type not in (WSMsgType.TEXT, WSMsgType.BINARY) or await over_rate(ws, viewer.messages):
                break
            try:
                await handle_text(loop, viewer, msg.data)
            except ProtocolError as exc:
                if await refuse_message(ws, viewer.errors, str(exc)):
                    break
    except (ConnectionError, RuntimeError):
        pass  # the client went away while we answered it
    finally:
        app[SOCKETS_KEY].discard(ws)
        if viewer is not None:
            loop.viewers.remove(viewer)
            loop.wake()
        if ws.closed:
            await ws.linger()
    return ws


class OneLineLog:
    """Warnings of one line, at most one per ``key`` every LOG_INTERVAL_S; the next line counts those left out."""

    def __init__(self, logger: logging.Logger, interval: float = LOG_INTERVAL_S) -> None:
        self.logger, self.interval = logger, interval
        self._last: dict[str, float] = {}
        self._left_out: dict[str, int] = {}

    def warn(self, key: str, text: str) -> None:
        now = time.monotonic()
        if now - self._last.get(key, -float("inf")) < self.interval:
            self._left_out[key] = self._left_out.get(key, 0) + 1
            return
        self._last[key] = now
        n = self._left_out.pop(key, 0)
        self.logger.warning(text + (f" (and {n} more since the last such line)" if n else ""))


class QuietServerLog(logging.LoggerAdapter):
    """aiohttp's server logger: a malformed request (an HTTP parse error) becomes one rate-limited line instead of a
    traceback (issue 20 item 8: 513 bytes of traceback per bad request); anything else is logged as before."""

    def __init__(self, lines: OneLineLog) -> None:
        super().__init__(logging.getLogger("aiohttp.server"), {})
        self.lines = lines

    def exception(self, msg: object, *args: object, exc_info: Any = True, **kwargs: Any) -> None:
        if isinstance(exc_info, HttpProcessingError):
            what = " ".join(str(exc_info.message).split())[:100] or type(exc_info).__name__
            remote = args[0] if args else "?"
            self.lines.warn("malformed", f"volren serve: refused a malformed HTTP request from {remote} "
                                         f"({exc_info.code}: {what})")
            return
        super().exception(msg, *args, exc_info=exc_info, **kwargs)


class Refusals:
    """Refused requests: logged (`OneLineLog`) and, past FREE_REFUSALS within REFUSAL_WINDOW_S, answered after
    REFUSAL_DELAY_S one at a time."""

    def __init__(self, lines: OneLineLog) -> None:
        self.lines = lines
        self.times: deque[float] = deque(maxlen=4 * FREE_REFUSALS)
        self._lock: asyncio.Lock | None = None

    async def refuse(self, request: web.Request, key: str, why: str,
                     status: type[web.HTTPClientError] = web.HTTPForbidden) -> None:
        now = time.monotonic()
        self.times.append(now)
        self.lines.warn(key, f"volren serve: refused {request.method} {request.path[:60]} from {request.remote}: "
                             f"{why}")
        if sum(now - t < REFUSAL_WINDOW_S for t in self.times) > FREE_REFUSALS:
            self._lock = self._lock or asyncio.Lock()
            async with self._lock:
                await asyncio.sleep(REFUSAL_DELAY_S)
        raise status(text=why)


def local_address(request: web.Request) -> tuple[str, int | None]:
    """The address and port the request's connection came in on ("", None: unknown)."""
    sockname = request.transport.get_extra_info("sockname") if request.transport is not None else None
    if not sockname or isinstance(sockname, str):
        return "", None
    return str(sockname[0]).split("%")[0].lower(), int(sockname[1])


def cookie_name(request: web.Request) -> str:
    """The name of this server's token cookie (TOKEN_COOKIE): by the port the connection came in on."""
    return TOKEN_COOKIE.format(port=local_address(request)[1] or request.url.port)


def host_allowed(request: web.Request, access: Access) -> bool:
    """Is the request's Host a name of this server (against DNS rebinding)? The address the connection came in on,
    on loopback also `localhost` and `*.localhost` (RFC 6761), and the names in ``access.hosts``."""
    m = HOST.fullmatch(request.headers.get("Host", "").lower())
    if m is None:
        return False
    name = m.group(1).strip("[]").rstrip(".")
    local = local_address(request)[0]
    if name == local or name in access.hosts:
        return True
    return bool(local) and is_loopback(local) and (name in ("localhost", "127.0.0.1", "::1")
                                                    or name.endswith(".localhost"))


@web.middleware
async def guard(request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]) \
        -> web.StreamResponse:
    """Host, then the token (every route), then a WebSocket upgrade's Origin; refusals through `Refusals`. The token
    comes in the query (exactly one token=, as scripts send it and as the page is first opened) or, with no token= in
    the query, in this server's cookie (`cookie_name`), which the page got with its first load."""
    access, refusals = request.app[ACCESS_KEY], request.app[REFUSALS_KEY]
    if not host_allowed(request, access):
        await refusals.refuse(request, "host", f"Host {request.headers.get('Host', '')[:60]!r} is not this server's "
                                               "(add it with --allow-host)")
    if access.token is not None:
        given = request.query.getall("token", [])
        if not given and (cookie := request.cookies.get(cookie_name(request))) is not None:
            given = [cookie]
        if len(given) != 1 or not hmac.compare_digest(given[0].encode(), access.token.encode()):
            await refusals.refuse(request, "token", "missing, repeated or wrong token (open the page as /?token=T)")
    origin = request.headers.get("Origin")
    if origin is not None and request.path == "/ws":  # browsers send one; other clients cannot be a hostile page
        own = f"{request.scheme}://{request.host}".lower()
        if origin.lower() not in (own, *access.origins):
            await refusals.refuse(request, "origin", f"Origin {origin[:60]!r} is not this server's (add it with "
                                                     "--allow-origin)")
    return await handler(request)


async def health(request: web.Request) -> web.Response:
    loop = request.app[LOOP_KEY]
    viewers = list(loop.viewers.viewers.values())
    return web.json_response({
        "viewers": len(viewers), "scene": request.app[SCENE_KEY], **loop.report(),
        "frames_sent": sum(v.frames for v in viewers), "frames_dropped": sum(v.dropped for v in viewers),
    })


async def index(request: web.Request) -> web.StreamResponse:
    """The viewer page. Opened as /?token=T (`guard` checked T), it also sets this server's token cookie (HttpOnly,
    SameSite=Strict, Path=/): the browser sends it with the page's own files, its WebSocket and later loads, so the
    page's script takes the token out of the address bar (history.replaceState) and nothing else carries it. With
    Referrer-Policy no-referrer the token-bearing first URL is not sent on as a Referer either."""
    response = web.Response(text=(STATIC / "index.html").read_text(), content_type="text/html",
                            headers={"Referrer-Policy": "no-referrer", "Cache-Control": "no-store"})
    token = request.app[ACCESS_KEY].token
    if token is not None and "token" in request.query:
        response.set_cookie(cookie_name(request), token, path="/", httponly=True, samesite="Strict",
                            secure=request.secure or None)
    return response


def make_app(loop: RenderLoop, scene: str, token: str | None = None, *, hosts: tuple[str, ...] = (),
             origins: tuple[str, ...] = ()) -> web.Application:
    """The application; the render loop starts and stops with it. ``token``, ``hosts``, ``origins``: `Access`."""
    lines = OneLineLog(log)
    app = web.Application(client_max_size=MAX_MESSAGE_BYTES, middlewares=[guard],
                          handler_args={"keepalive_timeout": KEEPALIVE_S, "logger": QuietServerLog(lines)})
    app[LOOP_KEY], app[SCENE_KEY] = loop, scene
    app[ACCESS_KEY] = Access(token, tuple(h.lower().strip("[]") for h in hosts),
                             tuple(o.lower().rstrip("/") for o in origins))
    app[SOCKETS_KEY], app[REFUSALS_KEY] = set(), Refusals(lines)
    app[CONNECTS_KEY] = ConnectRates(burst=loop.limits.connect_burst)
    app.router.add_get("/", index)
    app.router.add_get("/health", health)
    app.router.add_get("/ws", websocket)
    app.router.add_static("/static", STATIC)

    async def start(_: web.Application) -> None:
        loop.start()

    async def stop(_: web.Application) -> None:
        """Close every socket with 1001 (going away), then stop the loop (its tick abandoned at the next pass)."""
        loop.abandon()
        sockets = list(app[SOCKETS_KEY])
        await asyncio.gather(*(ws.close(code=CLOSE_GOING_AWAY, message=b"server shutting down") for ws in sockets),
                             return_exceptions=True)
        await loop.stop()

    app.on_startup.append(start)
    app.on_shutdown.append(stop)
    return app


async def _serve(app: web.Application, host: str, port: int, ready: str) -> str | None:
    """Serve until SIGINT or SIGTERM; the signal's name."""
    runner = web.AppRunner(app, shutdown_timeout=0.5, handle_signals=False)
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
    stopped: asyncio.Future[str] = asyncio.get_running_loop().create_future()
    for sig in (signal.SIGINT, signal.SIGTERM):
        asyncio.get_running_loop().add_signal_handler(
            sig, lambda name=sig.name: stopped.done() or stopped.set_result(name))
    try:
        name = await stopped
        print(f"volren serve: {name}: closing {len(app[LOOP_KEY].viewers)} viewer(s) and stopping", flush=True)
        return name
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            asyncio.get_running_loop().remove_signal_handler(sig)
        try:
            await asyncio.wait_for(runner.cleanup(), SHUTDOWN_S)
        except TimeoutError:  # `serve` ends the process all the same (before: a traceback and the slow teardown)
            print(f"volren serve: stopping took over {SHUTDOWN_S:g} s; exiting anyway", file=sys.stderr, flush=True)


def build_loop(scene_name: str, method: str | None, quality: str, resolution: int, device: str,
               limits: Limits, lock_settings: bool = False, *, scene: Scene | None = None,
               camera: Camera | None = None, animate: Callable[[], Scene] | None = None, shards: int | None = None,
               ray_address: str | None = None, data_parallel: Any = None) -> RenderLoop:
    """The render loop of a built-in scene: a volume scene at ``resolution`` seen from the CLI's default camera, or
    a fog scene from its own viewpoint; ``method`` None = the first live method that can render it. A ``scene``
    given (a file's, named ``scene_name``) is seen from ``camera`` and played by ``animate`` (None: not animated).
    ``shards``: a `ShardedLoop` of that many Ray actors (on the cluster at ``ray_address``; None: a local one), each
    building the animation itself. ``data_parallel``: a `volren.distributed.regions.RegionEngine` holding the
    given scene's volume in regions, which the loop renders through."""
    from volren.data import BUILTIN_SCENES, builtin_scene
    from volren.data.fog_scenes import FOG_SCENES, fog_scene, fog_scene_camera

    device = resolve_device(device)
    if scene is None:
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
        if shards is not None:  # each shard advects its own smoke: the simulation stays on its device
            animate_in: Callable[[], Callable[[], Scene] | None] = partial(animator, scene, scene_name, device)
        else:
            animate = animator(scene, scene_name, device)
    else:
        animate_in = partial(_given, animate)
    if shards is not None:
        from volren.serve.shards import ShardedLoop

        return ShardedLoop(scene, method or scene_methods(scene)[0], quality, shards=shards, address=ray_address,
                           animate=animate_in, limits=limits, camera=camera, device=device,
                           lock_settings=lock_settings)
    return RenderLoop(scene, method or scene_methods(scene)[0], quality, limits=limits, camera=camera,
                      device=device, animate=animate, lock_settings=lock_settings, data_parallel=data_parallel)


def _given(animate: Callable[[], Scene] | None) -> Callable[[], Scene] | None:
    """A shard's animation factory for a step built in the front end (a volume sequence's player: picklable)."""
    return animate


def open_line(host: str, port: int, token: str | None, source: str | None = "--token") -> str:
    """What `serve` prints once it listens: the URL to open. The token in it only when it came from --token (the
    command line shows it anyway); from a file or VOLREN_TOKEN the line names where it is instead, so the secret
    does not land in a terminal's scrollback or a service's log."""
    shown = f"[{host}]" if ":" in host else host
    url = f"http://{shown}:{port}/"
    if token and source == "--token":
        url += f"?token={token}"
    elif token:
        url += f"?token=<the token in {source}>"
    return f"volren serve: open {url} (Ctrl-C stops)"


def serve(app: web.Application, host: str, port: int, token: str | None, source: str | None = "--token") -> None:
    """Run until SIGINT or SIGTERM, then close every viewer (1001) and end the process with status 0 within
    SHUTDOWN_S: without the interpreter's teardown, which alone took 2.4 s with Warp loaded (2 busy cores). It prints
    `open_line` once listening."""
    asyncio.run(_serve(app, host, port, open_line(host, port, token, source)))
    sys.stdout.flush()
    sys.stderr.flush()
    logging.shutdown()
    os._exit(0)
