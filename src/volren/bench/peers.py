"""Suite ``peers``: volren against VTK, the CPU volume renderer most users have (issue 24, "Against VTK").

The same volume (the cloud, 128^3 full, 64^3 quick), camera, image size and sample distance, shaded, on an orbit of
N frames around the volume: volren's DSSRM (single scattering with its light-map shadows and the sky's ambient)
against VTK's ``vtkFixedPointVolumeRayCastMapper`` with ``ShadeOn`` (gradient Phong shading, no shadows), off-screen
(an EGL render window: no display, no Xvfb), on all cores (`vtkMultiThreader`'s default thread count).

Equal sample distance: volren takes at most V samples across a box's diagonal (``march_step_count``: steps of
diagonal / V or a little less, so that they fit the ray's span exactly); VTK samples every ``SetSampleDistance``
world units, set to diagonal / V, with ``SetImageSampleDistance(1)`` (a ray per pixel) and
``AutoAdjustSampleDistancesOff`` (VTK would otherwise coarsen them to hit a frame rate). VTK's opacity per sample
is the volren step's 1 - exp(-sigma_t dt): the scalar opacity table holds it at ``SetScalarOpacityUnitDistance`` =
dt. The shading models differ (VTK has no shadows and no phase function), so the images are shown side by side and
their PSNR is only a sanity check that both draw the same view.

Timing: VTK and volren frames are interleaved in one process (frame i of VTK, then of volren), so load from other
processes hits both alike; a round is the whole orbit, and after a warm-up round (VTK's first render, volren's
kernel compilation, upload and light map) the reported ms per frame is the fastest round's mean, of wall time and of
process CPU time (all threads: on a shared machine the figure other jobs disturb least). volren's time is that of
``render`` (all passes, readback included), VTK's that of ``vtkRenderWindow.Render`` (ray casting and drawing the
image). Each takes every core: VTK through `vtkMultiThreader` (``VTK threads``), volren through its CPU launch bands
(`volren.device.launch_rows`, ``volren threads``). The light does not move on the orbit, so volren computes its
light map once (the light-map cache, `volren.render.lightmap.LightMapCache`); the ``light maps`` column counts how
often it did in the timed rounds.
"""

from __future__ import annotations

import os
import time
from dataclasses import replace
from typing import Any

import numpy as np

from volren.bench import Suite, bench_scene
from volren.camera import Camera
from volren.device import cpu_threads
from volren.errors import VolrenError
from volren.imageio import composite, to_srgb8
from volren.metrics import psnr
from volren.progress import case_done
from volren.render import DSSRM, DSSRMConfig
from volren.scene import DirectionalLight, Scene, Volume

FULL = {"scene": "cloud", "resolution": 128, "sizes": [(480, 270), (960, 540)], "frames": 8, "rounds": 5,
        "samples": 360}
QUICK = {"scene": "cloud", "resolution": 64, "sizes": [(240, 135), (480, 270)], "frames": 4, "rounds": 5,
         "samples": 360}
CAMERA = (0.0, 0.4, 3.2)
"""the orbit's first eye (the `resolution` suite's camera); the orbit turns it about the y axis through the centre"""
VTK_AMBIENT, VTK_DIFFUSE = 0.5, 0.7
"""VTK's Phong weights (no specular): the ambient stands in for volren's sky term"""


def matched_sample_distance(volume: Volume, samples: int) -> float:
    """[m] VTK's sample distance for volren's V = ``samples`` across the box's (world) diagonal: diagonal / V."""
    return volume.diagonal / samples


def orbit(camera: Camera, frames: int) -> list[Camera]:
    """``frames`` cameras evenly around the full circle about the vertical axis through ``camera.look_at``."""
    target = np.asarray(camera.look_at)
    offset = np.asarray(camera.position) - target
    views = []
    for i in range(frames):
        a = 2.0 * np.pi * i / frames
        c, s = np.cos(a), np.sin(a)
        views.append(replace(camera, position=tuple(target + np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ offset)))
    return views


def import_vtk() -> Any:
    """VTK's modules this suite uses, or a one-line error naming the extra. The EGL window is chosen before the
    import: VTK's default (X) logs a warning and falls back to EGL when there is no display."""
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    try:
        import vtk
        from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy
    except ImportError as exc:
        raise VolrenError(f"bench peers needs VTK: pip install 'volren[peers]' ({exc})") from exc
    return vtk, numpy_to_vtk, vtk_to_numpy


class VTKPeer:
    """One volume of ``scene`` in VTK's fixed-point CPU ray caster, off-screen, its sample distance matched."""

    def __init__(self, scene: Scene, samples: int, width: int, height: int) -> None:
        vtk, numpy_to_vtk, self._to_numpy = import_vtk()
        if len(scene.volumes) != 1 or len(scene.lights) != 1 or not isinstance(scene.lights[0], DirectionalLight):
            raise VolrenError("bench peers compares one volume under one directional light")
        vol = scene.volumes[0]
        m = vol.to_world
        if not np.allclose(m[:3, :3], np.diag(np.diag(m[:3, :3]))):
            raise VolrenError(f"bench peers places volume '{vol.name}' axis-aligned: its to_world rotates")
        nz, ny, nx = vol.density.shape
        n = np.array([nx, ny, nz])
        scale = np.diag(m[:3, :3])
        self.image_data = image = vtk.vtkImageData()
        image.SetDimensions(nx, ny, nz)
        # volren's voxel i sits at local -1 + (i + 1/2) 2 / n (DESIGN.md); VTK's point i at origin + i spacing
        image.SetSpacing(*(2.0 * scale / n))
        image.SetOrigin(*(m[:3, 3] + scale * (-1.0 + 1.0 / n)))
        image.GetPointData().SetScalars(numpy_to_vtk(np.ascontiguousarray(vol.density, np.float32).reshape(-1),
                                                     deep=True))
        self.sample_distance = matched_sample_distance(vol, samples)
        peak = float(vol.density.max()) or 1.0
        opacity, color = vtk.vtkPiecewiseFunction(), vtk.vtkColorTransferFunction()
        for rho in np.linspace(0.0, peak, 64):
            # one step's opacity 1 - exp(-sigma_t dt) at unit distance dt: VTK applies it per sample unchanged
            opacity.AddPoint(float(rho), float(1.0 - np.exp(-vol.density_scale * rho * self.sample_distance)))
        color.AddRGBPoint(0.0, *vol.albedo)
        color.AddRGBPoint(peak, *vol.albedo)
        prop = vtk.vtkVolumeProperty()
        prop.SetScalarOpacity(opacity)
        prop.SetColor(color)
        prop.SetScalarOpacityUnitDistance(self.sample_distance)
        prop.SetInterpolationTypeToLinear()
        prop.ShadeOn()
        prop.SetAmbient(VTK_AMBIENT)
        prop.SetDiffuse(VTK_DIFFUSE)
        prop.SetSpecular(0.0)
        self.mapper = mapper = vtk.vtkFixedPointVolumeRayCastMapper()
        mapper.SetInputData(image)
        mapper.SetSampleDistance(self.sample_distance)
        mapper.SetImageSampleDistance(1.0)
        mapper.AutoAdjustSampleDistancesOff()
        self.threads = mapper.GetNumberOfThreads()
        volume = vtk.vtkVolume()
        volume.SetMapper(mapper)
        volume.SetProperty(prop)
        self._renderer = vtk.vtkRenderer()
        self._renderer.AddVolume(volume)
        self._renderer.SetBackground(*(float(c) for c in to_srgb8(np.asarray(scene.background)) / 255.0))
        light = vtk.vtkLight()
        light.SetLightTypeToSceneLight()
        light.SetPositional(False)
        light.SetFocalPoint(0.0, 0.0, 0.0)
        light.SetPosition(*(-np.asarray(scene.lights[0].direction, dtype=float)))
        light.SetAmbientColor(1.0, 1.0, 1.0)  # VTK's volume ambient is k_a times this, black by default
        self._renderer.AddLight(light)
        self._window = vtk.vtkRenderWindow()
        self._window.SetOffScreenRendering(1)
        self._window.AddRenderer(self._renderer)
        self._window.SetSize(width, height)
        self.window_class = self._window.GetClassName()
        self._grab = vtk.vtkWindowToImageFilter()
        self._grab.SetInput(self._window)
        self._grab.SetInputBufferTypeToRGB()
        self._grab.ReadFrontBufferOff()

    def render(self, cam: Camera) -> None:
        c = self._renderer.GetActiveCamera()
        c.SetPosition(*cam.position)
        c.SetFocalPoint(*cam.look_at)
        c.SetViewUp(*cam.up)
        c.SetViewAngle(cam.fov_y)  # vertical, as volren's fov_y
        self._renderer.ResetCameraClippingRange()
        self._window.Render()

    def image(self) -> np.ndarray:
        """The last frame as uint8 sRGB (H, W, 3), row 0 at the top."""
        self._grab.Modified()
        self._grab.Update()
        out = self._grab.GetOutput()
        w, h, _ = out.GetDimensions()
        return self._to_numpy(out.GetPointData().GetScalars()).reshape(h, w, 3)[::-1].copy()


def run_size(scene: Scene, cfg: dict[str, Any], width: int, height: int, device: str) -> dict[str, Any]:
    """One image size: interleaved VTK and volren orbits, ms per frame of the fastest round after a warm-up."""
    cams = orbit(Camera(position=CAMERA, width=width, height=height), cfg["frames"])
    peer = VTKPeer(scene, cfg["samples"], width, height)
    ours = DSSRM(DSSRMConfig(samples=cfg["samples"]), device)
    rounds: list[np.ndarray] = []  # per timed round: [VTK, volren] x [wall, CPU] seconds over the orbit
    light_maps, march = 0, []
    for r in range(cfg["rounds"] + 1):  # round 0 warms up
        spent = np.zeros((2, 2))
        for i, cam in enumerate(cams):
            for who in (0, 1):
                wall, cpu = time.perf_counter(), time.process_time()
                if who == 0:
                    peer.render(cam)
                else:
                    frame = ours.render(scene, [cam], frame=i)
                spent[who] += (time.perf_counter() - wall, time.process_time() - cpu)
            if r > 0:
                light_maps += "light_map" in frame.stats.times_ms
                march.append(frame.stats.times_ms["march"])
        if r > 0:
            rounds.append(1e3 * spent / len(cams))
    peer.render(cams[0])
    vtk_image = peer.image()
    ours_image = to_srgb8(composite(ours.render(scene, [cams[0]]).images[0], scene.background))
    case_done(f"VTK and volren, {cfg['frames']} frames of {width}x{height}")
    (vtk_ms, vtk_cpu), (ours_ms, ours_cpu) = np.min(rounds, axis=0).tolist()
    return {"size": f"{width}x{height}", "vtk_ms": vtk_ms, "volren_ms": ours_ms, "ratio": ours_ms / vtk_ms,
            "vtk_cpu_ms": vtk_cpu, "volren_cpu_ms": ours_cpu, "cpu_ratio": ours_cpu / vtk_cpu,
            "volren_march_ms": float(np.median(march)), "light_maps": light_maps,
            "psnr": psnr(vtk_image.astype(np.float32) / 255.0, ours_image.astype(np.float32) / 255.0),
            "vtk_threads": peer.threads, "volren_threads": cpu_threads(), "vtk_window": peer.window_class,
            "sample_distance": peer.sample_distance, "figure": np.concatenate([ours_image, vtk_image], axis=1)}


def run_config(cfg: dict[str, Any], device: str) -> dict[str, Any]:
    scene = bench_scene(cfg["scene"], cfg["resolution"])
    load = os.getloadavg()[0]
    rows = [run_size(scene, cfg, w, h, device) for w, h in cfg["sizes"]]
    figures = {f"{row['size']}-volren-left-vtk-right.png": row.pop("figure") for row in rows}
    columns = [
        ("size", "image", "s"), ("vtk_ms", "VTK [ms/frame]", ".1f"), ("volren_ms", "volren DSSRM [ms/frame]", ".1f"),
        ("ratio", "volren / VTK", ".2f"), ("vtk_cpu_ms", "VTK CPU [ms/frame]", ".1f"),
        ("volren_cpu_ms", "volren CPU [ms/frame]", ".1f"), ("cpu_ratio", "CPU volren / VTK", ".2f"),
        ("volren_march_ms", "volren march [ms]", ".1f"),
        ("light_maps", "light maps", "d"), ("psnr", "PSNR volren vs VTK [dB]", ".1f"),
        ("vtk_threads", "VTK threads", "d"), ("volren_threads", "volren threads", "d"),
    ]
    settings = {k: v for k, v in cfg.items() if k != "sizes"} | {
        "sizes": [f"{w}x{h}" for w, h in cfg["sizes"]], "camera": list(CAMERA), "method": "DSSRM",
        "vtk_mapper": "vtkFixedPointVolumeRayCastMapper", "vtk_window": rows[0]["vtk_window"],
        "sample_distance": rows[0]["sample_distance"], "vtk_shading": {"ambient": VTK_AMBIENT, "diffuse": VTK_DIFFUSE},
        "load_average": [load, os.getloadavg()[0]]}  # 1-minute, before and after: other jobs on the cores
    return {"settings": settings, "rows": rows, "columns": columns, "figures": figures}


def run(quick: bool, device: str) -> dict[str, Any]:
    if not device.startswith("cpu"):
        raise VolrenError("bench peers compares CPU renderers: use --device cpu")
    return run_config(QUICK if quick else FULL, device)


SUITE = Suite("peers", "volren DSSRM against VTK's CPU ray caster: ms per frame at equal sample distance", run)
