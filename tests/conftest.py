"""Shared test helpers: small homogeneous scenes, cameras with an on-axis centre pixel, host-side ray-box chords."""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest

from volren.camera import Camera
from volren.data import builtin_scene, classic_look
from volren.data.procedural import phantom_density
from volren.render import DSSRM, DSSRMConfig, Reference, ReferenceConfig
from volren.scene import DirectionalLight, Environment, Scene, Volume, scale_translate

DEVICE = os.environ.get("VOLREN_TEST_DEVICE", "cpu")
"""Where the renderers under test run: the CPU here and in CI; `VOLREN_TEST_DEVICE=cuda` runs the suite on a GPU."""


def hard_phantom(resolution: int = 64) -> Scene:
    """The built-in phantom with the hard-edged skull it had before issue 13's partial-volume edges: the case with the
    most fine detail, on which the VSA weights were fitted and the detail-keeping tests were measured, under the
    opacity and light they were measured with (`classic_look`)."""
    scene = classic_look(builtin_scene("phantom", resolution))
    hard = dataclasses.replace(scene.volumes[0], density=phantom_density(resolution, edge_voxels=0.0))
    return dataclasses.replace(scene, volumes=(hard,))


def homogeneous_volume(sigma: float, *, n: int = 8, albedo=0.0, g: float = 0.0, emission=0.0, scale=1.0,
                       translate=(0.0, 0.0, 0.0)) -> Volume:
    return Volume(np.ones((n, n, n), np.float32), scale_translate(scale, translate), density_scale=sigma,
                  albedo=albedo, g=g, emission=emission)


def scene_of(*volumes: Volume, lights=(), ambient=0.0) -> Scene:
    return Scene(volumes, tuple(lights), Environment(ambient))


def axis_camera(position=(0.0, 0.0, 3.0), size=(33, 33), **kw) -> Camera:
    """Odd image sizes put the centre pixel's ray exactly through the look-at point."""
    return Camera(position=position, width=size[0], height=size[1], **kw)


def chords(cam: Camera, lo=(-1, -1, -1), hi=(1, 1, 1)) -> tuple[np.ndarray, np.ndarray]:
    """(t_enter clamped at the near plane, chord length) of every pixel ray through an axis-aligned box, float64."""
    d = cam.ray_directions()
    o = np.asarray(cam.position)
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (np.asarray(lo) - o) / d
        tb = (np.asarray(hi) - o) / d
    t0 = np.nanmax(np.minimum(ta, tb), axis=-1)
    t1 = np.nanmin(np.maximum(ta, tb), axis=-1)
    forward = cam.basis()[2]
    t0 = np.maximum(t0, cam.near / (d @ forward))
    return t0, np.clip(t1 - t0, 0.0, None)


def face_point_np(f: int, u, v) -> np.ndarray:
    """Local point(s) on cube face f at tangent coordinates (u, v), as `volren.render.marching.cubemap.face_point`."""
    a, s = f // 2, 1.0 - 2.0 * (f % 2)
    p = np.zeros((*np.broadcast(u, v).shape, 3))
    p[..., a], p[..., (a + 1) % 3], p[..., (a + 2) % 3] = s, u, v
    return p


def render(method: str, scene: Scene, cams, **config):
    if method == "dssrm":
        return DSSRM(DSSRMConfig(**config), device=DEVICE).render(scene, list(cams))
    return Reference(ReferenceConfig(**config), device=DEVICE).render(scene, list(cams))


@pytest.fixture(params=["dssrm", "reference"])
def method(request) -> str:
    return request.param


def cloud_under_shared_light(resolution: int = 64) -> Scene:
    """The cloud under the light every built-in scene shared before issue 22.10 gave it its own sun and sky: tests
    whose floors were measured so keep them (the brighter sun shifts PSNR by 2-5 dB at coarse light grids)."""
    return dataclasses.replace(builtin_scene("cloud", resolution),
                               lights=(DirectionalLight((-0.5, -1.0, -0.35), (3.0,) * 3),),
                               environment=Environment((0.05, 0.065, 0.09)))


DOWN = DirectionalLight(direction=(0.0, -1.0, 0.0), irradiance=(2.0, 2.0, 2.0))


@pytest.fixture(scope="session")
def ray_cluster():
    """One local Ray cluster (2 CPUs, loopback only) for the test session: starting one costs ~20 s. Tests that use it
    carry ``@pytest.mark.xdist_group("ray")`` so that under ``pytest -n 2 --dist loadgroup`` they share one worker
    and so one start."""
    from volren.distributed.runtime import connect

    ray = connect("tests", num_cpus=2)
    yield ray
    ray.shutdown()
