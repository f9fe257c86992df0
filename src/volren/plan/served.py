"""What ``volren serve --volume`` shows: the file's scene, framed as `views_from_args` frames it for the largest
viewer image, and a sequence's frames to play (`ServedVolume`). The server's loop plays them
(`volren.serve.loop.sequence_player`); the plan knows no server."""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable
from typing import Any

from volren.plan.options import CliError
from volren.plan.volume import _file_scene, _volume_from_args, check_channel_flags, volume_sequence


@dataclasses.dataclass(frozen=True)
class ServedVolume:
    scene: Any
    """frame 0's `volren.scene.Scene`"""
    camera: Any
    """the `volren.camera.Camera` every viewer starts from"""
    frames: int
    """the sequence's length (1: a single volume)"""
    scene_at: Callable[[int], Any]
    """frame i's scene: the file's frame i in frame 0's lights and environment"""


def served_volume(args: argparse.Namespace) -> ServedVolume | None:
    """``serve --volume``'s scene, camera and frames (None without --volume), every check first."""
    from volren.camera import Camera
    from volren.framing import framed_eye

    check_channel_flags(args)
    if args.volume is None:
        return None
    if args.scene is not None or args.resolution is not None:
        raise CliError("serve --volume shows the file: --scene and --resolution apply to built-in scenes")
    loaded = _volume_from_args(args)
    if loaded.channels:  # `channel_scene` renders each channel by a renderer of its own; the loop has one
        raise CliError(f"serve --volume {args.volume}: a multi-channel volume renders with render and animate only")
    scene = _file_scene(args)
    position, look_at, near, far = framed_eye(loaded.corners_world, (0.0, 1.0, 0.0), Camera.fov_y,
                                              args.max_width / args.max_height)
    played = volume_sequence(args)
    return ServedVolume(scene, Camera(position=position, look_at=look_at, near=near, far=far), 1 if played is None else
                        len(played), lambda i: dataclasses.replace(scene, volumes=_file_scene(args, i).volumes))


@dataclasses.dataclass(frozen=True)
class ServedScene:
    """``serve --volume``'s scene, built where it is called (a region actor of ``serve --data-parallel``,
    `volren.distributed.regions`): picklable, unlike `ServedVolume.scene_at`."""

    args: argparse.Namespace
    cwd: str | None = None

    def __call__(self) -> Any:
        import os

        if self.cwd is not None and os.path.isdir(self.cwd):
            os.chdir(self.cwd)
        served = served_volume(self.args)
        if served is None:
            raise CliError("serve --data-parallel splits the volume of --volume FILE: give one")
        return served.scene
