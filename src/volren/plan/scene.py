"""A render's scene: a built-in, a fog scene or a ``--volume`` file, with the material, light, mesh and environment
overrides, and the warnings of a density that renders nothing or an opaque box."""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

from volren.plan.options import DEFAULT_RESOLUTION, DEFAULT_SCENE, SCENE_COUNT, CliError, check_scene_name, warn
from volren.plan.volume import BOX_OPTICAL_DEPTH, _file_scene, check_channel_flags

__all__ = ["emission_reading", "flame_defaults", "scene_from_args", "warn_density"]


def scene_from_args(args: argparse.Namespace, time: float = 0.0):
    """The scene the arguments ask for: a built-in (a fog scene at ``time`` [s]) or a volume file, with material and
    light overrides."""
    from volren.data import COUNTED_SCENES, builtin_scene, load_mesh_file
    from volren.data.fog_scenes import FOG_SCENES, fog_scene
    from volren.scene import DirectionalLight, Environment, Plane, Sphere

    check_channel_flags(args)
    if getattr(args, "grid", None) is not None and getattr(args, "volume", None) is None:
        raise CliError("--grid names a grid of a .vdb --volume; there is no --volume")
    if getattr(args, "volume", None) is not None:
        if args.scene is not None:
            raise CliError("give either --scene or --volume, not both")
        if args.resolution is not None:
            raise CliError("--resolution applies to built-in volume scenes only; --volume's file sets its own voxels")
        scene = _file_scene(args)
    elif getattr(args, "scene", None) in FOG_SCENES:
        if args.resolution is not None:
            raise CliError(f"--resolution applies to built-in volume scenes only, not to fog scene '{args.scene}'")
        scene = fog_scene(args.scene, time)
    else:
        name = getattr(args, "scene", None)
        check_scene_name(name)
        name = DEFAULT_SCENE if name is None else name
        if args.count is not None and name not in COUNTED_SCENES:
            raise CliError(f"--count applies to --scene {', '.join(COUNTED_SCENES)} only, not to scene '{name}'")
        resolution = DEFAULT_RESOLUTION if args.resolution is None else args.resolution
        scene = builtin_scene(name, resolution, count=SCENE_COUNT if args.count is None else args.count, seed=args.seed)
    check_fire_flags(args, scene)
    volumes = _with_material(args, scene.volumes)
    warn_density(volumes, transfer=args.tf is not None)
    lights = list(scene.lights)
    if args.light_dir is not None or args.light_irradiance is not None:
        idx = next((i for i, lt in enumerate(lights) if isinstance(lt, DirectionalLight)), None)
        base = lights[idx] if idx is not None else DirectionalLight()
        new = dataclasses.replace(
            base,
            **({"direction": args.light_dir} if args.light_dir is not None else {}),
            **({"irradiance": args.light_irradiance} if args.light_irradiance is not None else {}),
        )
        if idx is None:
            lights.append(new)
        else:
            lights[idx] = new
    lights += [rect_light(*r) for r in args.rect_light]
    if args.ambient is not None and args.environment is not None:
        raise CliError("give either --ambient or --environment, not both")
    opaque = list(scene.opaque) + [Sphere(tuple(s[:3]), s[3]) for s in args.sphere]
    alphas = mesh_alphas(args.mesh_alpha, len(args.mesh))
    opaque += [load_mesh_file(m, scale=args.mesh_scale, translate=args.mesh_translate, alpha=a)
               for m, a in zip(args.mesh, alphas, strict=True)]
    if args.ground is not None:
        opaque.append(Plane((0.0, args.ground, 0.0), (0.0, 1.0, 0.0)))
    environment = scene.environment
    if args.ambient is not None:
        environment = Environment(args.ambient)
    elif args.environment is not None:
        environment = named_environment(args.environment)
    background = args.background if args.background is not None else scene.background
    if getattr(args, "volume", None) is not None and getattr(args, "emission_scale", None) is None:
        volumes = flame_defaults(volumes, lights, environment)
    return dataclasses.replace(scene, volumes=volumes, lights=tuple(lights), environment=environment,
                               background=background, opaque=tuple(opaque))


def flame_defaults(volumes: tuple, lights, environment) -> tuple:
    """A file's volumes with the default emission scale of their emission grids (`flame_emission_scale`, relative
    to the white W = sum(Y(directional irradiance)) / pi + Y(mean environment radiance) of these lights; W = 3 / pi,
    the default light's, where there is no light)."""
    import numpy as np

    from volren.blackbody import flame_emission_scale, luminance
    from volren.scene import DirectionalLight

    white = sum(float(luminance(lt.irradiance)) for lt in lights if isinstance(lt, DirectionalLight)) / math.pi
    white += float(luminance(environment.mean_radiance()))
    white = white if white > 0 else float(luminance(DirectionalLight().irradiance)) / math.pi
    out = []
    for v in volumes:
        if v.emission_grid is not None:
            voxel = abs(float(np.linalg.det(v.to_world[:3, :3]))) * 8.0 / v.density.size
            scale = flame_emission_scale(v.emission_u, v.density, v.density_scale, *v.temperature_range, voxel, white)
            v = dataclasses.replace(v, emission_scale=scale)
        out.append(v)
    return tuple(out)


def named_environment(name: str | Path):
    """``--environment`` (``environment=``): a built-in environment's name (``sky``), else an equirectangular image
    file (``.npy`` linear, PNG or JPEG sRGB)."""
    from volren.data.environments import ENVIRONMENTS
    from volren.imageio import load_image
    from volren.scene import Environment

    if str(name) in ENVIRONMENTS:
        return ENVIRONMENTS[str(name)]()
    return Environment(image=load_image(name)[..., :3])


def emission_reading(args: argparse.Namespace, scene) -> dict:
    """stats.json's ``emission_grid`` for a file's emission grid, and one line on stdout: how its values became
    temperatures (kelvin, relative, or relative by --temperature-range) and the emission scale; nothing without."""
    from volren.blackbody import FLAME_CONTRAST, positive_range

    volume = next((v for v in scene.volumes if v.emission_grid is not None), None)
    if getattr(args, "volume", None) is None or volume is None:
        return {}
    values = list(positive_range(volume.emission_grid) or (0.0, 0.0))
    k0, k1 = volume.temperature_range
    if args.temperature_range is not None:
        reading, said = "relative", f"as relative (--temperature-range), mapped to {k0:g}..{k1:g} K"
        kelvin = [k0, k1]
    elif k0 == 0:
        reading, said = "kelvin", f"as kelvin ({values[0]:.4g}..{values[1]:.4g} K)"
        kelvin = values
    else:
        reading, said = "relative", f"as relative (values {values[0]:.4g}..{values[1]:.4g}), mapped to {k0:g}..{k1:g} K"
        kelvin = [k0, k1]
    given = args.emission_scale is not None
    rule = "--emission-scale" if given else f"default: the flame {FLAME_CONTRAST:g}x a lit white surface"
    print(f"volren: emission grid '{args.emission_grid}' read {said}; emission scale {volume.emission_scale:.4g} "
          f"W/(m^3 sr) ({rule})")
    return {"emission_grid": {"name": args.emission_grid, "reading": reading, "values": values, "kelvin": kelvin,
                              "temperature_range_given": args.temperature_range is not None,
                              "emission_scale": volume.emission_scale,
                              "emission_scale_rule": "--emission-scale" if given else "flame"}}


OPAQUE_VOXEL_DEPTH = 100.0
"""optical depth of one voxel beyond which a volume renders as an opaque box (transmittance e^-100 per voxel)"""
THIN_BOX_DEPTH = 0.05
"""optical depth at the densest value across the box's longest side below which a volume renders all but empty
(alpha under 5% in every pixel)"""
EMPTY_ALPHA = 0.01
"""a render whose alpha stays below this in every pixel of every view shows nothing of its --volume"""


def warn_density(volumes: tuple, transfer: bool) -> None:
    """Warn of a density that renders nothing (all zero), all but nothing (the densest value's optical depth across
    the box's longest side under `THIN_BOX_DEPTH`: a float file of tiny values, or a --density-scale [1/m] meant for
    a box in metres on one in micrometres) or an opaque box (the densest voxel's optical depth over
    `OPAQUE_VOXEL_DEPTH`, sigma_t = density_scale * density); a --tf reads density / its maximum, so only the first.
    A density_scale of 0 asks for nothing and gets no warning."""
    import numpy as np

    from volren.scene import box_longest_side, box_sides

    for v in volumes:
        hi = float(v.density.max())
        voxel = float(np.min(box_sides(v.to_world) / np.array(v.density.shape[::-1])))
        side = box_longest_side(v.to_world)
        if hi == 0:
            warn(f"volume '{v.name}' has an all-zero density: it renders nothing")
        elif not transfer and hi * v.density_scale * voxel > OPAQUE_VOXEL_DEPTH:
            warn(f"volume '{v.name}' is opaque (optical depth {hi * v.density_scale * voxel:.3g} in its densest "
                 "voxel): check --density-scale")
        elif not transfer and 0 < hi * v.density_scale * side < THIN_BOX_DEPTH:
            warn(f"volume '{v.name}' renders all but empty (optical depth {hi * v.density_scale * side:.3g} at its "
                 f"densest across its {side:.3g} m box): set --density-scale [1/m] to about "
                 f"{BOX_OPTICAL_DEPTH / (hi * side):.3g}")


def rect_light(x: float, y: float, z: float, width: float, height: float, radiance: float):
    """``--rect-light``: a width x height rectangle at (x, y, z) facing the origin (its height along the world's up,
    projected)."""
    import numpy as np

    from volren.scene import RectLight

    if not (width > 0 and height > 0):
        raise CliError(f"--rect-light needs a positive width and height, got {width} and {height}")
    position = np.array([x, y, z])
    if np.linalg.norm(position) < 1e-9:
        raise CliError("--rect-light cannot sit at the origin it faces")
    normal = -position / np.linalg.norm(position)
    up = np.array([0.0, 1.0, 0.0]) if abs(normal[1]) < 0.99 else np.array([1.0, 0.0, 0.0])
    u = np.cross(up, normal)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    # Emission faces edge_u x edge_v = normal.
    return RectLight(tuple(position), tuple(0.5 * width * u), tuple(0.5 * height * v), (radiance,) * 3)


def check_fire_flags(args: argparse.Namespace, scene) -> None:
    """--emission-grid names a grid of a .vdb --volume; --temperature-range and --emission-scale need a volume with
    an emission grid (--emission-grid or the fire scene): elsewhere they would do nothing."""
    if getattr(args, "emission_grid", None) is not None and getattr(args, "volume", None) is None:
        raise CliError("--emission-grid names a second grid of a .vdb --volume; there is no --volume (the fire scene "
                       "has its own)")
    flags = [f for f, k in (("--temperature-range", "temperature_range"), ("--emission-scale", "emission_scale"))
             if getattr(args, k, None) is not None]
    if flags and not any(v.emission_grid is not None for v in scene.volumes):
        raise CliError(f"{', '.join(flags)} set the blackbody emission of an emission grid: give --emission-grid "
                       "NAME with a .vdb --volume, or --scene fire")
    scale = getattr(args, "emission_scale", None)
    if scale is not None and not (math.isfinite(scale) and scale >= 0):
        raise CliError(f"--emission-scale must be a finite number >= 0, got {scale:g}")


def _with_material(args: argparse.Namespace, volumes: tuple) -> tuple:
    """``volumes`` with the material flags' values in place of their own."""
    names = ("density_scale", "albedo", "g", "emission", "temperature_range", "emission_scale")
    material = {k: getattr(args, k) for k in names if getattr(args, k) is not None}
    return tuple(dataclasses.replace(v, **material) for v in volumes) if material else volumes


def mesh_alphas(values: list[float], meshes: int) -> list[float]:
    """One opacity per --mesh from --mesh-alpha: none (all opaque), one for all, or one each."""
    if len(values) not in (0, 1, meshes):
        raise CliError(f"--mesh-alpha given {len(values)} times for {meshes} --mesh: give it once or once per --mesh")
    bad = [a for a in values if not 0.0 <= a <= 1.0]
    if bad:
        raise CliError(f"--mesh-alpha must lie in [0, 1], got {bad[0]:g}")
    return values * meshes if len(values) == 1 else values or [1.0] * meshes
