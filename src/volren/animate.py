"""Scripted interaction sequences (paper 002 §6: the camera orbits, the light rotates, the transfer function
switches while frames are rendered), and the MP4 writer of ``volren animate``.

A `Sequence` says what changes over its frames; `frame_views` and `frame_scene` give frame i's cameras and scene,
`frame_config` the renderer settings (a transfer-function switch at a given frame). The renderer is kept across
frames, so temporal methods see one continuous interaction.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from volren.camera import Camera
from volren.errors import VolrenError
from volren.scene import DirectionalLight, PointLight, RectLight, Scene, SpotLight


@dataclass(frozen=True)
class Sequence:
    frames: int = 60
    orbit: float = 0.0
    """[deg] the cameras turn about the vertical axis through their look-at point over the sequence"""
    light_orbit: float = 0.0
    """[deg] the lights turn about the vertical axis through the origin over the sequence"""
    switch_frame: int | None = None
    """frame from which ``switch_transfer`` replaces the transfer function (vpt)"""
    switch_transfer: str | None = None
    fps: float = 30.0

    def __post_init__(self) -> None:
        if not 1 <= self.frames <= 100_000:
            raise VolrenError(f"a sequence needs 1 to 100000 frames, got {self.frames}")
        if not (math.isfinite(self.orbit) and math.isfinite(self.light_orbit)):
            raise VolrenError("orbit angles must be finite")
        if (self.switch_frame is None) != (self.switch_transfer is None):
            raise VolrenError("a transfer-function switch needs both its frame and its transfer function")
        if self.switch_frame is not None and not 0 <= self.switch_frame < self.frames:
            raise VolrenError(f"switch frame must lie in [0, {self.frames - 1}], got {self.switch_frame}")
        if not (math.isfinite(self.fps) and 1 <= self.fps <= 240):
            raise VolrenError(f"fps must lie in [1, 240], got {self.fps}")

    def angle(self, total: float, i: int) -> float:
        """[rad] of a rotation by ``total`` degrees at frame i (0 at the first frame, total at the last)."""
        return math.radians(total) * (i / max(self.frames - 1, 1))


def yaw(v: np.ndarray, a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]) @ v


def frame_views(seq: Sequence, views: list[Camera], i: int) -> list[Camera]:
    """The cameras of frame i: each turned by the orbit about the vertical through its look-at point."""
    a = seq.angle(seq.orbit, i)
    out = []
    for cam in views:
        target = np.asarray(cam.look_at)
        out.append(dataclasses.replace(cam, position=tuple(target + yaw(np.asarray(cam.position) - target, a))))
    return out


def frame_scene(seq: Sequence, scene: Scene, i: int) -> Scene:
    """The scene of frame i: every light turned by the light orbit about the vertical through the origin."""
    a = seq.angle(seq.light_orbit, i)
    if a == 0.0:
        return scene
    lights = []
    for light in scene.lights:
        if isinstance(light, DirectionalLight):
            lights.append(dataclasses.replace(light, direction=tuple(yaw(np.asarray(light.direction), a))))
        elif isinstance(light, SpotLight):
            lights.append(dataclasses.replace(light, position=tuple(yaw(np.asarray(light.position), a)),
                                              direction=tuple(yaw(np.asarray(light.direction), a))))
        elif isinstance(light, RectLight):
            lights.append(dataclasses.replace(light, position=tuple(yaw(np.asarray(light.position), a)),
                                              edge_u=tuple(yaw(np.asarray(light.edge_u), a)),
                                              edge_v=tuple(yaw(np.asarray(light.edge_v), a))))
        elif isinstance(light, PointLight):
            lights.append(dataclasses.replace(light, position=tuple(yaw(np.asarray(light.position), a))))
    return dataclasses.replace(scene, lights=tuple(lights))


def frame_config(seq: Sequence, config: Any, i: int) -> Any:
    """The renderer settings of frame i: the switched transfer function from the switch frame on."""
    if seq.switch_frame is None or i < seq.switch_frame:
        return config
    if not hasattr(config, "transfer"):
        raise VolrenError("a transfer-function switch needs --method vpt")
    return dataclasses.replace(config, transfer=seq.switch_transfer)


def write_mp4(path: Path, images: list[np.ndarray], fps: float) -> Path:
    """An H.264 MP4 of uint8 RGB frames (imageio-ffmpeg)."""
    import imageio.v2 as imageio

    with imageio.get_writer(path, fps=fps, codec="libx264", quality=8, macro_block_size=1) as writer:
        for image in images:
            writer.append_data(image)
    return path
