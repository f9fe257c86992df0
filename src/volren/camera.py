"""Views: pinhole cameras, a stereo rig, and view lists of any length.

Camera space looks down -z with +y up (OpenGL). Pixel (row 0, col 0) is the top-left; rays go through pixel centres.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from volren.errors import VolrenError, flag
from volren.scene import as_vec3

MAX_VIEWS = 1024
"""Views per render: more is almost certainly a typo, and each view is a separate image in memory."""
MAX_PIXELS = 8192 * 8192
"""Per view: 64 Mpixel, a float32 RGBA image of 1 GiB. Larger requests are refused, not attempted."""


@dataclass(frozen=True)
class Camera:
    """A pinhole camera looking from ``position`` at ``look_at``."""

    position: tuple[float, float, float] = (0.0, 0.0, 3.5)
    look_at: tuple[float, float, float] = (0.0, 0.0, 0.0)
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_y: float = 45.0
    """[degrees] vertical field of view."""
    width: int = 640
    height: int = 360
    near: float = 0.01
    """[m] linear depth of the near plane."""
    far: float = 1000.0
    """[m] linear depth of the far plane."""

    def __post_init__(self) -> None:
        for name in ("position", "look_at", "up"):
            object.__setattr__(self, name, tuple(float(v) for v in as_vec3(getattr(self, name), f"camera {name}")))
        if not 0 < self.fov_y < 180:
            raise VolrenError(f"fov must lie in (0, 180) degrees, got {self.fov_y}")
        if int(self.width) != self.width or int(self.height) != self.height or self.width <= 0 or self.height <= 0:
            raise VolrenError(f"image size must be positive integers, got {self.width}x{self.height}")
        if self.width * self.height > MAX_PIXELS:
            raise VolrenError(f"image {self.width}x{self.height} is too large (at most {MAX_PIXELS} pixels per view)")
        if not 0 < self.near < self.far:
            raise VolrenError(f"need 0 < near < far, got near={self.near}, far={self.far}")
        forward = np.subtract(self.look_at, self.position)
        if np.linalg.norm(forward) < 1e-9:
            raise VolrenError("camera position and look-at point coincide")
        up = np.asarray(self.up)
        if np.linalg.norm(np.cross(forward, up)) < 1e-6 * np.linalg.norm(forward) * max(np.linalg.norm(up), 1e-30):
            raise VolrenError(f"camera up {self.up} is parallel to the view direction (or zero)")

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Orthonormal ``(right, up, forward)``; forward is the viewing direction (camera -z)."""
        forward = np.subtract(self.look_at, self.position)
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, self.up)
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        return right, up, forward

    @property
    def tan_half_fov(self) -> float:
        return float(np.tan(np.radians(self.fov_y) * 0.5))

    def view_matrix(self) -> np.ndarray:
        """World to camera space (4x4)."""
        right, up, forward = self.basis()
        m = np.eye(4)
        m[0, :3], m[1, :3], m[2, :3] = right, up, -forward
        m[:3, 3] = -m[:3, :3] @ np.asarray(self.position)
        return m

    def ray_directions(self) -> np.ndarray:
        """Unit world directions through every pixel centre, ``(H, W, 3)`` (used by tests and host-side tools)."""
        right, up, forward = self.basis()
        t = self.tan_half_fov
        aspect = self.width / self.height
        xs = ((np.arange(self.width) + 0.5) / self.width * 2 - 1) * t * aspect
        ys = (1 - (np.arange(self.height) + 0.5) / self.height * 2) * t
        d = forward + xs[None, :, None] * right + ys[:, None, None] * up
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


@dataclass(frozen=True)
class StereoRig:
    """Two eyes offset by -ipd/2 (left, view 0) and +ipd/2 (right) along the camera's right axis, same orientation."""

    camera: Camera
    ipd: float = 0.063
    """[m] interpupillary distance."""

    def __post_init__(self) -> None:
        if not 0 <= self.ipd < 10:
            raise VolrenError(f"ipd must lie in [0, 10) m, got {self.ipd}")

    def eyes(self) -> list[Camera]:
        right = self.camera.basis()[0]
        out = []
        for sign in (-0.5, 0.5):
            offset = right * (sign * self.ipd)
            out.append(
                replace(
                    self.camera,
                    position=tuple(np.add(self.camera.position, offset)),
                    look_at=tuple(np.add(self.camera.look_at, offset)),
                )
            )
        return out


def orbit_views(camera: Camera, count: int, spread_deg: float = 10.0) -> list[Camera]:
    """``count`` viewers on a horizontal arc around the look-at point, ``spread_deg`` apart, centred on ``camera``."""
    if not 1 <= count <= MAX_VIEWS:
        raise VolrenError(f"view count must lie in [1, {MAX_VIEWS}], got {count}")
    target = np.asarray(camera.look_at)
    offset = np.asarray(camera.position) - target
    views = []
    for i in range(count):
        a = np.radians((i - (count - 1) / 2) * spread_deg)
        c, s = np.cos(a), np.sin(a)
        rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        views.append(replace(camera, position=tuple(target + rot @ offset)))
    return views


def make_views(camera: Camera, views: str | int = "stereo", ipd: float = 0.063,
               words: Callable[[str], str] = flag) -> list[Camera]:
    """The view list for ``mono`` (1), ``stereo`` (2 eyes) or an integer N (N viewers on an arc); a bad ``views``
    is refused naming the option in ``words`` (`volren.errors.flag`: ``--views``; `keyword`: ``views=``)."""
    if isinstance(views, str):
        key = views.strip().lower()
        if key == "mono":
            return [camera]
        if key == "stereo":
            return StereoRig(camera, ipd).eyes()
        if not (key.isascii() and key.isdecimal()):
            raise VolrenError(f"{words('views')} must be mono, stereo or a positive integer, got '{views}'")
        views = int(key)
    return orbit_views(camera, int(views))

