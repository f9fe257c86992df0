"""Scene model: volumes, lights, environment and background. Plain data; no rendering logic.

Conventions (DESIGN.md): world is right-handed, y up, metres. A volume's density grid is a numpy array laid out
``[z, y, x]``; its ``to_world`` 4x4 matrix maps the local cube [-1, 1]^3 onto the world. Extinction is
``sigma_t = density_scale * density`` [1/m], scattering ``sigma_s = albedo * sigma_t``, emission adds
``emission * density`` [W/(m^3 sr)] of radiance per metre, and the phase function is Henyey-Greenstein with ``g``.

Fire (``Volume.emission_grid``): a second grid (a simulation's temperature, heat or flame) adds blackbody radiance
``table(u(x))`` per metre, u the grid normalised to [0, 1] and sampled trilinearly, then looked up in the volume's
blackbody table (`volren.blackbody`): temperature is interpolated, not colour, as the colour is nonlinear in T. It is
not multiplied by the density (a flame glows where its soot is thin), but it is emitted only where the density is
> 0: the medium's own extent, so empty-space skipping, the marches' shading of non-empty samples and the path
tracer's collision estimator E / mu_t (which needs mu_t > 0 wherever E > 0) all stay exact with no extra extinction.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from volren.blackbody import blackbody_table
from volren.errors import VolrenError
from volren.sparse import SparseGrid

RGB = tuple[float, float, float]


def as_rgb(value: float | Sequence[float], what: str) -> RGB:
    """Accept a scalar (grey) or three numbers; refuse anything else with a message that names ``what``."""
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.size == 1:
        arr = np.repeat(arr, 3)
    if arr.size != 3 or not np.all(np.isfinite(arr)):
        raise VolrenError(f"{what} must be one number or three finite numbers, got {value!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


def as_vec3(value: Sequence[float], what: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.size != 3 or not np.all(np.isfinite(arr)):
        raise VolrenError(f"{what} must be three finite numbers, got {value!r}")
    return arr


def validate_density(density: np.ndarray | SparseGrid, what: str = "density") -> np.ndarray | SparseGrid:
    """Return ``density`` as C-ordered float32 ``[z, y, x]`` (a `SparseGrid` as it is) or raise a one-line error
    saying what is wrong."""
    if getattr(density, "streamed", False):  # a `volren.stream.density.StreamedDensity`: mapped as it is read
        return density
    if isinstance(density, SparseGrid):
        lo, hi = float(density.min()), float(density.max())
        if not (np.isfinite(lo) and np.isfinite(hi)):
            raise VolrenError(f"{what} has NaN/Inf values; clean the data first")
        if lo < 0:
            raise VolrenError(f"{what} has negative values (down to {lo:.3g}); densities must be >= 0")
        return density
    arr = np.asarray(density)
    if arr.ndim != 3:
        raise VolrenError(f"{what} must be a 3D array [z, y, x], got {arr.ndim} dimension(s) with shape {arr.shape}")
    if min(arr.shape) < 2:
        raise VolrenError(f"{what} has shape {arr.shape}: every axis needs at least 2 voxels")
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise VolrenError(f"{what} must hold real numbers, got dtype {arr.dtype}")
    # two reductions without temporaries (NaN propagates into min and max, Inf shows there): 14x faster than the
    # element-wise checks on a 256 MiB grid; those run only to count what is wrong
    lo, hi = (float(arr.min()), float(arr.max()))
    if not (np.isfinite(lo) and np.isfinite(hi)):
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        raise VolrenError(f"{what} has {bad} NaN/Inf value(s); clean the data first")
    if max(-lo, hi) > float(np.finfo(np.float32).max):  # a Python float: NumPy 2 would cast it to float32
        huge = int(np.count_nonzero(np.abs(arr) > np.finfo(np.float32).max))
        raise VolrenError(f"{what} has {huge} value(s) beyond the float32 range; rescale the data first")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    negative = int(np.count_nonzero(arr < 0)) if lo < 0 else 0  # after the cast: -1e-50 becomes -0.0
    if negative:
        raise VolrenError(f"{what} has {negative} negative value(s); densities must be >= 0")
    return arr


def box_sides(to_world: np.ndarray) -> np.ndarray:
    """[m] (x, y, z) sides of the box that ``to_world`` maps the local cube [-1, 1]^3 onto."""
    return 2.0 * np.linalg.norm(np.asarray(to_world, dtype=np.float64)[:3, :3], axis=0)


def box_longest_side(to_world: np.ndarray) -> float:
    """[m] the longest side of that box (`box_sides`): what a loaded volume's or a channel's default opacity is
    relative to."""
    return float(np.max(box_sides(to_world)))


def scale_translate(scale: float | Sequence[float] = 1.0, translate: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """A ``to_world`` matrix mapping [-1, 1]^3 to a box of half-extent ``scale`` centred at ``translate``."""
    s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
    m = np.eye(4)
    m[0, 0], m[1, 1], m[2, 2] = s
    m[:3, 3] = as_vec3(translate, "translate")
    return m


def _downsample(grid: np.ndarray, reduce: str) -> np.ndarray:
    """Halve each axis (longer than 1) with a 2x2x2 mean or max; odd axes repeat their last voxel."""
    pads = [(0, n % 2) if n > 1 else (0, 0) for n in grid.shape]
    g = np.pad(grid, pads, mode="edge")
    shape = []
    for n in g.shape:
        shape += [max(n // 2, 1), 2 if n > 1 else 1]
    blocks = g.reshape(shape)
    op = np.mean if reduce == "mean" else np.max
    return op(blocks, axis=(1, 3, 5)).astype(np.float32)


def _dilate_max(grid: np.ndarray) -> np.ndarray:
    """Max over each voxel's 3x3x3 neighbourhood (edges clamped)."""
    g = np.pad(grid, 1, mode="edge")
    out = grid.copy()
    nz, ny, nx = grid.shape
    for dz in range(3):
        for dy in range(3):
            for dx in range(3):
                np.maximum(out, g[dz : dz + nz, dy : dy + ny, dx : dx + nx], out=out)
    return out


@dataclass(frozen=True, eq=False)
class Volume:
    """A density grid placed in the world.

    ``density`` is ``[z, y, x]``; voxel i of n along an axis sits at local ``-1 + (i + 0.5) * 2 / n`` and sampling is
    trilinear between centres, clamped at the border.
    """

    density: np.ndarray | SparseGrid
    """[z, y, x], dense or bricked (`volren.sparse.SparseGrid`: a sparse file loaded without a dense copy)"""
    to_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    density_scale: float = 10.0
    """[1/m] per unit density: sigma_t = density_scale * density."""
    albedo: RGB = (0.9, 0.9, 0.9)
    """single-scattering albedo sigma_s / sigma_t per RGB channel, in [0, 1]."""
    g: float = 0.0
    """Henyey-Greenstein asymmetry, in (-1, 1)."""
    emission: RGB = (0.0, 0.0, 0.0)
    """[W/(m^3 sr)] per unit density: emitted radiance added per metre is emission * density."""
    name: str = "volume"
    value_range: tuple[float, float] | None = None
    """the Hounsfield units that density 0 and 1 stand for (a CT, as the loader normalised it): transfer functions
    with a Hounsfield form classify by HU; None: not HU, transfer functions read density / its maximum."""
    emission_grid: np.ndarray | SparseGrid | None = None
    """[z, y, x] source of blackbody emission, the density's shape (module docstring, "Fire"): a value v > 0 is at
    K0 + (K1 - K0) v / max(v) kelvin (``temperature_range``); v <= 0 emits nothing. None: no fire."""
    temperature_range: tuple[float, float] = (1000.0, 3000.0)
    """[K] (K0, K1), 0 <= K0 < K1: the temperatures of ``emission_grid``'s values 0+ and max; (0, max(v)) reads the
    values as kelvin, T = v (a loaded grid whose values look like kelvin, `volren.blackbody.kelvin_span`)"""
    emission_scale: float = 1.0
    """[W/(m^3 sr)] the luminance Y of the blackbody radiance emitted per metre at K1 (`volren.blackbody`)"""
    owned_cells: tuple[tuple[int, int, int], tuple[int, int, int]] | None = None
    """data-parallel rendering (issue 43): the trilinear cells (z, y, x) [first, last + 1) this copy of the volume
    renders, a region's (`volren.dataparallel.region_volume`); its marches take only the samples in them
    (`volren.kernels.common.owns_sample`), and its density need hold only their bricks. None: the whole volume"""

    def __post_init__(self) -> None:
        object.__setattr__(self, "density", validate_density(self.density, f"volume '{self.name}' density"))
        if self.owned_cells is not None:
            lo, hi = (tuple(int(c) for c in corner) for corner in self.owned_cells)
            cells = [n - 1 for n in self.density.shape]
            if (len(lo), len(hi)) != (3, 3) or not all(0 <= a < b <= n for a, b, n in zip(lo, hi, cells, strict=True)):
                raise VolrenError(f"volume '{self.name}': owned_cells {list(lo)}..{list(hi)} is not a box of its "
                                  f"{list(cells)} cells (z, y, x)")
            object.__setattr__(self, "owned_cells", (lo, hi))
        self._check_fire()
        if self.value_range is not None:
            vr = tuple(float(v) for v in self.value_range)
            if len(vr) != 2 or not all(np.isfinite(vr)) or not vr[0] < vr[1]:
                raise VolrenError(f"volume '{self.name}': value_range must be two finite values lo < hi, "
                                  f"got {self.value_range}")
            object.__setattr__(self, "value_range", vr)
        m = np.asarray(self.to_world, dtype=np.float64)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise VolrenError(f"volume '{self.name}': to_world must be a finite 4x4 matrix")
        # scale-free: a micrometre box (det ~1e-15 m^3) is fine, parallel or zero axes are not
        scale = float(np.prod(np.linalg.norm(m[:3, :3], axis=0)))
        if not abs(np.linalg.det(m[:3, :3])) > 1e-9 * scale or not np.allclose(m[3], [0, 0, 0, 1]):
            raise VolrenError(f"volume '{self.name}': to_world must be an invertible affine matrix")
        object.__setattr__(self, "to_world", m)
        if not (np.isfinite(self.density_scale) and self.density_scale >= 0):
            raise VolrenError(f"volume '{self.name}': density_scale must be >= 0, got {self.density_scale}")
        albedo = as_rgb(self.albedo, "albedo")
        if min(albedo) < 0 or max(albedo) > 1:
            raise VolrenError(f"volume '{self.name}': albedo must lie in [0, 1], got {albedo}")
        object.__setattr__(self, "albedo", albedo)
        if not -1 < self.g < 1:
            raise VolrenError(f"volume '{self.name}': HG g must lie in (-1, 1), got {self.g}")
        emission = as_rgb(self.emission, "emission")
        if min(emission) < 0:
            raise VolrenError(f"volume '{self.name}': emission must be >= 0, got {emission}")
        object.__setattr__(self, "emission", emission)

    def __repr__(self) -> str:
        """A summary, not the voxels (issue 42: a 48^3 volume's repr was 1,936 characters of array)."""
        nx, ny, nz = self.resolution
        size = box_sides(self.to_world)
        centre = ", ".join(f"{c:.3g}" for c in self.center_world)
        lo, hi = float(self.density.min()), float(self.density.max())
        parts = [f"{self.name!r}", f"{nx}x{ny}x{nz} {self.density.dtype} (x, y, z)",
                 f"box {' x '.join(f'{e:.3g}' for e in size)} m at ({centre})", f"density {lo:.3g}..{hi:.3g}",
                 f"density_scale {self.density_scale:.4g} /m"]
        if self.value_range is not None:
            parts.append(f"HU {self.value_range[0]:g}..{self.value_range[1]:g}")
        if self.emission_grid is not None:
            parts.append(f"fire {self.temperature_range[0]:g}..{self.temperature_range[1]:g} K")
        return f"Volume({', '.join(parts)})"

    def _check_fire(self) -> None:
        if isinstance(self.emission_grid, SparseGrid):
            if self.emission_grid.shape != self.density.shape:
                raise VolrenError(f"volume '{self.name}': emission grid has shape {self.emission_grid.shape}, the "
                                  f"density {self.density.shape}: they must match")
            validate_density(self.emission_grid.map(np.abs), f"volume '{self.name}': emission grid")
        elif self.emission_grid is not None:
            grid = np.asarray(self.emission_grid)
            if grid.shape != self.density.shape:
                raise VolrenError(f"volume '{self.name}': emission grid has shape {grid.shape}, the density "
                                  f"{self.density.shape}: they must match")
            if not np.issubdtype(grid.dtype, np.number) or not np.all(np.isfinite(grid)):
                raise VolrenError(f"volume '{self.name}': emission grid must hold finite real numbers")
            object.__setattr__(self, "emission_grid", np.ascontiguousarray(grid, dtype=np.float32))
        k = tuple(float(v) for v in np.asarray(self.temperature_range, dtype=np.float64).reshape(-1))
        if len(k) != 2 or not all(np.isfinite(k)) or not 0 <= k[0] < k[1]:
            raise VolrenError(f"volume '{self.name}': temperature range must be two finite kelvin values "
                              f"0 < K0 < K1 (K0 = 0: the values are kelvin), got {self.temperature_range}")
        object.__setattr__(self, "temperature_range", k)
        if not (np.isfinite(self.emission_scale) and self.emission_scale >= 0):
            raise VolrenError(f"volume '{self.name}': emission scale must be a finite number >= 0, got "
                              f"{self.emission_scale}")

    @cached_property
    def emission_u(self) -> np.ndarray | None:
        """``emission_grid`` normalised to u = v / max(v) in [0, 1], values <= 0 at 0 (no emission); None without."""
        if self.emission_grid is None:
            return None
        peak = float(self.emission_grid.max())

        def normalised(v: np.ndarray) -> np.ndarray:
            return np.clip(v / np.float32(peak), 0.0, 1.0).astype(np.float32) if peak > 0 else np.zeros_like(v)

        if isinstance(self.emission_grid, SparseGrid):
            return self.emission_grid.map(normalised)
        return normalised(self.emission_grid)

    @cached_property
    def emission_table(self) -> np.ndarray | None:
        """(`TABLE_SIZE`, 3) blackbody radiance per metre at u = i / (size - 1) (`volren.blackbody.blackbody_table`
        over ``temperature_range``, scaled by ``emission_scale``); None without an emission grid."""
        if self.emission_grid is None:
            return None
        return blackbody_table(*self.temperature_range, self.emission_scale)

    @property
    def resolution(self) -> tuple[int, int, int]:
        """Voxels per axis as ``(x, y, z)``."""
        nz, ny, nx = self.density.shape
        return (nx, ny, nz)

    @cached_property
    def to_local(self) -> np.ndarray:
        return np.linalg.inv(self.to_world)

    @cached_property
    def corners_world(self) -> np.ndarray:
        """The 8 box corners in world space, ``(8, 3)``."""
        c = np.array([[x, y, z, 1.0] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)])
        return (c @ self.to_world.T)[:, :3]

    @property
    def center_world(self) -> np.ndarray:
        return self.to_world[:3, 3].copy()

    @cached_property
    def diagonal(self) -> float:
        """[m] the longest world-space diagonal of the box: V samples span it at most (uniform steps)."""
        c = self.corners_world
        return float(max(np.linalg.norm(c[i] - c[7 - i]) for i in range(4)))

    @cached_property
    def mip_pyramid(self) -> tuple[Any, ...]:
        """Level 0 is the grid; each next level halves every axis by a 2x2x2 mean, down to one voxel (for LOD). A
        sparse grid's levels are sparse (`SparseGrid.downsample`) while they have a trilinear cell on every axis,
        then dense (a few voxels). A streamed pyramid's levels are its file's (`StreamedDensity.levels`)."""
        if getattr(self.density, "streamed", False):
            return (self.density, *self.density.levels[1:])
        levels = [self.density]
        while max(levels[-1].shape) > 1:
            level = levels[-1]
            if isinstance(level, SparseGrid):
                coarse = tuple(-(-n // 2) if n > 1 else 1 for n in level.shape)
                levels.append(level.downsample() if min(coarse) >= 2 else _downsample(level.to_dense(), "mean"))
            else:
                levels.append(_downsample(level, "mean"))
        return tuple(levels)

    @cached_property
    def max_pyramid(self) -> tuple[np.ndarray, ...]:
        """Conservative max-density pyramid for empty-space culling.

        Level 0 holds, per voxel, the max over its 3x3x3 neighbourhood: a trilinear sample anywhere in the voxel's
        cell reads only voxels of that neighbourhood, so ``max_pyramid[0]`` bounds every sample there. Each next
        level is the 2x2x2 max of the previous one. Dense grids only: a sparse grid's bounds come from its bricks
        (`SparseGrid.cell_ranges`).
        """
        if isinstance(self.density, SparseGrid):
            raise VolrenError(f"volume '{self.name}': a sparse grid has no voxel max pyramid (its bricks bound it)")
        levels = [_dilate_max(self.density)]
        while max(levels[-1].shape) > 1:
            levels.append(_downsample(levels[-1], "max"))
        return tuple(levels)


@dataclass(frozen=True)
class DirectionalLight:
    """A distant light. ``direction`` is where the light travels (from the light into the scene)."""

    direction: tuple[float, float, float] = (-0.4, -1.0, -0.3)
    irradiance: RGB = (3.0, 3.0, 3.0)
    """[W/m^2] on a plane facing the light."""

    def __post_init__(self) -> None:
        d = as_vec3(self.direction, "light direction")
        n = np.linalg.norm(d)
        if n < 1e-9:
            raise VolrenError("light direction must not be the zero vector")
        # a unit direction is kept as it is: dividing it by its norm again can move the last bit, and a copy
        # (dataclasses.replace) would no longer equal its light (the light-map cache recomputed for it)
        object.__setattr__(self, "direction", tuple(float(v) for v in (d if abs(n - 1.0) < 1e-12 else d / n)))
        e = as_rgb(self.irradiance, "light irradiance")
        if min(e) < 0:
            raise VolrenError(f"light irradiance must be >= 0, got {e}")
        object.__setattr__(self, "irradiance", e)


@dataclass(frozen=True)
class PointLight:
    """An isotropic point light with inverse-square falloff."""

    position: tuple[float, float, float] = (0.0, 2.0, 0.0)
    intensity: RGB = (10.0, 10.0, 10.0)
    """[W/sr]"""

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", tuple(float(v) for v in as_vec3(self.position, "light position")))
        e = as_rgb(self.intensity, "light intensity")
        if min(e) < 0:
            raise VolrenError(f"light intensity must be >= 0, got {e}")
        object.__setattr__(self, "intensity", e)


SPOT_FALLOFFS = ("smoothstep", "linear")
"""`SpotLight.falloff` profiles, in the order of their kernel codes (`volren.kernels.common.light_irradiance`)"""


@dataclass(frozen=True)
class SpotLight:
    """A point light limited to a cone: full intensity inside ``inner_angle`` of ``direction``, falling to zero at
    ``outer_angle`` (half-angles [deg]), inverse-square falloff. Between the cones the intensity is scaled by
    ``falloff``'s profile of the angle theta to the axis: ``smoothstep`` (the default, as before), the cubic
    smoothstep(cos outer, cos inner, cos theta) in the cosine; ``linear``, (outer - theta) / (outer - inner) in the
    angle, the profile of other renderers. They differ: a 5-25 degree spot at 15 degrees is 0.736 of its axial
    intensity with smoothstep against 0.5 linear, and its whole cone emits 1.25 times the linear one's power."""

    position: tuple[float, float, float] = (0.0, 2.0, 0.0)
    direction: tuple[float, float, float] = (0.0, -1.0, 0.0)
    intensity: RGB = (10.0, 10.0, 10.0)
    """[W/sr] on the axis"""
    inner_angle: float = 20.0
    outer_angle: float = 30.0
    falloff: str = "smoothstep"
    """the profile between the cones: ``smoothstep`` (in cos theta) or ``linear`` (in theta); `SPOT_FALLOFFS`"""

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", tuple(float(v) for v in as_vec3(self.position, "spot light position")))
        d = as_vec3(self.direction, "spot light direction")
        if np.linalg.norm(d) < 1e-9:
            raise VolrenError("spot light direction must not be the zero vector")
        object.__setattr__(self, "direction", tuple(float(v) for v in d / np.linalg.norm(d)))
        e = as_rgb(self.intensity, "spot light intensity")
        if min(e) < 0:
            raise VolrenError(f"spot light intensity must be >= 0, got {e}")
        object.__setattr__(self, "intensity", e)
        if not 0 <= self.inner_angle < self.outer_angle <= 90:
            raise VolrenError(f"spot light angles need 0 <= inner < outer <= 90 degrees, got {self.inner_angle} and "
                              f"{self.outer_angle}")
        if self.falloff not in SPOT_FALLOFFS:
            raise VolrenError(f"spot light falloff must be one of {', '.join(SPOT_FALLOFFS)}, got '{self.falloff}'")


@dataclass(frozen=True)
class RectLight:
    """A one-sided rectangular area light of uniform radiance: centre ``position``, half-edge vectors ``edge_u`` and
    ``edge_v``; it emits towards edge_u x edge_v. The path tracer samples its area; the other methods treat it as a
    point at its centre with intensity radiance * area * cos(angle to the normal)."""

    position: tuple[float, float, float] = (0.0, 2.0, 0.0)
    edge_u: tuple[float, float, float] = (0.5, 0.0, 0.0)
    edge_v: tuple[float, float, float] = (0.0, 0.0, -0.5)
    radiance: RGB = (10.0, 10.0, 10.0)
    """[W/(m^2 sr)]"""

    def __post_init__(self) -> None:
        for name in ("position", "edge_u", "edge_v"):
            object.__setattr__(self, name, tuple(float(v) for v in as_vec3(getattr(self, name), f"rect light {name}")))
        if np.linalg.norm(np.cross(self.edge_u, self.edge_v)) < 1e-12:
            raise VolrenError("rect light edges must span a rectangle (non-zero, not parallel)")
        e = as_rgb(self.radiance, "rect light radiance")
        if min(e) < 0:
            raise VolrenError(f"rect light radiance must be >= 0, got {e}")
        object.__setattr__(self, "radiance", e)


Light = DirectionalLight | PointLight | SpotLight | RectLight


def _albedo(value: float | Sequence[float], what: str) -> RGB:
    a = as_rgb(value, what)
    if min(a) < 0 or max(a) > 1:
        raise VolrenError(f"{what} must lie in [0, 1], got {a}")
    return a


@dataclass(frozen=True)
class Sphere:
    """An opaque diffuse sphere (the analytic stand-in for meshes, paper 001 §3.2): it hides what lies behind it."""

    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius: float = 0.5
    """[m]"""
    albedo: RGB = (0.7, 0.7, 0.7)

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", tuple(float(v) for v in as_vec3(self.center, "sphere center")))
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise VolrenError(f"sphere radius must be > 0, got {self.radius}")
        object.__setattr__(self, "albedo", _albedo(self.albedo, "sphere albedo"))


@dataclass(frozen=True)
class Plane:
    """An opaque diffuse plane through ``point`` facing ``normal`` (e.g. a ground plane)."""

    point: tuple[float, float, float] = (0.0, -1.0, 0.0)
    normal: tuple[float, float, float] = (0.0, 1.0, 0.0)
    albedo: RGB = (0.5, 0.5, 0.5)

    def __post_init__(self) -> None:
        object.__setattr__(self, "point", tuple(float(v) for v in as_vec3(self.point, "plane point")))
        n = as_vec3(self.normal, "plane normal")
        if np.linalg.norm(n) < 1e-9:
            raise VolrenError("plane normal must not be the zero vector")
        object.__setattr__(self, "normal", tuple(float(v) for v in n / np.linalg.norm(n)))
        object.__setattr__(self, "albedo", _albedo(self.albedo, "plane albedo"))


@dataclass(frozen=True, eq=False)
class TriangleMesh:
    """A diffuse triangle mesh in world coordinates (vertices (N, 3) [m], faces (M, 3) vertex indices), ray-cast
    through a `wp.Mesh` BVH. ``alpha`` = 1: opaque (both sides). ``alpha`` < 1: every crossing of the surface is a
    translucent layer (paper 000 §3.3) that adds alpha * its shaded colour (lit like the opaque surfaces, either side
    facing the eye) and multiplies the transmittance behind it by 1 - alpha."""

    vertices: np.ndarray
    faces: np.ndarray
    albedo: RGB = (0.7, 0.7, 0.7)
    name: str = "mesh"
    alpha: float = 1.0
    """opacity of each layer in [0, 1]; 1 = opaque"""

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, dtype=np.float64)
        f = np.asarray(self.faces)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3 or not np.all(np.isfinite(v)):
            raise VolrenError(f"mesh '{self.name}': vertices must be a finite (N >= 3, 3) array, got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) < 1 or not np.issubdtype(f.dtype, np.integer):
            raise VolrenError(f"mesh '{self.name}': faces must be an integer (M >= 1, 3) array, got {f.shape}")
        if f.min() < 0 or f.max() >= len(v):
            raise VolrenError(f"mesh '{self.name}': face indices must lie in [0, {len(v) - 1}]")
        object.__setattr__(self, "vertices", np.ascontiguousarray(v, dtype=np.float32))
        object.__setattr__(self, "faces", np.ascontiguousarray(f, dtype=np.int32))
        object.__setattr__(self, "albedo", _albedo(self.albedo, f"mesh '{self.name}' albedo"))
        alpha = float(self.alpha)
        if not 0.0 <= alpha <= 1.0:
            raise VolrenError(f"mesh '{self.name}': alpha must lie in [0, 1], got {self.alpha}")
        object.__setattr__(self, "alpha", alpha)

    @property
    def translucent(self) -> bool:
        return self.alpha < 1.0


Opaque = Sphere | Plane | TriangleMesh


@dataclass(frozen=True, eq=False)
class Environment:
    """Distant environment: a constant radiance, or an equirectangular HDR image ``(H, W, 3)``.

    Image convention (DESIGN.md): u (column) is the azimuth, v (row) the polar angle from +y. Pixel (row, col) of an
    H x W image is the direction (sin t cos p, cos t, sin t sin p) at t = pi (row + 1/2) / H, p = 2 pi (col + 1/2) / W
    (azimuth 0 on +x, increasing towards +z).
    """

    radiance: RGB = (0.0, 0.0, 0.0)
    """[W/(m^2 sr)] used when ``image`` is None."""
    image: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "radiance", as_rgb(self.radiance, "environment radiance"))
        if min(self.radiance) < 0:
            raise VolrenError(f"environment radiance must be >= 0, got {self.radiance}")
        if self.image is not None:
            img = np.asarray(self.image, dtype=np.float32)
            if img.ndim != 3 or img.shape[2] < 3 or min(img.shape[:2]) < 1:
                raise VolrenError(f"environment image must be (H, W, 3), got shape {img.shape}")
            img = np.ascontiguousarray(img[..., :3])
            if not np.all(np.isfinite(img)) or img.min() < 0:
                raise VolrenError("environment image must hold finite, non-negative radiance")
            object.__setattr__(self, "image", img)

    def mean_radiance(self) -> RGB:
        """Radiance averaged over the sphere (solid-angle weights sin(theta) per row for an image).

        This is the ambient term's L_ambient: an isotropic, unshadowed in-scattering sigma_s * L_ambient, because
        any normalised phase function integrates to 1 over the sphere.
        """
        if self.image is None:
            return self.radiance
        h = self.image.shape[0]
        theta = (np.arange(h) + 0.5) / h * np.pi
        w = np.sin(theta)
        mean = np.einsum("hwc,h->c", self.image.astype(np.float64), w) / (w.sum() * self.image.shape[1])
        return (float(mean[0]), float(mean[1]), float(mean[2]))


@dataclass(frozen=True)
class FogBox:
    """A local fog volume (Hillaire 2015's participating-media box): an axis-aligned box of extra fog density,
    modulated by Perlin noise, ``density * (1 - noise_amount + noise_amount * (noise + 1) / 2)``."""

    center: tuple[float, float, float] = (0.0, 0.5, 0.0)
    half_size: tuple[float, float, float] = (1.0, 0.5, 1.0)
    """[m]"""
    density: float = 1.0
    """multiplies the fog's extinction inside the box"""
    noise_amount: float = 0.5
    """in [0, 1]: 0 = uniform"""
    noise_frequency: float = 1.0
    """[1/m]"""
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", tuple(float(v) for v in as_vec3(self.center, "fog box center")))
        h = as_vec3(self.half_size, "fog box half size")
        if min(h) <= 0:
            raise VolrenError(f"fog box half size must be > 0 on every axis, got {tuple(h)}")
        object.__setattr__(self, "half_size", tuple(float(v) for v in h))
        if not (np.isfinite(self.density) and self.density >= 0):
            raise VolrenError(f"fog box density must be >= 0, got {self.density}")
        if not 0 <= self.noise_amount <= 1:
            raise VolrenError(f"fog box noise amount must lie in [0, 1], got {self.noise_amount}")
        if not (np.isfinite(self.noise_frequency) and self.noise_frequency > 0):
            raise VolrenError(f"fog box noise frequency must be > 0, got {self.noise_frequency}")


@dataclass(frozen=True)
class Fog:
    """Participating media for the froxel fog (paper 003, after Hillaire 2015): one material (extinction
    sigma_t [1/m] at density 1, single-scattering albedo, emission, HG g) whose density is the sum of a global
    homogeneous term, an exponential height fog ``height_density * exp(-height_falloff * (y - height_base))`` (capped
    at ``height_density`` below the base) and the local boxes."""

    extinction: float = 0.05
    """[1/m] sigma_t at density 1"""
    albedo: RGB = (0.9, 0.9, 0.9)
    emission: RGB = (0.0, 0.0, 0.0)
    """[W/(m^3 sr)] per unit density"""
    g: float = 0.3
    density: float = 1.0
    """global homogeneous density"""
    height_density: float = 0.0
    height_falloff: float = 0.5
    """[1/m]"""
    height_base: float = 0.0
    """[m]"""
    boxes: tuple[FogBox, ...] = ()

    def __post_init__(self) -> None:
        for name in ("extinction", "density", "height_density", "height_falloff"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise VolrenError(f"fog {name.replace('_', ' ')} must be a finite number >= 0, got {value}")
        object.__setattr__(self, "albedo", _albedo(self.albedo, "fog albedo"))
        e = as_rgb(self.emission, "fog emission")
        if min(e) < 0:
            raise VolrenError(f"fog emission must be >= 0, got {e}")
        object.__setattr__(self, "emission", e)
        if not -1 < self.g < 1:
            raise VolrenError(f"fog g must lie in (-1, 1), got {self.g}")
        object.__setattr__(self, "boxes", tuple(self.boxes))
        for b in self.boxes:
            if not isinstance(b, FogBox):
                raise VolrenError(f"fog boxes must be FogBox objects, got {type(b).__name__}")


@dataclass(frozen=True, eq=False)
class Scene:
    """What is rendered: volumes, lights, a distant environment (ambient) and a background colour."""

    volumes: tuple[Volume, ...]
    lights: tuple[Light, ...] = (DirectionalLight(),)
    environment: Environment = field(default_factory=lambda: Environment((0.05, 0.06, 0.08)))
    background: RGB = (0.0, 0.0, 0.0)
    """linear RGB seen where rays leave the scene (composited only when an image is written)."""
    name: str = "scene"
    opaque: tuple[Opaque, ...] = ()
    """opaque diffuse surfaces, ray-traced into a colour + depth buffer per view that clips the volumes"""
    fog: Fog | None = None
    """participating media of the froxel fog method (a fog scene may have no volumes)"""

    def __repr__(self) -> str:
        """A summary: its name, each volume's (`Volume.__repr__`), what else it holds by count."""
        volumes = ", ".join(repr(v) for v in self.volumes[:4]) + (f", ... ({len(self.volumes)})"
                                                                  if len(self.volumes) > 4 else "")
        extra = [f"{len(self.lights)} light(s)"] + ([f"{len(self.opaque)} opaque"] if self.opaque else []) + (
            ["fog"] if self.fog is not None else [])
        return f"Scene({self.name!r}, volumes=[{volumes}], {', '.join(extra)})"

    def __post_init__(self) -> None:
        object.__setattr__(self, "volumes", tuple(self.volumes))
        object.__setattr__(self, "lights", tuple(self.lights))
        object.__setattr__(self, "opaque", tuple(self.opaque))
        for o in self.opaque:
            if not isinstance(o, Sphere | Plane | TriangleMesh):
                raise VolrenError(f"opaque objects must be Sphere, Plane or TriangleMesh, got {type(o).__name__}")
        if self.fog is not None and not isinstance(self.fog, Fog):
            raise VolrenError(f"scene fog must be a Fog, got {type(self.fog).__name__}")
        if not self.volumes and self.fog is None:
            raise VolrenError("a scene needs at least one volume (or fog)")
        for v in self.volumes:
            if not isinstance(v, Volume):
                raise VolrenError(f"scene volumes must be Volume objects, got {type(v).__name__}")
        for light in self.lights:
            if not isinstance(light, DirectionalLight | PointLight | SpotLight | RectLight):
                raise VolrenError(f"unknown light type {type(light).__name__}")
        object.__setattr__(self, "background", as_rgb(self.background, "background"))

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World-space axis-aligned bounds of all volume boxes: ``(lo, hi)``."""
        c = np.concatenate([v.corners_world for v in self.volumes])
        return c.min(axis=0), c.max(axis=0)
