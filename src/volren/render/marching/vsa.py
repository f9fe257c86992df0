"""Variable step amplification (VSA, paper 000 §3.1.3, Eq. 4-6): the step amplification each ray proposes."""

from __future__ import annotations

import json
from pathlib import Path

import warp as wp

VSA_FIT_FILE = Path(__file__).with_name("vsa_fit.json")
VSA_FIT: dict[str, float] = json.loads(VSA_FIT_FILE.read_text())["weights"]
"""Eq. 4-6 constants fitted by ``scripts/fit_vsa.py`` (quality at equal voxel gathers; the file says how, on what)."""

END = wp.constant(1.0e-4)
"""[base steps] what may remain of a ray (floating-point rest) when its last step has been taken"""


@wp.struct
class VSAParams:
    """Eq. 4-6 constants; k_a = 0 with all weights 0 gives uniform steps (as does enabled = 0, without the work)."""

    enabled: int
    k_a: float
    k_b: float
    f_lambda_max: float
    w_lambda: float
    w_t: float
    w_a: float
    lambda_cap: float
    """a bound on f_lambda^w_lambda (f_lambda_max^w_lambda with a little slack, `lambda_cap`)"""


def lambda_cap(f_lambda_max: float, w_lambda: float) -> float:
    """`VSAParams.lambda_cap`: f_lambda_max^w_lambda raised by 1e-5 (relative, on f_lambda_max and on the power), so
    that float rounding of Eq. 5's quotient or of the products cannot take f_lambda^w_lambda past it."""
    return float((f_lambda_max * (1.0 + 1.0e-5)) ** w_lambda * (1.0 + 1.0e-5))


@wp.func
def weighted(f: float, w: float) -> float:
    """f^w, by products for whole weights up to 8: pow for the fitted w_T = 4 made the CPU frame 22% slower (smoke
    64^3, 480x270 stereo, N = 360, eyes alone, no InS: 317 against 259 ms). The fitted weights (1 and 4) are spelt
    out: the loop's count made a proposal cost twice as much (microbenchmark, 100k x 100 calls: 30 against 16 ns);
    the same products in the same order, so the same bits."""
    if w == 1.0:
        return f
    if w == 4.0:
        return f * f * f * f
    if w == 0.0:
        return 1.0
    if w == wp.floor(w) and w <= 8.0:
        out = float(1.0)
        for _ in range(int(w)):
            out = out * f
        return out
    return wp.pow(f, w)


@wp.func
def wave_length_factor(vp: VSAParams, drho: float) -> float:
    """Eq. 5: f_lambda = min(k_b / |rho'|, f_lambda_max), rho' the change of density per base step."""
    if wp.abs(drho) * vp.f_lambda_max > vp.k_b:
        return vp.k_b / wp.abs(drho)
    return vp.f_lambda_max


@wp.func
def transparency_factor(rho: float, drho: float, absorb: float) -> float:
    """Eq. 6: f_T = 1 - a rho~(t + Delta t), the next density predicted as rho + rho' (clamped to [0, 1])."""
    return wp.clamp(1.0 - absorb * (rho + drho), 0.0, 1.0)


@wp.func
def attenuation_factor(trans: float) -> float:
    """Eq. 6: f_A = 1 - T(t), the opacity accumulated up to the current sample."""
    return wp.clamp(1.0 - trans, 0.0, 1.0)


@wp.func
def vsa_amplification(vp: VSAParams, t: float, slope: float, rho: float, drho: float, trans: float,
                      absorb: float) -> float:
    """Eq. 4's amplification of the base step: max(k_a t / t_max, f_lambda^w_lambda f_T^w_T f_A^w_A, 1).

    a (Eq. 6) is the optical depth of one base step per unit density, so f_T is the transparency of the next base
    step. f_T and f_A lie in [0, 1], so they only take back what f_lambda grants (at most f_lambda_max): long steps
    need smooth density (f_lambda), thin medium ahead (f_T) and opacity already accumulated (f_A; none in front of
    the medium, where a step over a dense feature would cost the most). The result is a real number: steps are not
    rounded to whole base steps (rounding made every product below 2 a uniform step).

    t and t_max are distances from the eye (t_max: to the texel; slope = k_a / t_max, `ramp_slope`). Algorithm 2
    starts its t at 0, which can be read as t from the volume entry; measured at equal gathers (64^3, six orbit
    frames of ``bench binocular`` at 96x64, N = 16 to 96, against uniform steps): k_a (t - t_min) / t_max with the
    paper's k_a = 3 and f_lambda_max = 2 gained 0.0-0.2 dB, k_a (t - t_min) / (t_max - t_min) lost up to 2.6 dB, the
    eye-based ramp with the fitted constants gained up to 0.7 dB (cloud, phantom) and 0.2 dB (smoke). f_A is kept as
    printed: letting empty samples in front of the medium amplify (f_A = 1 where rho = rho' = 0 and T = 1; 94-97% of
    the smoke's and cloud's voxels are empty) cut gathers by 40-60% but lost 0.4-13 dB at equal gathers: the long
    step that enters the medium misses or over-weights its front."""
    ramp = wp.max(slope * t, 1.0)
    # f_T <= 1, so the product is at most lambda_cap f_A^w_A (float products are monotone): where that bound is not
    # above the ramp (in front of the medium f_A = 0) the ramp is the proposal, and Eq. 5-6 are not evaluated. The
    # same result, bit for bit.
    f_a = weighted(attenuation_factor(trans), vp.w_a)
    if vp.lambda_cap * f_a <= ramp:
        return ramp
    return wp.max(ramp, weighted(wave_length_factor(vp, drho), vp.w_lambda)
                  * weighted(transparency_factor(rho, drho, absorb), vp.w_t) * f_a)


@wp.func
def vsa_product(vp: VSAParams, rho: float, drho: float, trans: float, absorb: float) -> float:
    """Eq. 4's product f_lambda^w_lambda f_T^w_T f_A^w_A (Eq. 5-6); constant along a run of zero samples (rho =
    rho' = 0, T unchanged), which the coupled march walks through with `vsa_ramp` alone."""
    f_lambda = wave_length_factor(vp, drho)
    f_t = transparency_factor(rho, drho, absorb)
    f_a = attenuation_factor(trans)
    return weighted(f_lambda, vp.w_lambda) * weighted(f_t, vp.w_t) * weighted(f_a, vp.w_a)


@wp.func
def ramp_slope(vp: VSAParams, t_max: float) -> float:
    """k_a / t_max, Eq. 4's ramp per unit distance for a ray of length t_max (once per ray: the ramp is then a
    product, slope t, not a quotient per step)."""
    if t_max > 0.0:
        return vp.k_a / t_max
    return 0.0


@wp.func
def vsa_ramp(t: float, slope: float, product: float) -> float:
    """Eq. 4's outer max(k_a t / t_max, product, 1), slope = `ramp_slope`."""
    return wp.max(wp.max(slope * t, product), 1.0)


@wp.func
def zero_product(vp: VSAParams, cached: wp.vec2, trans: float, absorb: float) -> wp.vec2:
    """(T, product) of a zero sample (rho = rho' = 0) at transmittance T = trans, from ``cached`` when it holds that
    T: the product of a run of zero samples changes only where the medium lowered T."""
    if cached[0] == trans:
        return cached
    return wp.vec2(trans, vsa_product(vp, 0.0, 0.0, trans, absorb))


@wp.func
def vsa_proposal(vp: VSAParams, t: float, slope: float, rho: float, prev: float, prev_t: float, trans: float,
                 dt: float, absorb: float) -> float:
    """`vsa_amplification` after a sample of density rho at distance t, rho' per base step from the ray's previous
    sample (density prev at prev_t; prev < 0: none yet, rho' = 0)."""
    drho = float(0.0)
    if prev >= 0.0:
        drho = (rho - prev) * dt / wp.max(t - prev_t, 1.0e-9)
    return vsa_amplification(vp, t, slope, rho, drho, trans, absorb)
