"""`make cuda-check`: every Warp kernel module of volren compiled for CUDA (PTX for sm_80 and sm_90 through NVRTC),
on a machine with no GPU and no driver, so a kernel that builds for the CPU and not for CUDA fails CI, not a user.

The modules are found, not listed: every module under ``volren`` is imported and each Warp module named
``volren.*`` that holds a kernel is compiled (a hand-kept list had missed two of 19). volren's kernels are all
defined once at module level, with no per-config or generic variants (``tests/test_cuda_check.py`` renders each
method, preset, sci-vis mode, channels and fire and asserts no kernel appears at run time), so compiling each module
covers every kernel a config or preset can launch.

Artifacts go to Warp's own kernel cache, named by the module's content hash (its kernels, the device functions they
call and the compile options), so an unchanged module is skipped on the next run and a changed one is rebuilt. The
jobs (module x architecture) run on one process per core, largest source first.

    python scripts/cuda_check.py                      # every module, sm_80 and sm_90
    python scripts/cuda_check.py --arch 90 --module volren.render.lightmap
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import multiprocessing
import os
import pkgutil
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

ARCHS = (80, 90)
"""A100 (sm_80) and H100/H200 (sm_90): the GPUs volren's users and the lent machines have."""


@dataclass(frozen=True)
class Job:
    module: str
    arch: int


@dataclass(frozen=True)
class Result:
    job: Job
    seconds: float
    compiled: bool
    """False when Warp's cache already held this module's PTX for this architecture (same content hash)."""
    error: str | None
    """Warp's exception and NVRTC's log when the compile failed."""


def _warp():
    from volren.device import init_warp

    init_warp()
    import warp as wp

    return wp


def _user_modules() -> dict:
    from warp._src.context import user_modules  # Warp keeps no public registry of its modules

    return user_modules


def kernel_modules(package: str = "volren") -> list[str]:
    """Import every module of ``package`` and name the Warp modules under it that hold at least one kernel. An import
    that fails is an error: a module the check cannot import is a module it cannot compile."""
    _warp()
    root = importlib.import_module(package)
    for info in pkgutil.walk_packages(root.__path__, f"{package}."):
        importlib.import_module(info.name)
    return sorted(name for name, m in _user_modules().items()
                  if (name == package or name.startswith(f"{package}.")) and m.kernels)


def _captured(fd_path: Path):
    """Redirect the process's stdout and stderr (file descriptors, where NVRTC writes its log) to ``fd_path``."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    fd = os.open(fd_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    return saved


def _restored(saved) -> None:
    sys.stdout.flush()
    sys.stderr.flush()
    os.dup2(saved[0], 1)
    os.dup2(saved[1], 2)
    os.close(saved[0])
    os.close(saved[1])


def compile_job(job: Job, path: list[str] | None = None) -> Result:
    """Compile one module for one architecture to PTX in Warp's kernel cache (run in a worker process)."""
    if path:
        sys.path[:0] = [p for p in path if p not in sys.path]
    wp = _warp()
    start = time.perf_counter()
    started = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "log"
        saved = _captured(log)
        try:
            importlib.import_module(job.module)
            artifacts = wp.compile_aot_module(job.module, arch=job.arch, use_ptx=True)
            error = None
        except Exception as exc:  # Warp raises plain Exceptions for build failures; report every kind by module
            artifacts, error = [], f"{type(exc).__name__}: {exc}"
        finally:
            _restored(saved)
        if error is not None:
            noise = ("creating precompiled header", "Warp CUDA warning", "Warp NVRTC compilation error")
            lines = [ln for ln in log.read_text(errors="replace").splitlines() if not any(n in ln for n in noise)]
            error = "\n".join([error, *[ln for ln in lines if ln.strip()]])
    seconds = time.perf_counter() - start
    if error is None and not any(p.suffix == ".ptx" and ".entry" in p.read_text() for p in artifacts):
        error = f"Warp returned no PTX with an entry point for {job.module} (artifacts: {artifacts})"
    compiled = error is None and any(p.stat().st_mtime >= started - 1.0 for p in artifacts)
    return Result(job, seconds, compiled, error)


def _source_size(module: str) -> int:
    spec = importlib.util.find_spec(module)
    return Path(spec.origin).stat().st_size if spec and spec.origin else 0


def run(modules: list[str], archs: tuple[int, ...], workers: int, path: list[str] | None = None) -> list[Result]:
    """Compile every (module, arch) job, ``workers`` processes at a time, largest source first; print a line per job."""
    jobs = sorted((Job(m, a) for m in modules for a in archs), key=lambda j: (-_source_size(j.module), j.arch))
    results = []
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = [pool.submit(compile_job, job, path) for job in jobs]
        for done, future in enumerate(as_completed(futures), 1):
            r = future.result()
            state = "FAILED" if r.error else "compiled" if r.compiled else "cached"
            print(f"[{done}/{len(jobs)}] {r.job.module} sm_{r.job.arch}: {state} in {r.seconds:.1f} s", flush=True)
            results.append(r)
    return results


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--arch", type=int, action="append", help="an SM architecture (repeatable; default 80 and 90)")
    ap.add_argument("--module", action="append", help="a Warp module by its Python name (repeatable; default all)")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="processes (default: one per core)")
    args = ap.parse_args(argv)
    if args.workers < 1:
        ap.error(f"--workers must be at least 1, got {args.workers}")
    start = time.perf_counter()
    _warp()
    from warp._src.context import runtime

    missing = sorted(set(args.arch or ARCHS) - set(runtime.nvrtc_supported_archs or ()))
    if missing:
        print(f"cuda-check: this Warp build's NVRTC cannot compile for sm_{missing[0]} (supported: "
              f"{sorted(runtime.nvrtc_supported_archs or ()) or 'none, a CPU-only warp-lang wheel'})", file=sys.stderr)
        return 2
    modules = args.module or kernel_modules()
    archs = tuple(args.arch or ARCHS)
    results = run(modules, archs, args.workers, [p for p in sys.path if p])
    failed = [r for r in results if r.error]
    for r in failed:
        print(f"\ncuda-check: {r.job.module} does not compile for sm_{r.job.arch}:\n{r.error}", file=sys.stderr)
    passed, built = len(results) - len(failed), sum(r.compiled for r in results)
    targets = ", ".join(f"sm_{a}" for a in archs)
    print(f"cuda-check: {passed} of {len(results)} module builds for {targets} passed ({built} compiled, "
          f"{passed - built} cached) in {time.perf_counter() - start:.0f} s on {args.workers} process(es)", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
