"""Dynamic ambient global illumination with spherical harmonics (paper 000 §3.2), for every light-map marcher.

``GIConfig.method`` picks how each volume's lighting grid gets the SH coefficients of its phase-weighted
visibility (`volren.render.gi.passes`):

- ``sresir`` (ours, the paper's): per frame a sample pass (one uniform direction per voxel, coarse transmittance with
  ``coarse_factor`` times the fine step), an SH-transform pass (simplified reservoir resampling over the 3x3x3
  neighbours, Eq. 12, one fine march, variance clamp and adaptive temporal accumulation, Eq. 8-11) and the lighting
  integration (Eq. 7). Eq. 12 as printed divides by the chosen neighbour's coarse transmittance and is unbounded
  (43x the radiance of a constant environment after one frame on the cloud); ``resampling="ris"`` makes it resampled
  importance sampling with a positive, defensive target (coarse T times the sky's luminance, plus ``alpha``):
  unbiased, bounded, and 1.2-3 dB above own directions at 1-32 frames (docs/BENCHMARKS.md);
- ``restir``: strict ReSTIR, the same passes with fine transmittance as the resampling target and the voxel's
  temporal reservoir merged in (M capped at ``reservoir_cap`` times the spatial M), then our accumulation;
- ``prt``: precomputed radiance transfer, ``rays`` stratified fine marches per voxel projected to SH, recomputed only
  when the scene's density changes;
- ``major``: paper 001's major-direction approximation (one march along the negative density gradient);
- ``brute``: the ground truth, ``rays`` fine marches per voxel integrated against the environment directly (no SH),
  from the points of a quadrature over the voxel's trilinear basis function, projected so the marchers' lookup
  reads the field's L2 projection (``projection``; isotropic scattering: the phase function's g is not applied);
- ``none``: the constant, unshadowed ambient (the environment's mean radiance).

The lighting update is amortised over volumes: ``volumes_per_frame`` volumes per frame in turn (§3.2.3), every volume
on the first frame. Marches cross every volume (shadowing between volumes), and with GI on the direct light map does
too. The environment enters through its SH projection of order ``order`` (n^2 coefficients, `volren.sh`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from volren.device import launch_rows
from volren.errors import VolrenError
from volren.render.environment import environment_light
from volren.render.frame import PassClock
from volren.render.gi.passes import (
    Accumulation,
    GIBuffers,
    GIScene,
    integrate_kernel,
    major_kernel,
    sample_kernel,
    sphere_kernel,
    transform_kernel,
)
from volren.sh import MAX_ORDER, check_order, project_environment, vec16
from volren.upload import DeviceScene

GI_METHODS = ("none", "major", "prt", "restir", "sresir", "brute")
RESAMPLING = ("ris", "none", "eq12")
LUMINANCE = (0.2126, 0.7152, 0.0722)
MAX_RAYS = 1 << 20
COSINE_LOBE = (1.0, 2.0 / 3.0, 1.0 / 4.0, 0.0)
"""A_l / pi per band l: the clamped-cosine kernel's SH convolution factors (Ramamoorthi and Hanrahan 2001)."""


@dataclass(frozen=True)
class GIConfig:
    method: str = "none"
    order: int = 3
    """SH order n: n^2 coefficients per voxel (1 to 4)"""
    coarse_factor: int = 4
    """ours: the sample pass marches with this many times the fine step (the paper's quadruple step)"""
    convergence_frames: int = 32
    """N of lambda(n) = 1 / min(n + 1, N): the frame count regarded as converged"""
    k_gamma: float = 0.5
    """Eq. 9's variance-clamp adjustment"""
    k_lambda: float = 0.5
    """Eq. 11's adjustment of lambda"""
    w_dst: float = 0.125
    """Eq. 10's weights (the paper's initial values; `scripts/fit_gi.py` fits them)"""
    w_clamped: float = 0.875
    w_poly: float = 0.0
    poly: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """(a, b, c) of Eq. 10's cubic"""
    resampling: str = "ris"
    """Eq. 12's reuse of the 3x3x3 neighbours' directions: ``ris`` (resampled importance sampling with the
    defensive target r = T~ l / l_mean + alpha), ``none`` (each voxel its own direction), ``eq12`` (as printed)"""
    alpha: float = 0.5
    """the defensive term of the RIS target: > 0 keeps it unbiased, and bounds one estimate by (1 + alpha) / alpha
    times the environment's radiance in a constant environment"""
    record: bool = False
    """keep Eq. 10's inputs (SH_dst, SH_clamped, mu~) of each update for fitting its weights (`scripts/fit_gi.py`)"""
    rays: int = 256
    """brute force and PRT: rays per voxel (the paper: 393,216 and 24,576 on a GPU)"""
    projection: bool = True
    """brute force: the grid holds the ambient field's L2 projection onto the trilinear basis the marchers' lookup
    interpolates with (`project_to_basis`: images within 0.3% of the exact single scattering at 16 light voxels,
    issue 19 item 7); False: the field at the voxel centres, what PRT and the per-frame methods estimate (for
    comparing their grids with it)"""
    volumes_per_frame: int = 1
    reservoir_cap: float = 20.0
    """strict ReSTIR: temporal reservoir's M at most this times the spatial M"""

    def __post_init__(self) -> None:
        if self.method not in GI_METHODS:
            raise VolrenError(f"unknown GI method '{self.method}': choose from {', '.join(GI_METHODS)}")
        check_order(self.order)
        if self.resampling not in RESAMPLING:
            raise VolrenError(f"unknown GI resampling '{self.resampling}': choose from {', '.join(RESAMPLING)}")
        for name in ("coarse_factor", "convergence_frames", "rays", "volumes_per_frame"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise VolrenError(f"GI {name.replace('_', ' ')} must be an integer >= 1, got {value}")
        if self.rays > MAX_RAYS:
            raise VolrenError(f"GI rays per voxel must be at most {MAX_RAYS}, got {self.rays}")
        weights = (self.w_dst, self.w_clamped, self.w_poly)
        if not all(math.isfinite(w) for w in (*weights, *self.poly, self.k_gamma, self.k_lambda)):
            raise VolrenError("GI weights must be finite")
        if abs(sum(weights) - 1.0) > 1e-6:
            raise VolrenError(f"Eq. 10's weights must sum to 1, got {sum(weights):.6g}")
        if self.k_gamma <= 0 or self.k_lambda < 0 or self.reservoir_cap <= 0:
            raise VolrenError("GI k_gamma and the reservoir cap must be > 0 and k_lambda >= 0")
        if not (math.isfinite(self.alpha) and self.alpha > 0):
            raise VolrenError(f"GI alpha must be > 0 (every candidate needs a positive weight), got {self.alpha}")

    @property
    def on(self) -> bool:
        return self.method != "none"


def environment_coefficients(ds: DeviceScene, order: int) -> tuple[np.ndarray, np.ndarray]:
    """(16, 3) SH coefficients of the scene's environment (zero beyond order^2), and the same scaled by the
    clamped-cosine factors A_l / pi for the major-direction method."""
    sh = np.zeros((MAX_ORDER**2, 3), np.float32)
    sh[: order * order] = project_environment(ds.scene.environment, order)
    band = np.repeat(np.arange(MAX_ORDER), [2 * band + 1 for band in range(MAX_ORDER)])
    return sh, sh * np.asarray(COSINE_LOBE, np.float32)[band][:, None]


def relative_luminance(sh: np.ndarray) -> np.ndarray:
    """(16,) SH coefficients of the environment's luminance over its mean, l(w) / l_mean (the constant 1 for a
    black environment): the resampling target's radiance factor."""
    lum = sh @ np.asarray(LUMINANCE, np.float32)
    mean = lum[0] / math.sqrt(4 * math.pi)
    if mean <= 0:
        lum = np.zeros(MAX_ORDER**2, np.float32)
        lum[0], mean = math.sqrt(4 * math.pi), 1.0
    return (lum / mean).astype(np.float32)


def basis_gram(n: int) -> np.ndarray:
    """G_ij = integral of phi_i phi_j / integral of phi_i for the n clamped linear basis functions of a lookup that
    interpolates between voxel centres (interior hats: 1/6, 2/3, 1/6; the end functions, constant out to the face:
    5/6 on the diagonal; one voxel: 1). Rows sum to 1, so a constant field keeps its value."""
    if n == 1:
        return np.ones((1, 1))
    g = np.diag(np.full(n, 2.0 / 3.0)) + np.diag(np.full(n - 1, 1.0 / 6.0), 1) + np.diag(np.full(n - 1, 1.0 / 6.0), -1)
    g[0, 0] = g[-1, -1] = 5.0 / 6.0
    return g


def project_to_basis(means: np.ndarray) -> np.ndarray:
    """Grid values (z, y, x, C) whose clamped trilinear interpolation is the L2 projection of a field, from its
    basis-weighted means b_i = integral f phi_i / integral phi_i (`volren.render.gi.passes.sphere_kernel`): per axis
    v = G^-1 b (`basis_gram`), so the integral of the lookup against any trilinear weight is the field's. The
    field's values at the voxel centres (the lookup's nodes) instead miss its steep fall from a lit face to the
    first centre, where the lookup clamps (issue 19 item 7; tests/test_ambient_truth.py)."""
    out = means
    for axis in range(3):
        inv = np.linalg.inv(basis_gram(means.shape[axis]))
        out = np.moveaxis(np.tensordot(inv, np.moveaxis(out, axis, 0), axes=1), 0, axis)
    return out


class AmbientGI:
    """The lighting grids of one scene's volumes and their history across frames; ``update`` runs one frame."""

    def __init__(self, config: GIConfig, ds: DeviceScene, seed: int = 0) -> None:
        self.config = config
        self.seed = seed
        self.light_res = list(ds.light_res)
        voxels = self.light_voxels = ds.light_voxels
        total = max(sum(voxels), 1)
        n2 = config.order**2
        dev = ds.device
        b = GIBuffers()
        b.dirs = wp.zeros(total, dtype=wp.vec3, device=dev)
        b.values = wp.zeros(total, dtype=float, device=dev)
        b.sh = wp.zeros(total * n2, dtype=float, device=dev)
        b.mu = wp.zeros(total * n2, dtype=float, device=dev)
        strict = config.method == "restir"
        b.res_dir = wp.zeros(total if strict else 1, dtype=wp.vec3, device=dev)
        b.res_value = wp.zeros(total if strict else 1, dtype=float, device=dev)
        b.res_wsum = wp.zeros(total if strict else 1, dtype=float, device=dev)
        b.res_m = wp.zeros(total if strict else 1, dtype=float, device=dev)
        b.terms = wp.zeros(total * n2 if config.record else 1, dtype=wp.vec3, device=dev)
        b.ambient = wp.zeros(total, dtype=wp.vec3, device=dev)
        self.buffers = b
        self.updates = [0] * len(voxels)
        """per volume: lighting updates so far (Eq. 8's n)"""
        self.tick = 0
        self._next = 0
        self._static_scene: tuple[object, int] | None = None
        """(scene, its streamed bricks' generation) of the last precomputation (prt, brute)"""
        self._env: tuple[object, wp.array, wp.array] | None = None
        """(environment, its SH on the device, cosine-convolved SH on the device), uploaded once per environment"""
        self._luminance = vec16()

    def fits(self, ds: DeviceScene, config: GIConfig) -> bool:
        """Whether this state can carry on with ``ds`` (same grids, same settings): animated densities keep history."""
        return config == self.config and list(ds.light_res) == self.light_res

    def _environment(self, ds: DeviceScene) -> tuple[wp.array, wp.array]:
        env = ds.scene.environment
        if self._env is None or self._env[0] is not env:
            sh, cosine = environment_coefficients(ds, self.config.order)
            self._env = (env, wp.array(sh, dtype=wp.vec3, device=ds.device),
                         wp.array(cosine, dtype=wp.vec3, device=ds.device))
            self._luminance = vec16(*relative_luminance(sh))
        return self._env[1], self._env[2]

    def _volumes_this_frame(self, n: int) -> list[int]:
        if self.tick == 0:
            return list(range(n))
        k = min(self.config.volumes_per_frame, n)
        chosen = [(self._next + i) % n for i in range(k)]
        self._next = (self._next + k) % n
        return chosen

    def _scene(self, ds: DeviceScene, v: int, samples: int) -> GIScene:
        s = GIScene()
        s.volumes, s.density, s.bvh, s.v, s.samples = ds.volumes, ds.density, ds.volume_bvh.id, v, samples
        return s

    def _accumulation(self, v: int) -> Accumulation:
        c = self.config
        a = Accumulation()
        a.order2, a.n, a.frames = c.order**2, self.updates[v], c.convergence_frames
        a.k_gamma, a.k_lambda = c.k_gamma, c.k_lambda
        a.w_dst, a.w_clamped, a.w_poly, a.poly = c.w_dst, c.w_clamped, c.w_poly, wp.vec3(*c.poly)
        a.strict, a.cap = int(c.method == "restir"), c.reservoir_cap
        a.resampling, a.alpha = {"none": 0, "eq12": 1, "ris": 2}[c.resampling], c.alpha
        a.record = int(c.record)
        a.seed = self._seed(1)
        return a

    def _seed(self, stream: int) -> int:
        return (self.seed * 1_000_003 + self.tick * 7_919 + stream * 104_729 + 12_345) % (2**31 - 1)

    def update(self, ds: DeviceScene, light_samples: int, clock: PassClock) -> dict[str, object]:
        """One frame's lighting passes; afterwards ``ds`` shades with the ambient grids. Returns what it did."""
        c = self.config
        env_sh, env_cosine = self._environment(ds)
        b = self.buffers
        n2 = c.order**2
        launch = self._launcher(ds, clock)
        updated: list[int] = []
        if c.method in ("prt", "brute"):
            # Precomputation: only when the density changes (the scene, or a streamed volume's bricks on the device).
            if self._static_scene is None or self._static_scene[0] is not ds.scene \
                    or self._static_scene[1] != ds.stream_generation:
                env = environment_light(ds.scene.environment, ds.device)
                updated = list(range(ds.volume_count))
                projected = c.method == "brute" and c.projection
                for v in updated:
                    launch("gi_precompute", v, sphere_kernel, light_samples,
                           [b, env, c.rays, n2, self._seed(0), int(projected)])
                if projected:
                    with clock.measure("gi_projection"):
                        b.sh = self._projected(b.sh, ds)
                        b.ambient = self._projected(b.ambient, ds, clamp=True)
                self._static_scene = (ds.scene, ds.stream_generation)
        else:
            updated = self._volumes_this_frame(ds.volume_count)
            for v in updated:
                if c.method == "major":
                    launch("gi_major", v, major_kernel, light_samples, [b, env_cosine])
                    continue
                coarse = light_samples if c.method == "restir" else max(1, light_samples // c.coarse_factor)
                launch("gi_sample", v, sample_kernel, coarse, [b, self._seed(0)])
                launch("gi_transform", v, transform_kernel, light_samples,
                       [b, self._accumulation(v), self._luminance])
                self.updates[v] += 1
        if c.method in ("prt", "restir", "sresir"):
            for v in updated:
                launch("gi_integrate", v, integrate_kernel, light_samples, [b, env_sh, n2])
        self.tick += 1
        ds.ambient_grid, ds.gi = b.ambient, True
        return {"method": c.method, "updated_volumes": updated}

    def _projected(self, array: wp.array, ds: DeviceScene, clamp: bool = False) -> wp.array:
        """``array`` with each volume's basis-weighted means replaced by the grid values of their L2 projection
        (`project_to_basis`), clamped at 0 for radiance."""
        host = array.numpy()
        flat = host.reshape(max(sum(self.light_voxels), 1), -1).astype(np.float64)
        start = 0
        for (nx, ny, nz), count in zip(self.light_res, self.light_voxels, strict=True):
            grid = flat[start: start + count].reshape(nz, ny, nx, -1)
            flat[start: start + count] = project_to_basis(grid).reshape(count, -1)
            start += count
        if clamp:
            flat = np.maximum(flat, 0.0)
        return wp.array(flat.astype(np.float32).reshape(host.shape), dtype=array.dtype, device=ds.device)

    def _launcher(self, ds: DeviceScene, clock: PassClock):
        def launch(name: str, v: int, kernel, samples: int, inputs: list) -> None:
            nx, ny, nz = ds.light_res[v]
            with clock.measure(name):
                launch_rows(kernel, nz * ny, nx, [self._scene(ds, v, samples), *inputs], ds.device, clock.counters)
        return launch

    def sh_grid(self, v: int) -> np.ndarray:
        """Volume v's SH coefficients as (z, y, x, order^2), a copy."""
        return self._grid(self.buffers.sh, v, self.config.order**2)

    def terms_grid(self, v: int) -> np.ndarray:
        """With ``record``: volume v's Eq. 10 inputs of its last update as (z, y, x, order^2, 3), a copy."""
        n2 = self.config.order**2
        start = sum(self.light_voxels[:v])
        nx, ny, nz = self.light_res[v]
        return self.buffers.terms.numpy()[start * n2: (start + nx * ny * nz) * n2].reshape(nz, ny, nx, n2, 3).copy()

    def ambient_grid(self, v: int) -> np.ndarray:
        """Volume v's ambient radiance per unit sigma_s as (z, y, x, 3), a copy."""
        return self._grid(self.buffers.ambient, v, 1)

    def _grid(self, array: wp.array, v: int, per_voxel: int) -> np.ndarray:
        start = sum(self.light_voxels[:v])
        nx, ny, nz = self.light_res[v]
        flat = array.numpy().copy()
        if flat.ndim == 2:
            return flat[start: start + nx * ny * nz].reshape(nz, ny, nx, flat.shape[1])
        return flat[start * per_voxel: (start + nx * ny * nz) * per_voxel].reshape(nz, ny, nx, per_voxel)
