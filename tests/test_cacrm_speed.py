"""CACRM's coupled march, faster (issue 24, first item): idle steps and runs of them over empty space.

Most of a coupled pair's steps cross empty space together (smoke 128^3, 480x270 stereo, defaults: 11.3 M eye steps
skipped for 0.62 M density fetches). The texel kernel walks a run of steps where every live eye sits in an empty skip
cell in `idle_run` (VSA's ramp over a constant product, unit steps jumped in one go up to where the ramp passes 1,
`unit_run`; longer runs of VSA steps in closed form by `ramp_jump`) instead of its full loop, and follows each eye's
empty skip cubes ahead of the lattice (`empty_horizon`) so that a run ends only where an eye meets the medium. What
that must not change: the lattice and the counts (skipping on and off give the same image, to float rounding under
VSA, and fetched + skipped = fetched without skipping: `test_skipping`), and each eye's march (below; the images
agree with the kernel's before `ramp_jump` to 125-163 dB PSNR with the same counters, smoke, cloud and phantom at
128^3, 480x270 stereo, `scripts/cacrm_speed.py --compare`; before `empty_horizon`, 123-165 dB).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

from conftest import DEVICE
from volren.camera import Camera, make_views
from volren.data import builtin_scene
from volren.metrics import psnr
from volren.render import CACRM, CMSRM, CACRMConfig, CMSRMConfig
from volren.render.marching.cacrm import idle_run, mat24, ramp_jump, unit_run
from volren.render.marching.vsa import VSAParams, lambda_cap, ramp_slope, vsa_proposal, zero_product
from volren.scene import Scene

VIEWS = make_views(Camera(position=(0.3, 0.5, 2.4), width=48, height=32), "stereo")
BASE = {"samples": 128, "light_samples": 16, "light_grid": 16, "hybrid": False, "adaptive_lod": False,
        "interleave": False}


def test_coupled_pair_equals_each_eye_alone_with_skipping_and_jumps():
    """Uniform steps, no voxel sharing: one loop over the eyes marches each eye as it marches alone (eye 1 through
    the same code as eye 0), with the idle runs on (skipped steps differ: a pair's tiles are culled for both eyes);
    and the pair's image is CMSRM's within the lattices' difference (texel-anchored against CMSRM's: 62.9 dB)."""
    scene = builtin_scene("cloud", 64)
    config = CACRMConfig(**BASE, vsa=False, share_voxels=False)
    coupled = CACRM(config, DEVICE).render(scene, VIEWS)
    alone = CACRM(dataclasses.replace(config, coupling=False), DEVICE).render(scene, VIEWS)
    for a, b in zip(coupled.images, alone.images, strict=True):
        np.testing.assert_array_equal(a, b)
    for key in ("density_samples", "lightmap_lookups"):
        assert coupled.stats.counters[key] == alone.stats.counters[key], key
    assert coupled.stats.counters["skipped_steps"] > 5 * coupled.stats.counters["density_samples"]
    cmsrm = CMSRM(CMSRMConfig(**{k: v for k, v in BASE.items() if k != "interleave"}), DEVICE).render(scene, VIEWS)
    worst = min(psnr(b, a) for a, b in zip(coupled.images, cmsrm.images, strict=True))
    assert worst > 50.0, worst


def half_smoke() -> Scene:
    """The smoke with its front half (towards +z, the camera) emptied: long empty runs in front of the medium that
    cross t = t_max / k_a, where VSA's ramp starts to lengthen the steps."""
    scene = builtin_scene("smoke", 64)
    density = scene.volumes[0].density.copy()
    density[density.shape[0] // 2:] = 0.0
    return dataclasses.replace(scene, volumes=(dataclasses.replace(scene.volumes[0], density=density),))


def slabs() -> Scene:
    """A dense slab, empty space, a thin slab: runs behind a medium (T < 1, f_A large), whose first sample in the
    thin slab is dense at once and smooth enough that VSA's product (not the ramp or 1) decides the step there, so
    that rho', taken from the run's last distance, matters."""
    scene = builtin_scene("smoke", 64)
    density = np.zeros_like(scene.volumes[0].density)
    density[40:52] = 0.6
    density[8:20] = 0.01
    return dataclasses.replace(scene, volumes=(dataclasses.replace(scene.volumes[0], density=density),))


@pytest.mark.parametrize("name", ["half-smoke", "slabs"])
def test_idle_runs_walk_the_lattice_of_the_steps(name):
    """With the fitted VSA, the idle runs (unit steps jumped, ramp steps walked) give the image and counts of the
    loop that fetches every step: the same image with skipping on and off, fetched + skipped = fetched without
    skipping. The half-emptied smoke's runs cross the ramp's start; the slabs put runs between media, where VSA's
    product and previous distance matter."""
    scene = half_smoke() if name == "half-smoke" else slabs()
    views = make_views(Camera(position=(0.2, 0.4, 2.2), width=48, height=32), "stereo")
    config = CACRMConfig(**BASE)
    on = CACRM(config, DEVICE).render(scene, views)
    off = CACRM(dataclasses.replace(config, skip_empty=False), DEVICE).render(scene, views)
    for a, b in zip(on.images, off.images, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)  # `ramp_jump`: float rounding of the lattice
    c_on, c_off = on.stats.counters, off.stats.counters
    assert c_on["density_samples"] + c_on["skipped_steps"] == c_off["density_samples"]
    assert c_on["skipped_steps"] > 0.5 * c_on["density_samples"], (c_on, c_off)  # slabs: 0.68


@wp.kernel
def jump_kernel(states: wp.array(dtype=wp.vec4), segs: wp.array(dtype=mat24), products: wp.array(dtype=wp.vec2),
                checks: wp.array(dtype=wp.vec2), vp: VSAParams, dt: float, out: wp.array(dtype=wp.vec4)):
    i = wp.tid()
    seg = segs[i]
    slope = wp.vec2(ramp_slope(vp, seg[0, 1]), ramp_slope(vp, seg[1, 1]))
    pos, m, k, last = ramp_jump(states[i][0], states[i][1], seg, slope, wp.vec2i(1, 1), wp.vec2i(100000),
                                wp.vec2(1.0), checks[i], wp.vec2(1.0e30), products[i], vp, dt, 0.01)
    out[i] = wp.vec4(pos, m, k, last[0])


def walk(pos, m, seg, product, check, dt, k_a, limit=None):
    """`idle_run`'s loop in float32 (both eyes live, no mesh layers): (steps to the first idle-run stop, the states
    after each step)."""
    f = np.float32
    pos, m, dt = f(pos), f(m), f(dt)
    slope = [f(k_a) / f(seg[e][1]) for e in range(2)]
    states = [(pos, m, None)]
    while pos > f(1e-4) and (limit is None or len(states) <= limit):
        step = min(m, pos)
        t = [f(0.5) * (max(f(seg[e][1]) - pos * dt, f(seg[e][0])) + (f(seg[e][1]) - (pos - step) * dt))
             for e in range(2)]
        if any(t[e] >= f(check[e]) for e in range(2)):
            break
        m = max(f(1.0), *(max(max(slope[e] * t[e], f(product[e])), f(1.0)) for e in range(2)))
        pos = pos - step
        states.append((pos, m, t[0]))
    return len(states) - 1, states


# (pos, m), both eyes' (t_min, t_max), products, next lookups: in front of the medium (ramp steps from the start),
# behind it with constant steps of C = 1.8 (k_a = 0: no ramp), and constant steps C = 1.2 that the ramp overtakes.
JUMPS = {
    "ramp": ((100.0, 1.16), ((2.2, 4.2), (2.21, 4.21)), (0.0, 0.0), (4.15, 4.16), 1.5),
    "constant": ((120.0, 1.8), ((2.2, 4.2), (2.21, 4.21)), (1.8, 1.7), (3.9, 3.95), 0.0),
    "constant-then-ramp": ((140.0, 1.2), ((2.2, 4.2), (2.21, 4.21)), (1.2, 1.1), (4.1, 4.12), 1.5),
}


DT = 0.0096


def jump(pos, m, seg, product, check, k_a):
    """`ramp_jump` from (pos, m) for both eyes live (no mesh layers, no eye left to enter): (pos, m, steps k, eye 0's
    last step midpoint)."""
    vp = VSAParams()
    vp.enabled, vp.k_a, vp.k_b, vp.f_lambda_max, vp.w_lambda, vp.w_t, vp.w_a = 1, k_a, 0.01, 4.0, 1.0, 4.0, 1.0
    vp.lambda_cap = lambda_cap(4.0, 1.0)
    device = "cpu"
    out = wp.zeros(1, dtype=wp.vec4, device=device)
    wp.launch(jump_kernel, dim=1, device=device, inputs=[
        wp.array([wp.vec4(pos, m, 0.0, 0.0)], dtype=wp.vec4, device=device),
        wp.array([mat24(*seg[0], 1.0, 1.0, *seg[1], 1.0, 1.0)], dtype=mat24, device=device),
        wp.array([wp.vec2(*product)], dtype=wp.vec2, device=device),
        wp.array([wp.vec2(*check)], dtype=wp.vec2, device=device), vp, DT, out])
    return out.numpy()[0]


@pytest.mark.parametrize("case", list(JUMPS))
def test_ramp_jump_lands_on_the_step_where_the_loop_stops(case):
    """`ramp_jump`'s closed form (constant steps, Eq. 4's ramp as two geometric sequences, the step of the event by
    bisection) against `idle_run`'s float32 loop: it jumps every step the loop walks before the next skip-cell
    lookup, landing on the loop's (pos, m) to float rounding, with the last step's midpoint."""
    (pos, m), seg, product, check, k_a = JUMPS[case]
    steps, states = walk(pos, m, seg, product, check, DT, k_a)
    assert steps > 20, steps
    got_pos, got_m, k, last = jump(pos, m, seg, product, check, k_a)
    # The event: the lookup, or (constant steps) the step after which the ramp's proposal passes C, where the steps
    # turn into the ramp's and `idle_run` jumps again.
    turn = next((i - 1 for i, (_, mi, _) in enumerate(states) if i and product[0] > 0 and mi > max(product)), steps)
    assert k == turn, (k, turn, steps)
    want_pos, want_m, want_last = states[int(k)]
    assert got_pos == pytest.approx(want_pos, abs=1e-3) and got_m == pytest.approx(want_m, abs=1e-5)
    assert last == pytest.approx(want_last, abs=1e-5)


@pytest.mark.parametrize("case", list(JUMPS))
def test_ramp_jump_leaves_a_lookup_on_a_step_midpoint_to_the_loop(case):
    """A skip-cell lookup exactly at the float32 midpoint of step j (the loop's event: t >= check there): the jump
    takes steps 0 .. j - 1 and never step j, which the float64 closed form puts a hair before the lookup as often
    as after (JUMP_SLACK: without it the ramp's and the constant steps' jumps took the event's step for most of
    these lookups)."""
    (pos, m), seg, product, _, k_a = JUMPS[case]
    _, states = walk(pos, m, seg, product, (1.0e9, 1.0e9), DT, k_a, limit=60)
    for j in range(15, 45):
        check = (float(states[j + 1][2]), 1.0e9)
        steps, _ = walk(pos, m, seg, product, check, DT, k_a)
        k = jump(pos, m, seg, product, check, k_a)[2]
        assert k <= steps, (j, k, steps)
        if product[0] == 0:  # the ramp: no turn before the lookup
            assert k == steps, (j, k, steps)


@wp.kernel
def unit_run_kernel(pos: float, seg: mat24, product: wp.vec2, check: wp.vec2, vp: VSAParams, dt: float,
                    out: wp.array(dtype=float)):
    slope = wp.vec2(ramp_slope(vp, seg[0, 1]), ramp_slope(vp, seg[1, 1]))
    out[0] = unit_run(pos, seg, slope, wp.vec2i(1, 1), wp.vec2i(100000), wp.vec2(1.0), check, wp.vec2(1.0e30),
                      product, vp, dt, 0.01)


# pos, products, next lookups, k_a (both eyes' segments as in JUMPS): where the ramp passes 1 first, where the
# lookup comes first, a product above 1 (no unit step), and no ramp (k_a = 0).
UNIT_RUNS = {
    "ramp": (200.0, (0.0, 0.0), (4.15, 4.16), 1.5),
    "lookup": (200.0, (0.5, 0.0), (2.5, 4.16), 1.5),
    "product": (200.0, (1.2, 0.0), (4.15, 4.16), 1.5),
    "no-ramp": (150.0, (0.0, 1.0), (4.15, 3.9), 0.0),
}


@pytest.mark.parametrize("case", list(UNIT_RUNS))
def test_unit_runs_end_in_closed_form_where_the_loop_leaves_unit_steps(case):
    """`unit_run`'s closed form for a run of unit steps (m = 1) against `idle_run`'s float32 loop: it ends where
    the loop's proposal leaves 1 (Eq. 4's ramp k_a t / t_max passing 1, or a product above 1) or a lookup comes,
    at most one step past by rounding (which `idle_run` checks step by step: without the ramp's bound it walked
    back one step at a time from the lookup, ~15% of the smoke's coupled march)."""
    pos, product, check, k_a = UNIT_RUNS[case]
    seg = ((2.2, 4.2), (2.21, 4.21))
    _, states = walk(pos, 1.0, seg, product, check, DT, k_a)
    exact = next((i - 1 for i, (_, mi, _) in enumerate(states) if i and mi > 1.0), len(states) - 1)
    vp = VSAParams()
    vp.enabled, vp.k_a, vp.k_b, vp.f_lambda_max, vp.w_lambda, vp.w_t, vp.w_a = 1, k_a, 0.01, 4.0, 1.0, 4.0, 1.0
    out = wp.zeros(1, dtype=float, device="cpu")
    wp.launch(unit_run_kernel, dim=1, device="cpu", inputs=[
        pos, mat24(*seg[0], 1.0, 1.0, *seg[1], 1.0, 1.0), wp.vec2(*product), wp.vec2(*check), vp, DT, out])
    k = out.numpy()[0]
    assert exact <= k <= exact + 1, (k, exact, len(states) - 1)
    assert (exact == 0) == (case == "product") and (case != "ramp" or exact < len(states) - 10), (exact, states)


@wp.kernel
def idle_run_kernel(poss: wp.array(dtype=float), seg: mat24, checks: wp.array(dtype=wp.vec2), vp: VSAParams,
                    dt: float, out: wp.array(dtype=wp.vec4), units: wp.array(dtype=float)):
    """Per start pos (m = 1, both eyes live, products 0, no mesh layers): `unit_run`'s closed-form unit steps, and
    what `idle_run` returns: (pos, m, eye steps, eye 0's last step midpoint)."""
    i = wp.tid()
    slope = wp.vec2(ramp_slope(vp, seg[0, 1]), ramp_slope(vp, seg[1, 1]))
    product = wp.vec2(0.0)
    units[i] = unit_run(poss[i], seg, slope, wp.vec2i(1, 1), wp.vec2i(100000), wp.vec2(1.0), checks[i],
                        wp.vec2(1.0e30), product, vp, dt, 0.01)
    pos, m, steps, _, last = idle_run(poss[i], 1.0, seg, slope, wp.vec2i(1, 1), wp.vec2i(100000), wp.vec2(1.0),
                                      checks[i], wp.vec2(1.0e30), product, vp, dt, 0.01)
    out[i] = wp.vec4(pos, m, steps, last[0])


def test_idle_run_leaves_unit_steps_where_the_ramp_passes_1_in_a_step_clipped_at_t_min():
    """An idle run that starts with its first step cut at the segment's entry t_min (an eye's step straddling its
    volume's face) and Eq. 4's ramp k_a t / t_max passing 1 inside that step: `unit_run` bounds unit steps by their
    unclipped midpoints and counts that step as a unit step, but its clipped midpoint is past t_max / k_a, so VSA
    proposes the next step longer than 1. `idle_run` must walk it as the loop does: the (pos, m) after it, the eye
    steps and the last midpoint are the float32 loop's for every start across the step (a unit jump there kept m at
    1: the next step up to 6e-4 base steps short of VSA's, and the lattice behind it off)."""
    k_a = 1.5
    seg = ((2.7985, 4.2), (2.7985, 4.2))  # t_max / k_a = 2.8: just past t_min
    poss = np.arange(146.0, 147.0, 1.0 / 32.0, dtype=np.float32)  # the first step [pos - 1, pos) starts before t_min
    ends = np.float32(4.2) - (poss - np.float32(1.0)) * np.float32(DT)  # its far end
    checks = np.repeat((ends + np.float32(0.25 * DT))[:, None], 2, axis=1)  # a lookup just behind: the run's end
    vp = VSAParams()
    vp.enabled, vp.k_a, vp.k_b, vp.f_lambda_max, vp.w_lambda, vp.w_t, vp.w_a = 1, k_a, 0.01, 4.0, 1.0, 4.0, 1.0
    out = wp.zeros(len(poss), dtype=wp.vec4, device="cpu")
    units = wp.zeros(len(poss), dtype=float, device="cpu")
    wp.launch(idle_run_kernel, dim=len(poss), device="cpu", inputs=[
        wp.array(poss, dtype=float, device="cpu"), mat24(*seg[0], 1.0, 1.0, *seg[1], 1.0, 1.0),
        wp.array(checks, dtype=wp.vec2, device="cpu"), vp, DT, out, units])
    ramped = 0
    for pos, check, got, unit in zip(poss, checks, out.numpy(), units.numpy(), strict=True):
        steps, states = walk(pos, 1.0, seg, (0.0, 0.0), check, DT, k_a)
        want_pos, want_m, want_last = states[steps]
        assert steps == 1, (pos, steps)
        np.testing.assert_allclose(got, [want_pos, want_m, 2 * steps, want_last], rtol=1e-7, err_msg=str(pos))
        ramped += int(unit == 1.0 and want_m > 1.0)  # `unit_run` took the step as a unit one; the loop's m > 1
    assert ramped >= 8, ramped  # 11 of the 32 starts (pos 146.34 - 146.66)


def test_vsa_idle_runs_are_jumped_and_counted():
    """The half-emptied smoke's long runs in front of the medium, under VSA's ramp: a third of the skipped steps are
    taken by `ramp_jump` (counted as jumped_steps; the rest in runs too short to jump), none with uniform steps (their
    unit runs are jumped exactly)."""
    scene = half_smoke()
    views = make_views(Camera(position=(0.2, 0.4, 2.2), width=48, height=32), "stereo")
    vsa = CACRM(CACRMConfig(**BASE), DEVICE).render(scene, views).stats.counters
    uniform = CACRM(CACRMConfig(**BASE, vsa=False), DEVICE).render(scene, views).stats.counters
    assert uniform["jumped_steps"] == 0 < uniform["skipped_steps"]
    assert vsa["jumped_steps"] > 0.2 * vsa["skipped_steps"], vsa  # measured 0.31


@pytest.mark.parametrize("vsa", [True, False])
def test_empty_horizon_ends_idle_runs_where_an_eye_meets_the_medium(vsa):
    """The smoke (94% empty voxels): an eye's empty skip cubes are followed ahead of the lattice (`empty_horizon`),
    so the pair's idle runs end where an eye reaches a cell that is not empty, not at each cube boundary of either
    eye: 1.49 runs a pair (4.85 when each lookup waits for a step midpoint), with VSA and with uniform steps; which
    steps are skipped is unchanged (`test_idle_runs_walk_the_lattice_of_the_steps`)."""
    views = make_views(Camera(position=(0.2, 0.4, 2.2), width=48, height=32), "stereo")
    c = CACRM(CACRMConfig(**BASE, vsa=vsa), DEVICE).render(builtin_scene("smoke", 64), views).stats.counters
    per_pair = c["idle_runs"] / (c["rays"] / 2)
    assert 0.5 < per_pair < 2.0, (per_pair, c)
    assert c["skipped_steps"] > 10 * c["density_samples"], c


@wp.kernel
def proposal_kernel(cases: wp.array(dtype=wp.vec4), vp: VSAParams, out: wp.array(dtype=wp.vec2)):
    """Per case (rho, prev, T, t): `vsa_proposal` at t (ramp slope k_a / 4, prev at t - 0.01), and the product of a
    zero sample at T through `zero_product`, its cache carried from the case before."""
    cached = wp.vec2(-1.0, 0.0)
    for i in range(cases.shape[0]):
        c = cases[i]
        cached = zero_product(vp, cached, c[2], 0.05)
        out[i] = wp.vec2(vsa_proposal(vp, c[3], ramp_slope(vp, 4.0), c[0], c[1], c[3] - 0.01, c[2], 0.01, 0.05),
                         cached[1])


def test_vsa_proposals_follow_eq_4_to_6():
    """The proposal (with its shortcut: where lambda_cap f_A cannot beat the ramp, Eq. 5-6 are not evaluated) and the
    cached product of a zero sample against Eq. 4-6 in float64, over media in front of and behind, thin and dense,
    smooth and steep, with T repeated and changed between cases (the cache must follow T)."""
    k_a, k_b, cap, w = 1.5, 0.01, 4.0, (1.0, 4.0, 1.0)
    vp = VSAParams()
    vp.enabled, vp.k_a, vp.k_b, vp.f_lambda_max, vp.w_lambda, vp.w_t, vp.w_a = 1, k_a, k_b, cap, *w
    vp.lambda_cap = lambda_cap(cap, w[0])
    rng = np.random.default_rng(3)
    cases = np.column_stack([rng.choice([0.0, 0.001, 0.02, 0.3, 1.0], 400), rng.choice([0.0, 0.001, 0.25], 400),
                             np.repeat(rng.choice([1.0, 0.9, 0.7, 0.4, 0.1], 100), 4), rng.uniform(0.5, 4.0, 400)])
    out = wp.zeros(len(cases), dtype=wp.vec2, device="cpu")
    wp.launch(proposal_kernel, dim=1, inputs=[wp.array(cases.astype(np.float32), dtype=wp.vec4, device="cpu"), vp,
                                              out], device="cpu")
    got = out.numpy()
    rho, prev, trans, t = cases.astype(np.float32).astype(np.float64).T

    def product(rho, drho, trans):
        f_l = np.where(np.abs(drho) * cap > k_b, k_b / np.maximum(np.abs(drho), 1e-30), cap)
        f_t = np.clip(1 - 0.05 * (rho + drho), 0, 1)
        return f_l ** w[0] * f_t ** w[1] * np.clip(1 - trans, 0, 1) ** w[2]

    drho = (rho - prev) * 0.01 / 0.01
    want = np.maximum(np.maximum(k_a * t / 4.0, product(rho, drho, trans)), 1.0)
    np.testing.assert_allclose(got[:, 0], want, rtol=2e-5)
    np.testing.assert_allclose(got[:, 1], product(0.0, 0.0, trans), rtol=2e-5)
    assert (want > np.maximum(k_a * t / 4.0, 1.0)).mean() > 0.1  # the product decides 14.5% of the cases
