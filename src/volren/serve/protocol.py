"""The `volren serve` wire protocol (docs/SERVE.md): client messages validated into typed values, frames packed.

Every client message is one JSON text message of at most `MAX_MESSAGE_BYTES`, nested at most `MAX_DEPTH` deep (both
checked before parsing, so a hostile message costs a length test and a bracket scan), with a "type" and only that
type's fields; anything else (unknown type or field, NaN or infinity, a number out of range, a wrong type) raises a
`ProtocolError` whose one-line text goes back to the client as {"type": "error", "message": ...}.
"""

from __future__ import annotations

import json
import math
import re
import struct
from dataclasses import dataclass
from typing import Any

from volren.errors import VolrenError

MAX_MESSAGE_BYTES = 1024
"""a camera message is ~150 bytes (~300 with 17-digit coordinates), every other message less: a longer one is not a
viewer's, and refusing it unparsed keeps the event loop free (issue 20 item 6: 65 KB of nested lists parsed per
message raised another client's round trip from 0.7 ms to 1.1 s)"""
MAX_DEPTH = 2
"""nesting of objects and lists: a message object holding lists of numbers"""
_BRACKETS = re.compile(r"[\[\]{}]")
MAX_COORDINATE = 1e4
"""[m] camera and light-direction components: larger is a typo or an attack (float32 kernels lose precision)"""
MAX_CAMERA_ID = 2**31 - 1
"""ids must increase; a page sending 60 a second takes a year to get here (then it reconnects)"""
MIN_SIDE = 16
"""[px] smallest image side a viewer may ask for (the clamp's floor)"""
MIN_FOV, MAX_FOV = 1.0, 170.0
"""[deg] vertical field of view"""
MIN_ISO, MAX_ISO = 1e-6, 1e6
"""[density] the iso value of mode iso (> 0)"""


class ProtocolError(VolrenError):
    """A client message the server refuses; the text names the field and what is wrong."""


@dataclass(frozen=True)
class Hello:
    width: int
    height: int
    stereo: bool = False


@dataclass(frozen=True)
class CameraMessage:
    id: int
    position: tuple[float, float, float]
    look_at: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov: float = 45.0


@dataclass(frozen=True)
class Ack:
    """The page drew the frame of ``tick`` (flow control: a viewer has at most one frame unacknowledged)."""

    tick: int


@dataclass(frozen=True)
class Resize:
    width: int
    height: int


@dataclass(frozen=True)
class Settings:
    """Only the fields the client sent are set; the others stay None."""

    method: str | None = None
    quality: str | None = None
    tf: str | None = None
    light_dir: tuple[float, float, float] | None = None
    playing: bool | None = None
    stereo: bool | None = None
    mode: str | None = None
    iso_value: float | None = None


Message = Hello | CameraMessage | Ack | Resize | Settings

_FIELDS: dict[str, tuple[set[str], set[str]]] = {
    # type -> (required fields, optional fields), "type" aside
    "hello": ({"width", "height"}, {"stereo"}),
    "camera": ({"id", "position", "look_at"}, {"up", "fov"}),
    "ack": ({"tick"}, set()),
    "resize": ({"width", "height"}, set()),
    "settings": (set(), {"method", "quality", "tf", "light_dir", "playing", "stereo", "mode", "iso_value"}),
}


def _reject_constant(name: str) -> Any:
    raise ProtocolError(f"{name} is not a number this server accepts (finite numbers only)")


def _number(value: Any, field: str, lo: float, hi: float) -> float:
    # bool is an int in Python, not a number in the protocol
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ProtocolError(f"{field} must be a number, got {type(value).__name__}")
    if not (math.isfinite(value) and lo <= value <= hi):
        raise ProtocolError(f"{field} must be a finite number in [{lo:g}, {hi:g}], got {value}")
    return float(value)


def _integer(value: Any, field: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ProtocolError(f"{field} must be an integer, got {type(value).__name__}")
    if not lo <= value <= hi:
        raise ProtocolError(f"{field} must lie in [{lo}, {hi}], got {value}")
    return value


def _vec3(value: Any, field: str) -> tuple[float, float, float]:
    if not isinstance(value, list) or len(value) != 3:
        raise ProtocolError(f"{field} must be a list of 3 numbers")
    return tuple(_number(v, f"{field}[{i}]", -MAX_COORDINATE, MAX_COORDINATE)  # type: ignore[return-value]
                 for i, v in enumerate(value))


def _flag(value: Any, field: str) -> bool:
    if not isinstance(value, bool):
        raise ProtocolError(f"{field} must be true or false, got {type(value).__name__}")
    return value


def _name(value: Any, field: str, choices: tuple[str, ...]) -> str:
    if not isinstance(value, str) or value not in choices:
        shown = value if isinstance(value, str) and len(value) <= 40 else type(value).__name__
        raise ProtocolError(f"{field} must be one of {', '.join(choices)}, got {shown}")
    return value


@dataclass(frozen=True)
class Choices:
    """What a settings message may name (the server's methods, quality presets, transfer functions)."""

    methods: tuple[str, ...]
    qualities: tuple[str, ...]
    tfs: tuple[str, ...]
    modes: tuple[str, ...] = ("dvr",)
    """the light-map marchers' modes (`volren.render.marching.modes.MODES`)"""


def _side(value: Any, field: str) -> int:
    # any positive size is accepted and clamped by the server; the cap only keeps the integer sane
    return _integer(value, field, 1, 1 << 16)


def parse_message(data: str | bytes, choices: Choices) -> Message:
    """One client message, validated; raises `ProtocolError`."""
    if isinstance(data, bytes):
        raise ProtocolError("messages must be JSON text, not binary")
    if len(data) > MAX_MESSAGE_BYTES or len(data.encode()) > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"message too large: {len(data.encode())} bytes (at most {MAX_MESSAGE_BYTES})")
    depth = 0
    for bracket in _BRACKETS.findall(data):  # brackets inside strings count too: no valid message has any
        depth += 1 if bracket in "[{" else -1
        if depth > MAX_DEPTH:
            raise ProtocolError(f"message nested deeper than {MAX_DEPTH} levels")
    try:
        msg = json.loads(data, parse_constant=_reject_constant)
    except (ValueError, RecursionError) as exc:
        raise ProtocolError(f"message is not valid JSON: {str(exc).splitlines()[0][:80]}") from None
    if not isinstance(msg, dict):
        raise ProtocolError("message must be a JSON object with a \"type\"")
    kind = msg.get("type")
    if not isinstance(kind, str) or kind not in _FIELDS:
        shown = kind if isinstance(kind, str) and len(kind) <= 40 else type(kind).__name__
        raise ProtocolError(f"type must be one of {', '.join(_FIELDS)}, got {shown}")
    required, optional = _FIELDS[kind]
    given = set(msg) - {"type"}
    unknown = sorted(given - required - optional)
    if unknown:
        raise ProtocolError(f"{kind}: unknown field(s) {', '.join(f[:40] for f in unknown[:5])}")
    missing = sorted(required - given)
    if missing:
        raise ProtocolError(f"{kind}: missing field(s) {', '.join(missing)}")
    if kind == "hello":
        return Hello(_side(msg["width"], "hello.width"), _side(msg["height"], "hello.height"),
                     _flag(msg.get("stereo", False), "hello.stereo"))
    if kind == "ack":
        return Ack(_integer(msg["tick"], "ack.tick", 0, 2**62))
    if kind == "resize":
        return Resize(_side(msg["width"], "resize.width"), _side(msg["height"], "resize.height"))
    if kind == "camera":
        return CameraMessage(
            _integer(msg["id"], "camera.id", 0, MAX_CAMERA_ID),
            _vec3(msg["position"], "camera.position"),
            _vec3(msg["look_at"], "camera.look_at"),
            _vec3(msg.get("up", [0.0, 1.0, 0.0]), "camera.up"),
            _number(msg.get("fov", 45.0), "camera.fov", MIN_FOV, MAX_FOV),
        )
    fields: dict[str, Any] = {}
    if "method" in msg:
        fields["method"] = _name(msg["method"], "settings.method", choices.methods)
    if "quality" in msg:
        fields["quality"] = _name(msg["quality"], "settings.quality", choices.qualities)
    if "tf" in msg:
        fields["tf"] = _name(msg["tf"], "settings.tf", choices.tfs)
    if "mode" in msg:
        fields["mode"] = _name(msg["mode"], "settings.mode", choices.modes)
    if "iso_value" in msg:
        fields["iso_value"] = _number(msg["iso_value"], "settings.iso_value", MIN_ISO, MAX_ISO)
    if "light_dir" in msg:
        d = _vec3(msg["light_dir"], "settings.light_dir")
        if math.hypot(*d) < 1e-6:
            raise ProtocolError("settings.light_dir must not be zero")
        fields["light_dir"] = d
    for key in ("playing", "stereo"):
        if key in msg:
            fields[key] = _flag(msg[key], f"settings.{key}")
    return Settings(**fields)


def error_message(text: str) -> str:
    return json.dumps({"type": "error", "message": text})


def pack_frame(header: dict[str, Any], jpeg: bytes) -> bytes:
    """A binary frame: uint32 little-endian header length, the UTF-8 JSON header, the JPEG bytes."""
    head = json.dumps({"type": "frame", **header}, separators=(",", ":")).encode()
    return struct.pack("<I", len(head)) + head + jpeg


def unpack_frame(data: bytes) -> tuple[dict[str, Any], bytes]:
    """(header, JPEG bytes) of a binary frame (clients and tests)."""
    (n,) = struct.unpack_from("<I", data)
    return json.loads(data[4:4 + n]), data[4 + n:]
