"""scripts/gpu_suite.py: the GPU session's one prepared command, checked here on the CPU by its dry run (the plan, the
sizes, the test selection and the parity comparison itself), so a lent device's minutes are not lost to a typo."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
SPEC = importlib.util.spec_from_file_location("gpu_suite", ROOT / "scripts" / "gpu_suite.py")
gpu_suite = importlib.util.module_from_spec(SPEC)
sys.modules["gpu_suite"] = gpu_suite  # its dataclasses look their module up there
SPEC.loader.exec_module(gpu_suite)


def test_the_dry_run_checks_the_plan_collects_the_tests_and_runs_parity_on_the_cpu(tmp_path, capsys):
    assert gpu_suite.main(["--dry-run", "--out", str(tmp_path)]) == 0
    plan = json.loads((tmp_path / "plan.json").read_text())
    steps = {s["step"]: s for s in plan["steps"]}
    assert sum(s["limit_s"] for s in plan["steps"]) <= gpu_suite.BUDGET_S <= gpu_suite.CALL_LIMIT_S
    # the tests run on CUDA, the benches at full size on CUDA, every result under --out
    assert steps["tests"]["env"] == {"VOLREN_TEST_DEVICE": "cuda"}
    benches = [s for s in plan["steps"] if s["step"].startswith("bench-")]
    assert {"bench-dssrm", "bench-binocular", "bench-vpt", "bench-gi", "bench-viewers"} <= {s["step"] for s in benches}
    for s in benches:
        argv = s["argv"]
        assert argv[argv.index("--device") + 1] == "cuda" and "--quick" not in argv
        assert argv[argv.index("--out") + 1].startswith(str(tmp_path))
    collected = plan["tests_collected"]
    assert int(collected.split("/")[0]) > 1000, collected
    assert [r["method"] for r in plan["parity"]] == ["dssrm", "cmsrm", "cacrm", "reference", "fog", "vpt"]
    assert all(r["passed"] for r in plan["parity"])
    assert all(r["psnr_db"] == "inf" for r in plan["parity"][:5])  # the CPU against itself: the same image
    sizes = {s["step"]: s for s in plan["sizes"]}
    assert sizes["bench-oit"]["instances"] == 36 and sizes["bench-dssrm"]["max_pixels"] == 3840 * 2160
    assert "dry run: 10 steps" in capsys.readouterr().out


def test_the_plan_refuses_what_would_waste_device_time():
    steps = gpu_suite.plan(Path("/tmp/x"))
    assert gpu_suite.check_plan(steps) == []
    bad = [dataclasses.replace(steps[0], limit_s=601),
           dataclasses.replace(steps[2], suite="nosuch"),
           dataclasses.replace(steps[2], suite="gi", repeats=2, settings={}),
           dataclasses.replace(steps[2], suite="vpt", repeats=None, settings={"framez": 3}),
           dataclasses.replace(steps[2], suite="dssrm", repeats=None, settings={"repeats": 3})]
    problems = gpu_suite.check_plan(bad, budget_s=10_000)
    assert any("limit 601 s exceeds one call's 600 s" in p for p in problems)
    assert any("no bench suite 'nosuch'" in p for p in problems)
    assert any("bench gi does not take --repeats" in p for p in problems)
    assert any("bench vpt has no setting 'framez'" in p for p in problems)
    assert any("bench dssrm does not take --set" in p for p in problems)
    over = gpu_suite.check_plan([*steps, dataclasses.replace(steps[2], name="more", limit_s=60)])
    assert over == [f"the steps' limits add up to {sum(s.limit_s for s in steps) + 60} s, over the 540 s budget"]


def test_only_selects_steps_and_refuses_unknown_names(tmp_path, capsys):
    with pytest.raises(SystemExit):
        gpu_suite.main(["--dry-run", "--only", "tests,bench-nope", "--out", str(tmp_path)])
    assert "no step bench-nope" in capsys.readouterr().err
    assert gpu_suite.main(["--dry-run", "--only", "bench-dssrm", "--out", str(tmp_path)]) == 0
    plan = json.loads((tmp_path / "plan.json").read_text())
    assert [s["step"] for s in plan["steps"]] == ["bench-dssrm"] and "parity" not in plan


def noisy(image: np.ndarray, seeds: int, rng: np.random.Generator, sigma: float = 0.2) -> np.ndarray:
    return image[None] + rng.normal(0.0, sigma, (seeds, *image.shape))


def test_vpt_parity_passes_independent_noise_and_fails_a_bias():
    rng = np.random.default_rng(7)
    image = np.zeros((96, 160, 4))
    image[24:72, 40:120] = 1.0
    a = noisy(image, 8, rng)
    assert gpu_suite.statistical_match(a, noisy(image, 8, rng))["passed"]
    biased = gpu_suite.statistical_match(a, noisy(image * 1.01, 8, rng))  # 1% brighter where it is lit
    assert not biased["passed"] and biased["z_mean"] > 3  # too little for any block alone, not for the whole
    assert biased["blocks_over_4_sigma"] <= 0.01
    local = image.copy()
    local[24:40, 40:72] *= 1.5  # one region wrong: 8 of 240 blocks, the whole image's mean barely moves
    result = gpu_suite.statistical_match(a, noisy(local, 8, rng))
    assert not result["passed"] and result["blocks_over_4_sigma"] > 0.01
    # a background that differs where no seed varies (both noiseless) fails too
    flat = np.zeros((4, 16, 16, 4))
    assert not gpu_suite.statistical_match(flat, flat + 0.1)["passed"]


def test_deterministic_parity_fails_below_50_db(monkeypatch, tmp_path):
    def render(method, device, width, height, **settings):
        rng = np.random.default_rng(settings.get("seed", 0) + (0 if device == "a" else 99))
        img = np.full((height, width, 4), 0.5)
        return img + (0.02 if device == "b" and method == "cacrm" else 0.0) + rng.normal(0, 0.05, img.shape) * (
            method == "vpt")

    monkeypatch.setattr(gpu_suite, "_render", render)
    out = tmp_path / "parity.json"
    assert gpu_suite.main(["parity", "--devices", "a,b", "--size", "64x40", "--vpt-seeds", "4", "--out", str(out)]) == 1
    rows = {r["method"]: r for r in json.loads(out.read_text())["rows"]}
    assert not rows["cacrm"]["passed"] and rows["cacrm"]["psnr_db"] < 50  # 0.02 of 0.5: 34 dB
    assert rows["dssrm"]["passed"] and rows["vpt"]["passed"]


def test_wheels_are_joined_from_their_parts_and_listed_in_the_plan(tmp_path):
    """`--wheels`: the warp-lang wheel arrives in 50 MB parts (`device-wheels.sh`), the small wheels whole; the dry run
    lists what it would install, parts joined in order; a gap in the parts is refused before any install."""
    parts = tmp_path / "parts"
    parts.mkdir()
    for i, chunk in enumerate((b"PK\x03\x04a", b"bc", b"d")):
        (parts / f"warp_lang-1.19.0-py3-none-manylinux.whl.{i:02d}").write_bytes(chunk)
    (parts / "nibabel-5.4.2-py3-none-any.whl").write_bytes(b"PK")
    out = tmp_path / "out"
    assert gpu_suite.main(["--dry-run", "--only", "bench-dssrm", "--wheels", str(parts), "--out", str(out)]) == 0
    plan = json.loads((out / "plan.json").read_text())
    assert plan["wheels"] == ["nibabel-5.4.2-py3-none-any.whl", "warp_lang-1.19.0-py3-none-manylinux.whl"]
    joined = gpu_suite.wheels_in(parts)["warp_lang-1.19.0-py3-none-manylinux.whl"]
    assert b"".join(p.read_bytes() for p in joined) == b"PK\x03\x04abcd"
    (parts / "warp_lang-1.19.0-py3-none-manylinux.whl.01").unlink()
    with pytest.raises(SystemExit, match=r"not \.00 to"):
        gpu_suite.wheels_in(parts)
