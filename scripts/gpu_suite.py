"""The one prepared command for a session lent a GPU (issue 46): the test suite on CUDA, every method's default scene
on CUDA against the CPU, and the benchmark suites at full size, each step under its own time limit so the whole fits
one device call (about 9 minutes of the session's 15), every result written under ``$OUT``.

On the device, from a clean tree of HEAD, with the wheels the device lacks copied into /tmp/parts by the earlier
calls (`../shared/tools/device-wheels.sh` splits and lists them; docs/BENCHMARKS.md, "Running the GPU suites"):

    python3 scripts/gpu_suite.py --wheels /tmp/parts --out $OUT/gpu-suite

Here, on the CPU, before any device time is spent (CI runs this through tests/test_gpu_suite.py):

    python scripts/gpu_suite.py --dry-run --out out/gpu-suite

The dry run checks the plan (every step's limit within one call, their sum within the budget, every bench suite,
``--repeats`` and ``--set`` key known to the suite), prints each bench's full sizes and an estimate of its device
memory against the smallest lent GPU, collects the test selection as the device run would, and runs the parity
comparison itself on the CPU against the CPU at a tiny size.

Parity: a deterministic method passes at >= 50 dB PSNR between the devices (floating-point order differs, the
algorithm does not); VPT is compared statistically: ``--vpt-seeds`` independent frames per device, 8x8-pixel block
means, each block's difference against its standard error from the seeds' spread; it passes when the whole image's
mean differs by less than 3 standard errors and at most 1% of blocks by more than 4 (about 0.006% of blocks would by
chance).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
CALL_LIMIT_S = 600
"""the device tool's limit on one command"""
BUDGET_S = 540
"""the suite's steps together: one call, with a minute left for the machine's start and the result's transfer"""
GPU_MEMORY_GIB = 78.0
"""the smallest GPU lent (an H100; the H200 has 139)"""
DETERMINISTIC = ("dssrm", "cmsrm", "cacrm", "reference", "fog")
PARITY_DB = 50.0


@dataclass(frozen=True)
class Step:
    name: str
    limit_s: int
    argv: tuple[str, ...]
    env: dict[str, str] = field(default_factory=dict)
    suite: str | None = None
    """the bench suite a bench step runs"""
    repeats: int | None = None
    settings: dict = field(default_factory=dict)
    """``--set`` entries for the bench suite"""


TEST_ARGS = ("-q", "-n", "12", "-p", "no:cacheprovider", "--timeout", "120", "--ignore", "tests/test_animate.py",
             "-k", "not usd", "tests")
"""The device image has no usd-core or imageio-ffmpeg (too large to carry): their tests are left out."""

BENCHES: tuple[tuple[str, int, int | None, dict], ...] = (
    ("dssrm", 35, None, {}),
    ("resolution", 45, None, {}),
    ("binocular", 55, 2, {"frames": 12}),
    ("vpt", 55, 2, {"score_every": 20, "reference_spp": 256, "variance_sequences": 16}),
    ("gi", 40, None, {"frames": 20, "warmup": 10, "gt_every": 10, "dynamic_frames": 20}),
    ("oit", 30, None, {}),
    ("integrated", 30, None, {}),
    ("viewers", 40, 2, {}),
)
"""(suite, limit [s], --repeats, --set): the suites whose tables are the papers' GPU figures. `peers` (VTK's CPU
ray caster), `serve`, `batch` and `load` measure the host and Ray, not the GPU; `interactive` is the CPU preset.
Sizes (volumes, images, spp) are the full ones; repeats, camera paths, ground-truth spp and scored frames are cut
where a suite's own would not fit its limit, as the CPU's full-size runs cut them: the 2026-11-29 H200 run took 25 s
for `dssrm` and more than 140 s for `binocular` and `viewers` each at their own frame counts. A step that overruns is
stopped and marked in summary.json; the first lent session reads each step's seconds there and sets these."""


def plan(out: Path, python: str = sys.executable) -> list[Step]:
    steps = [
        Step("tests", 150, (python, "-m", "pytest", *TEST_ARGS, "--junitxml", str(out / "tests.xml")),
             env={"VOLREN_TEST_DEVICE": "cuda"}),
        Step("parity", 60, (python, str(Path(__file__).resolve()), "parity", "--devices", "cuda,cpu",
                            "--out", str(out / "parity.json"))),
    ]
    for suite, limit, repeats, settings in BENCHES:
        argv = [python, "-m", "volren.cli", "bench", suite, "--device", "cuda", "--out", str(out / "bench")]
        if repeats is not None:
            argv += ["--repeats", str(repeats)]
        argv += [a for k, v in settings.items() for a in ("--set", f"{k}={json.dumps(v)}")]
        steps.append(Step(f"bench-{suite}", limit, tuple(argv), suite=suite, repeats=repeats, settings=settings))
    return steps


def check_plan(steps: list[Step], budget_s: int = BUDGET_S) -> list[str]:
    """What would waste device time: a step longer than one call, steps longer than the budget together, a bench
    suite, ``--repeats`` or ``--set`` key the suite does not take (each refused only once it runs)."""
    from volren.bench.runner import all_suites

    problems = [f"{s.name}: limit {s.limit_s} s exceeds one call's {CALL_LIMIT_S} s" for s in steps
                if not 0 < s.limit_s <= CALL_LIMIT_S]
    total = sum(s.limit_s for s in steps)
    if total > budget_s:
        problems.append(f"the steps' limits add up to {total} s, over the {budget_s} s budget")
    suites = all_suites()
    for s in (s for s in steps if s.suite):
        if s.suite not in suites:
            problems.append(f"{s.name}: no bench suite '{s.suite}' (suites: {', '.join(suites)})")
            continue
        if s.repeats is not None and not suites[s.suite].repeats:
            problems.append(f"{s.name}: bench {s.suite} does not take --repeats")
        if s.settings:
            full = _full_config(s.suite)
            if not suites[s.suite].settable or full is None:
                problems.append(f"{s.name}: bench {s.suite} does not take --set")
            else:
                problems += [f"{s.name}: bench {s.suite} has no setting '{k}' (it has {', '.join(full)})"
                             for k in s.settings if k not in full]
    return problems


def _full_config(suite: str) -> dict | None:
    import importlib

    return getattr(importlib.import_module(f"volren.bench.{suite}"), "FULL", None)


def _pixels(cfg: dict) -> int:
    sizes = [tuple(s) for s in cfg.get("sizes", [])] + ([tuple(cfg["size"])] if "size" in cfg else [])
    return max((w * h for w, h in sizes), default=3840 * 2160)


def size_estimate(step: Step) -> dict:
    """A bench step's full sizes and an upper estimate of its device memory: per voxel the density, its mip and
    max-density pyramids, the light map and a 16-coefficient GI grid per colour (4 + 4 + 4 + 4 + 192 bytes at
    most), for one volume or for each instance of (n/2)^3 (the instance scenes), and per pixel and view 64 bytes of
    images and buffers (a fog scene's froxels are 16 bytes per 8x8 pixels and slice: less)."""
    cfg = {**(_full_config(step.suite) or {}), **step.settings}
    n = int(cfg.get("resolution", 0))
    instances = max(cfg.get("counts", [1])) if "resolution" in cfg else 0
    voxels = n**3 if instances <= 1 else instances * (n // 2) ** 3
    nbytes = voxels * 208 + _pixels(cfg) * 2 * 64
    return {"step": step.name, "resolution": n, "instances": instances, "max_pixels": _pixels(cfg),
            "estimate_gib": round(nbytes / 2**30, 2)}


def _default_view(method: str, width: int, height: int):
    """Each method's default scene (the CLI's: smoke, and `hall` for fog) and one camera on it."""
    from volren.camera import Camera
    from volren.data import builtin_scene, classic_look
    from volren.data.fog_scenes import fog_scene, fog_scene_camera

    if method == "fog":
        spot = fog_scene_camera("hall")
        return fog_scene("hall", 0.0), Camera(position=spot["position"], look_at=spot["look_at"], width=width,
                                               height=height)
    # the light the parity floors were set under: under the key light of issue 45.6 a quarter of vpt's 8x8 blocks
    # of two CPU runs were past 4 sigma (the floor allows 1%)
    return classic_look(builtin_scene("smoke", 64)), Camera(position=(0.0, 0.4, 3.2), width=width, height=height)


def _render(method: str, device: str, width: int, height: int, **settings) -> np.ndarray:
    import volren as vr

    scene, cam = _default_view(method, width, height)
    return vr.render(scene, cam, method=method, quality="default", device=device, **settings).images[0]


def statistical_match(a: np.ndarray, b: np.ndarray, block: int = 8) -> dict:
    """``a``, ``b``: (seeds, H, W, 4) independent frames of one image from two devices. Block means per seed; the
    difference of the seeds' means against its standard error, per block and over the whole image."""
    def blocks(x):
        s, h, w = x.shape[:3]
        h, w = h - h % block, w - w % block
        return x[:, :h, :w].reshape(s, h // block, block, w // block, block, -1).mean(axis=(2, 4, 5))

    ba, bb = blocks(a.astype(np.float64)), blocks(b.astype(np.float64))
    se = np.sqrt(ba.var(axis=0, ddof=1) / len(ba) + bb.var(axis=0, ddof=1) / len(bb))
    diff = ba.mean(axis=0) - bb.mean(axis=0)
    live = se > 0
    z_blocks = np.abs(diff[live]) / se[live]
    ga, gb = ba.mean(axis=(1, 2)), bb.mean(axis=(1, 2))
    se_all = np.sqrt(ga.var(ddof=1) / len(ga) + gb.var(ddof=1) / len(gb))
    z_all = abs(ga.mean() - gb.mean()) / se_all if se_all > 0 else (0.0 if ga.mean() == gb.mean() else np.inf)
    identical_elsewhere = bool(np.all(diff[~live] == 0))
    over = float((z_blocks > 4).mean()) if z_blocks.size else 0.0
    return {"z_mean": round(float(z_all), 3), "blocks_over_4_sigma": round(over, 4),
            "passed": bool(z_all < 3 and over <= 0.01 and identical_elsewhere)}


def parity(devices: tuple[str, str], width: int, height: int, seeds: int) -> list[dict]:
    """Every method's default scene on both devices: PSNR for the deterministic ones, the statistical test for VPT."""
    from volren.metrics import psnr

    rows = []
    for method in (*DETERMINISTIC, "vpt"):
        start = time.perf_counter()
        if method == "vpt":
            frames = [np.stack([_render("vpt", d, width, height, seed=s + 1000 * k) for s in range(seeds)])
                      for k, d in enumerate(devices)]
            row = {"method": method, **statistical_match(*frames)}
        else:
            a, b = (_render(method, d, width, height) for d in devices)
            db = psnr(b, a)
            row = {"method": method, "psnr_db": round(db, 2) if np.isfinite(db) else "inf", "passed": db >= PARITY_DB}
        row["seconds"] = round(time.perf_counter() - start, 1)
        print(f"parity {method}: {row}", flush=True)
        rows.append(row)
    return rows


def _collect(step: Step) -> tuple[int, str]:
    """The test step's selection collected here as the device would collect it (the CUDA device is only named)."""
    argv = [a for a in step.argv if not a.startswith("--junitxml") and not a.endswith("tests.xml")]
    argv = [*argv[:3], "--collect-only", *[a for a in argv[3:] if a not in ("-n", "12")]]
    proc = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=300,
                          env={**os.environ, **step.env})
    return proc.returncode, (proc.stdout.strip().splitlines() or [""])[-1]


def wheels_in(folder: Path) -> dict[str, list[Path]]:
    """The wheels in ``folder`` by name: whole ``*.whl`` files, and ``NAME.whl.00``, ``.01``, ... parts (the pieces
    `../shared/tools/device-wheels.sh` splits warp-lang into, copied there by the earlier calls), in order."""
    wheels = {p.name: [p] for p in sorted(folder.glob("*.whl"))}
    for first in sorted(folder.glob("*.whl.00")):
        name = first.name[: -len(".00")]
        parts = sorted(folder.glob(f"{name}.[0-9][0-9]"))
        if [p.name for p in parts] != [f"{name}.{i:02d}" for i in range(len(parts))]:
            raise SystemExit(f"gpu-suite: --wheels {folder}: the parts of {name} are not .00 to .{len(parts) - 1:02d}")
        wheels[name] = parts
    return wheels


def install_wheels(folder: Path, site: Path) -> list[str]:
    """Join each wheel's parts and install every wheel into ``site`` (no index, no dependencies: the device has no
    network); return their names."""
    wheels = wheels_in(folder)
    joined = site.parent / "gpu-suite-wheels"
    joined.mkdir(parents=True, exist_ok=True)
    files = []
    for name, parts in wheels.items():
        target = joined / name
        with open(target, "wb") as out:
            for part in parts:
                out.write(part.read_bytes())
        files.append(str(target))
    if files:
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile",
                        "--upgrade", "--target", str(site), *files], check=True, timeout=300)
    return sorted(wheels)


def run_steps(steps: list[Step], out: Path) -> list[dict]:
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    results = []
    for step in steps:
        start = time.perf_counter()
        with open(logs / f"{step.name}.log", "w") as log:
            try:
                rc = subprocess.run(step.argv, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, timeout=step.limit_s,
                                    env={**os.environ, **step.env}).returncode
                timed_out = False
            except subprocess.TimeoutExpired:
                rc, timed_out = None, True
        row = {"step": step.name, "rc": rc, "timed_out": timed_out, "seconds": round(time.perf_counter() - start, 1),
               "limit_s": step.limit_s}
        print(f"gpu-suite {step.name}: {'timed out' if timed_out else f'rc {rc}'} in {row['seconds']} s", flush=True)
        results.append(row)
    return results


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command")
    p = sub.add_parser("parity", help="only the parity comparison")
    p.add_argument("--devices", default="cuda,cpu", help="two devices, comma-separated (default cuda,cpu)")
    p.add_argument("--size", default="160x90", help="WxH (default 160x90)")
    p.add_argument("--vpt-seeds", type=int, default=8, help="independent VPT frames per device (default 8)")
    p.add_argument("--out", type=Path, required=True, help="the JSON file to write")
    ap.add_argument("--out", type=Path, default=Path(os.environ.get("OUT", "out")) / "gpu-suite",
                    help="folder for every result (default $OUT/gpu-suite)")
    ap.add_argument("--dry-run", action="store_true", help="check the plan and sizes on the CPU; no GPU needed")
    ap.add_argument("--only", help="comma-separated step names (default: all)")
    ap.add_argument("--wheels", type=Path, help="a folder of wheels (and split wheel parts) the device lacks: joined "
                    "and installed into --site first, which every step then imports before the image's packages")
    ap.add_argument("--site", type=Path, default=Path("/tmp/site"), help="where --wheels go (default /tmp/site)")
    args = ap.parse_args(argv)
    if args.wheels is not None and not args.wheels.is_dir():
        ap.error(f"--wheels: no folder {args.wheels}")

    if args.command == "parity":
        width, height = (int(v) for v in args.size.lower().split("x"))
        devices = tuple(args.devices.split(","))
        if len(devices) != 2 or args.vpt_seeds < 2:
            ap.error("parity: --devices takes two devices and --vpt-seeds at least 2")
        rows = parity(devices, width, height, args.vpt_seeds)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"devices": devices, "size": [width, height], "rows": rows}, indent=1))
        return 0 if all(r["passed"] for r in rows) else 1

    steps = plan(args.out)
    if args.only:
        names = args.only.split(",")
        unknown = sorted(set(names) - {s.name for s in steps})
        if unknown:
            ap.error(f"--only: no step {', '.join(unknown)} (steps: {', '.join(s.name for s in steps)})")
        steps = [s for s in steps if s.name in names]
    problems = check_plan(steps)
    for problem in problems:
        print(f"gpu-suite plan: {problem}", file=sys.stderr)
    if problems:
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    sizes = [size_estimate(s) for s in steps if s.suite]
    over = [s for s in sizes if s["estimate_gib"] > GPU_MEMORY_GIB]
    for s in sizes:
        data = f"{s['instances']} x {s['resolution']}^3" if s["resolution"] else "a fog scene"
        print(f"gpu-suite size {s['step']}: {data}, up to {s['max_pixels']:,} px a view, about {s['estimate_gib']} GiB"
              f" of the {GPU_MEMORY_GIB:.0f} GiB", flush=True)
    summary = {"dry_run": args.dry_run, "budget_s": BUDGET_S, "steps": [
        {"step": s.name, "limit_s": s.limit_s, "argv": list(s.argv), "env": s.env} for s in steps], "sizes": sizes}
    if args.wheels is not None:
        summary["wheels"] = sorted(wheels_in(args.wheels))
        print(f"gpu-suite wheels: {', '.join(summary['wheels']) or 'none'} from {args.wheels}", flush=True)
    if args.dry_run:
        if over:
            print(f"gpu-suite plan: {', '.join(s['step'] for s in over)} would not fit {GPU_MEMORY_GIB} GiB",
                  file=sys.stderr)
            return 2
        test = next((s for s in steps if s.name == "tests"), None)
        if test is not None:
            rc, line = _collect(test)
            summary["tests_collected"] = line
            print(f"gpu-suite tests: {line}", flush=True)
            if rc != 0:
                print("gpu-suite plan: the test selection does not collect", file=sys.stderr)
                return 2
        if any(s.name == "parity" for s in steps):
            summary["parity"] = parity(("cpu", "cpu"), 32, 18, 3)
            if not all(r["passed"] for r in summary["parity"]):
                (args.out / "plan.json").write_text(json.dumps(summary, indent=1))
                return 1
        (args.out / "plan.json").write_text(json.dumps(summary, indent=1))
        print(f"gpu-suite dry run: {len(steps)} steps within {sum(s.limit_s for s in steps)} s of the {BUDGET_S} s "
              f"budget; wrote {args.out / 'plan.json'}")
        return 0
    if args.wheels is not None:
        install_wheels(args.wheels, args.site)
        os.environ["PYTHONPATH"] = os.pathsep.join([str(args.site), str(ROOT / "src"),
                                                    os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    summary["results"] = run_steps(steps, args.out)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    return 0 if all(r["rc"] == 0 for r in summary["results"]) else 1


if __name__ == "__main__":
    sys.exit(main())
