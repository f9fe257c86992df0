"""Variable step amplification (VSA, paper 000 §3.1.3, Eq. 4-6): the step multiple each ray proposes."""

from __future__ import annotations

import json
from pathlib import Path

import warp as wp

VSA_FIT_FILE = Path(__file__).with_name("vsa_fit.json")
VSA_FIT: dict[str, float] = json.loads(VSA_FIT_FILE.read_text())["weights"]
"""Eq. 4-6 weights fitted by ``scripts/fit_vsa.py`` against the reference (the file says how and on what)."""


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


@wp.func
def weighted(f: float, w: float) -> float:
    """f^w, without a pow for the common weights 0 and 1 (three per sample and eye otherwise)."""
    if w == 0.0:
        return 1.0
    if w == 1.0:
        return f
    return wp.pow(f, w)


@wp.func
def vsa_multiple(vp: VSAParams, t: float, t_max: float, rho: float, drho: float, trans: float,
                 absorb: float) -> int:
    """Eq. 4 as a whole number of base steps: max(k_a t / t_max, f_lambda^w_lambda f_T^w_T f_A^w_A, 1), floored.
    f_lambda = min(k_b / |rho'|, f_lambda_max) (Eq. 5); f_T = 1 - a (rho + rho') with a the optical depth of one
    base step per unit density, and f_A = 1 - T (Eq. 6). rho' is the change of density per base step."""
    f_lambda = vp.f_lambda_max
    if wp.abs(drho) * vp.f_lambda_max > vp.k_b:
        f_lambda = vp.k_b / wp.abs(drho)
    f_t = wp.clamp(1.0 - absorb * (rho + drho), 0.0, 1.0)
    f_a = wp.clamp(1.0 - trans, 0.0, 1.0)
    product = weighted(f_lambda, vp.w_lambda) * weighted(f_t, vp.w_t) * weighted(f_a, vp.w_a)
    amp = wp.max(wp.max(vp.k_a * t / t_max, product), 1.0)
    return int(wp.floor(amp))
