"""`make cuda-check` (scripts/cuda_check.py): every Warp kernel module of volren compiles for CUDA sm_80 and sm_90
through NVRTC on a machine with no GPU, and no config, preset or mode makes a kernel the check would not have seen.

`make test` runs the check first, so the per-module compiles here find Warp's cache warm (0.1 s each) and still
catch a module edited since (its content hash changes): that is what kills the catalogue's CPU-only-construct mutant.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from volren.cli import main

ROOT = Path(__file__).resolve().parent.parent
SPEC = importlib.util.spec_from_file_location("cuda_check", ROOT / "scripts" / "cuda_check.py")
cuda_check = importlib.util.module_from_spec(SPEC)
sys.modules["cuda_check"] = cuda_check  # its dataclasses look their module up there
SPEC.loader.exec_module(cuda_check)


def modules_defining_kernels() -> list[str]:
    """The Python modules whose source defines a Warp kernel, read off the files (independently of Warp's registry)."""
    src = ROOT / "src"
    return sorted(".".join(p.relative_to(src).with_suffix("").parts) for p in (src / "volren").rglob("*.py")
                  if re.search(r"^@wp\.kernel\b|wp\.Kernel\(", p.read_text(), re.MULTILINE))


def test_the_check_finds_every_module_that_defines_a_kernel():
    found = cuda_check.kernel_modules()
    assert found == modules_defining_kernels()
    # the two the hand-kept list of the earlier PTX test had missed
    assert {"volren.render.compositing.mesh_layers", "volren.render.compositing.surface_light"} <= set(found)


@pytest.mark.parametrize("arch", cuda_check.ARCHS)
@pytest.mark.parametrize("module", modules_defining_kernels())
def test_every_kernel_module_compiles_for_cuda(module, arch):
    result = cuda_check.compile_job(cuda_check.Job(module, arch))
    assert result.error is None, result.error


def test_a_cpu_only_construct_fails_naming_the_module_and_nvrtcs_error(tmp_path):
    """A kernel that runs on the CPU (an x86 intrinsic in a native snippet) fails the check with the module's name and
    NVRTC's own line, and the check exits 1 (run as `make cuda-check` runs it, in a fresh process)."""
    (tmp_path / "cycle_stamp.py").write_text(textwrap.dedent('''
        import warp as wp

        @wp.func_native("return (int)(__builtin_ia32_rdtsc() & 0x7f);")
        def cycle_count() -> int: ...

        @wp.kernel
        def stamp(out: wp.array(dtype=int)):
            out[wp.tid()] = cycle_count() + 1
    '''))
    sys.path.insert(0, str(tmp_path))
    try:
        import cycle_stamp
        import warp as wp

        out = wp.zeros(3, dtype=int, device="cpu")
        wp.launch(cycle_stamp.stamp, dim=3, inputs=[out], device="cpu")
        assert out.numpy().min() >= 1  # it does run on the CPU
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop("cycle_stamp", None)
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "cuda_check.py"), "--module", "cycle_stamp",
                           "--module", "volren.simulate", "--arch", "90"], capture_output=True, text=True,
                          timeout=240, env={**os.environ, "PYTHONPATH": str(tmp_path)})
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "cuda-check: cycle_stamp does not compile for sm_90" in proc.stderr
    assert re.search(r'identifier "__builtin_ia32_rdtsc" is undefined', proc.stderr)
    assert "volren.simulate sm_90: cached" in proc.stdout or "volren.simulate sm_90: compiled" in proc.stdout
    assert "1 of 2 module builds for sm_90 passed" in proc.stdout


def _kernels() -> dict[str, tuple]:
    """Every volren Warp module's kernels, by key, with the kernel object's identity and its overload count."""
    return {name: tuple(sorted((key, id(k), len(k.overloads)) for key, k in m.kernels.items()))
            for name, m in cuda_check._user_modules().items() if name.startswith("volren")}


def test_no_config_preset_or_mode_makes_a_kernel_the_check_has_not_compiled(tmp_path, capfd):
    """Each method at each quality preset, the sci-vis modes, channels, fire, OIT, GI, the VPT denoisers and surfaces
    render (tiny, on the CPU) without adding a kernel or a generic overload to Warp's registry: the modules the check
    compiles are every kernel any of them launches."""
    cuda_check.kernel_modules()
    before = _kernels()
    channels = tmp_path / "channels.npy"
    rng = np.random.default_rng(1)
    np.save(channels, rng.random((2, 12, 12, 12)).astype(np.float32))
    small = ["--width", "20", "--height", "12", "--device", "cpu"]
    cases = [["--method", m, "--quality", q] for m in ("dssrm", "cmsrm", "cacrm", "reference", "vpt")
             for q in ("interactive", "default", "high")]
    cases += [["--method", "fog", "--scene", "hall", "--quality", q] for q in ("interactive", "default", "high")]
    cases += [["--method", m, "--mode", mode] for m in ("dssrm", "cmsrm", "cacrm")
              for mode in ("mip", "mida", "iso")]
    cases += [["--method", m, "--volume", channels] for m in ("dssrm", "cmsrm", "cacrm", "reference")]
    cases += [["--method", m, "--scene", "fire"] for m in ("dssrm", "cmsrm", "vpt", "reference")]
    cases += [["--method", "cacrm", "--scene", "instances", "--count", "4", "--oit", o]
              for o in ("tiled", "pixel-rt", "pixel-sort")]
    cases += [["--method", "cacrm", "--gi", g] for g in ("major", "prt", "restir", "sresir", "brute")]
    cases += [["--method", "vpt", "--denoise", d, "--frames", "2"] for d in ("ours", "svgf", "wrls")]
    cases += [["--method", m, "--scene", "smoke-floor", "--sphere", "0,0,0,0.3"] for m in ("dssrm", "cmsrm", "vpt")]
    for i, case in enumerate(cases):
        argv = ["render", *small, *map(str, case), "--out", tmp_path / f"c{i}"]
        code = main([str(a) for a in argv])
        assert code == 0, (case, capfd.readouterr().err)
    assert _kernels() == before
