"""The Ray batch engine (issue 23 items 1, 2, 4): ``--workers`` / ``--ray-address`` on render and animate, output
identical to the in-process run, resume from the manifest, a killed worker, a failing unit, Ctrl-C, a temporal
method's warm-up; and the default path, which never imports Ray."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from volren import cli
from volren.distributed import engine
from volren.distributed.engine import DENOISE_WARMUP, MANIFEST, Job, run_jobs
from volren.distributed.worker import UnitWorker
from volren.errors import VolrenError
from volren.plan.spec import RenderSpec

SMALL = ("--width", "64", "--height", "48", "--resolution", "64", "--device", "cpu")
ANIMATE = ("animate", *SMALL, "--frames", "4", "--jitter", "--save-linear")
"""a stereo turntable of the jittered smoke: a stochastic method's per-frame seeds, both eyes, the MP4"""
LIGHT_MAP_COUNTERS = ("light_samples", "light_skipped")
"""the light map's work: a pass cached per scene, so each worker's first frame does it again"""


def run_files(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.name not in ("stats.json", MANIFEST)}


def assert_same_run(ref: Path, out: Path) -> None:
    """The same files, byte for byte, and the same per-frame work counters (the light map's counted where a worker
    first computed it: at most once per frame and as the in-process run's first frame did)."""
    want, got = run_files(ref), run_files(out)
    assert sorted(got) == sorted(want)
    assert [n for n in want if got[n] != want[n]] == []
    frames = [json.loads((d / "stats.json").read_text())["frames"] for d in (ref, out)]
    assert [f["index"] for f in frames[1]] == [f["index"] for f in frames[0]]
    first = frames[0][0]["counters"]
    for a, b in zip(*frames, strict=True):
        view = {k: v for k, v in a["counters"].items() if k not in LIGHT_MAP_COUNTERS}
        assert {k: b["counters"][k] for k in view} == view
        assert all(b["counters"][k] in (a["counters"][k], first[k]) for k in LIGHT_MAP_COUNTERS)


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """The in-process animate run every Ray run here must reproduce."""
    out = tmp_path_factory.mktemp("ref") / "out"
    assert cli.main([*ANIMATE, "--out", str(out)]) == 0
    return out


def job(out: Path, *extra: str) -> Job:
    return Job(RenderSpec.parse((*ANIMATE, *extra, "--out", str(out))))


class InThreadRay:
    """What the engine uses of Ray, with each actor an object in this process whose calls run one at a time (one
    lock: renders never overlap), so the engine's scheduling, manifest, retries and failures are tested without a
    cluster's start-up; `kill(pid)` makes an actor die as a killed process does (its call fails, it takes no more).
    The same tests on the session's real cluster follow."""

    class exceptions:  # as ray.exceptions
        class RayActorError(Exception):
            pass

        class RayTaskError(Exception):
            def __init__(self, cause: BaseException) -> None:
                super().__init__(str(cause))
                self.cause = cause

    def __init__(self, cpus: int = 2) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self.cpus, self.lock, self.pool = cpus, __import__("threading").Lock(), ThreadPoolExecutor(4)
        self.dead: set[int] = set()
        self.started = 0

    def cluster_resources(self) -> dict[str, float]:
        return {"CPU": float(self.cpus)}

    def get_runtime_context(self):
        return type("Context", (), {"get_job_id": staticmethod(lambda: "in-thread"),
                                    "get_node_id": staticmethod(lambda: f"node-{id(self)}")})()

    def remote(self, **_):
        fake = self

        class Handle:
            def __init__(self, *args) -> None:
                fake.started += 1
                self._pid, self._worker, self._args = 10_000 + fake.started, None, args

            def __getattr__(self, name: str):
                def call(*args):
                    def run():
                        with fake.lock:
                            if self._pid in fake.dead:
                                raise fake.exceptions.RayActorError(self._pid)
                            if name == "pid":
                                return self._pid
                            self._worker = self._worker or UnitWorker(*self._args)
                            try:
                                result = getattr(self._worker, name)(*args)
                            except Exception as exc:
                                raise fake.exceptions.RayTaskError(exc) from exc
                            if self._pid in fake.dead:  # killed while it ran: its result is lost
                                raise fake.exceptions.RayActorError(self._pid)
                            return result
                    return fake.pool.submit(run)
                return type("Method", (), {"remote": staticmethod(call)})()

        factory = type("Factory", (), {"remote": staticmethod(lambda *a: Handle(*a))})()
        return lambda cls: type("Remote", (), {"options": staticmethod(lambda **_: factory)})()

    def get(self, ref):
        return [self.get(r) for r in ref] if isinstance(ref, list) else ref.result()

    def wait(self, refs, num_returns=1, timeout=None):
        from concurrent.futures import FIRST_COMPLETED
        from concurrent.futures import wait as wait_futures

        done, rest = wait_futures(refs, timeout=timeout, return_when=FIRST_COMPLETED)
        return list(done)[:num_returns], list(rest)

    def kill(self, actor, no_restart=True):
        self.dead.add(actor._pid)


@pytest.fixture
def in_thread_ray(monkeypatch):
    from volren.distributed import runtime

    fake = InThreadRay()
    monkeypatch.setattr(runtime, "connect", lambda *args, **kwargs: fake)
    monkeypatch.setattr(engine, "_POOL", [])
    monkeypatch.setenv("VOLREN_CPU_THREADS", os.environ.get("VOLREN_CPU_THREADS", ""))  # the workers set it
    return fake


@pytest.fixture(params=["in-thread", pytest.param("ray", marks=pytest.mark.xdist_group("ray"))])
def backend(request):
    """Each engine test twice: on `InThreadRay`, and on the session's Ray cluster. Yields ``kill(pid)``, what a
    test does to a worker's process."""
    if request.param == "ray":
        request.getfixturevalue("ray_cluster")
        return lambda pid: os.kill(pid, signal.SIGKILL)
    return request.getfixturevalue("in_thread_ray").dead.add


# --- the default path and the flags' refusals: no Ray started ---

def test_a_plain_render_never_imports_ray(tmp_path):
    code = (f"import sys, volren.cli as cli\nassert cli.main(['render', *{SMALL!r}, '--views', 'mono', '--out', "
            f"{str(tmp_path / 'o')!r}]) == 0\nprint('ray' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "False"


@pytest.mark.parametrize(("extra", "message"), [
    (("--workers", "0"), "--workers must be >= 1, got 0"),
    (("--gpus-per-worker", "0.5"), "--gpus-per-worker shares a GPU among the workers of --workers or --ray-address"),
    (("--workers", "1", "--gpus-per-worker", "0.5"), "--gpus-per-worker shares a GPU among workers: the workers "
                                                     "render on the CPU here"),
])
def test_batch_flags_that_would_do_nothing_are_refused(tmp_path, capsys, extra, message):
    assert cli.main(["render", *SMALL, *extra, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_workers_without_ray_installed_is_one_line_naming_the_flag(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    assert cli.main(["render", *SMALL, "--workers", "2", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "volren: error: --workers: Ray is not installed: pip install 'volren[ray]'"


def test_a_plain_render_into_a_batch_folder_replaces_the_batch(tmp_path):
    """The manifest is one of a run's files: a plain render there removes it with the batch's frames, so a later
    --workers run of the batch's command starts clean instead of trusting files another render replaced."""
    out = tmp_path / "out"
    out.mkdir()
    for name in (MANIFEST, "frame0000_view0.png", "stats.json", "notes.txt"):
        (out / name).write_text("{}")
    assert cli.main(["render", "--width", "16", "--height", "12", "--resolution", "64", "--device", "cpu", "--views",
                     "mono", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt", "stats.json", "view0.png"]


# --- the engine, in-thread and on the session's Ray cluster ---

def test_workers_write_what_animate_writes_in_process(backend, reference, tmp_path):
    """Two workers, a unit per frame: every PNG, .npy and the MP4 byte for byte as in process, the same counters;
    stats.json adds each unit's worker and times."""
    out = tmp_path / "out"
    report = run_jobs([job(out)], workers=2, address=None, flag="--workers")
    assert_same_run(reference, out)
    assert (report.units_run, report.units_skipped, report.units_retried, report.workers) == (4, 0, 0, 2)
    assert report.files_written == len(run_files(reference)) - 1  # all but animation.mp4, made at the end
    units = json.loads((out / "stats.json").read_text())["batch"]["units"]
    assert [u["frames"] for u in units] == [[i, i + 1] for i in range(4)]
    assert all(u["worker"] and u["attempts"] == 1 for u in units)


def test_ctrl_c_leaves_complete_units_and_a_rerun_resumes(backend, reference, tmp_path, capsys):
    """Ctrl-C while the third unit's files are being written (after 2 of its 5): only the first two units' files
    stay, listed in the manifest; the same command again skips the second (checked against its files: one changed
    makes the first incomplete) and renders the rest; another command into that folder starts clean."""
    out = tmp_path / "out"
    calls = []
    write = engine.write_atomically

    def interrupted(path, data):
        calls.append(path.name)
        if len(calls) == 2 * 6 + 3:  # each unit: 5 files + the manifest; then unit 3's third file
            raise KeyboardInterrupt
        write(path, data)

    with pytest.MonkeyPatch.context() as patch, pytest.raises(KeyboardInterrupt):
        patch.setattr(engine, "write_atomically", interrupted)
        run_jobs([job(out)], workers=1, address=None, flag="--workers")
    manifest = json.loads((out / MANIFEST).read_text())
    done = manifest["units"]
    assert list(done) == ["frames 0-0", "frames 1-1"]
    assert sorted(p.name for p in out.iterdir()) == sorted({n for u in done.values() for n in u["files"]} | {MANIFEST})
    # a unit's file changed since: that unit is not complete any more
    (out / "frame0000_view1.npy").write_bytes(b"changed")
    report = run_jobs([job(out)], workers=2, address=None, flag="--workers")
    assert (report.units_skipped, report.units_run) == (1, 3)
    assert_same_run(reference, out)
    # another command into that folder starts clean: one line says so, no file of the first run stays
    capsys.readouterr()
    report = run_jobs([Job(RenderSpec.parse(("render", *SMALL, "--views", "mono", "--out", str(out))))], workers=1,
                      address=None, flag="--workers")
    assert capsys.readouterr().err.count("starting clean") == 1
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "stats.json", "view0.png"]


def test_a_killed_worker_costs_a_retry_of_its_unit_only(backend, reference, tmp_path):
    """The worker given frame 1 is killed (SIGKILL) as the unit goes to it: a fresh worker renders that unit again,
    nothing else is rendered twice, nothing written twice, and the output is the in-process run's."""
    out = tmp_path / "out"
    killed = []

    def kill(unit, pid):
        if unit.start == 1 and not killed:
            killed.append(pid)
            backend(pid)

    report = run_jobs([job(out)], workers=2, address=None, flag="--workers", on_dispatch=kill)
    assert killed and (report.units_run, report.units_retried) == (4, 1)
    assert report.files_written == len(run_files(reference)) - 1
    assert [u.attempts for u in sorted(report.units, key=lambda u: u.start)] == [1, 2, 1, 1]
    assert_same_run(reference, out)


def test_a_temporal_method_warms_up_to_the_single_machine_sequence(backend, tmp_path):
    """vpt with the spatiotemporal denoiser keeps history: the worker given frames 5-9 renders frames 1-4 first
    (`DENOISE_WARMUP`), and its frames match one in-process run's to over 55 dB (measured 65.4 dB; with no warm-up
    scripts/batch_warmup.py measures 40 dB), well under one 8-bit step. The first worker's continue from frame 0:
    identical."""
    argv = ("animate", "--width", "48", "--height", "32", "--resolution", "64", "--device", "cpu", "--views", "mono",
            "--method", "vpt", "--denoise", "ours", "--spp", "2", "--frames", "10", "--orbit", "30", "--save-linear")
    assert cli.main([*argv, "--out", str(tmp_path / "ref")]) == 0
    out = tmp_path / "out"
    report = run_jobs([Job(RenderSpec.parse((*argv, "--out", str(out))))], workers=2, address=None, flag="--workers",
                      unit_frames=5)
    assert sorted((u.start, u.warmup) for u in report.units) == [(0, 0), (5, DENOISE_WARMUP)]
    from volren.metrics import psnr

    def image(folder: str, i: int) -> np.ndarray:
        return np.load(tmp_path / folder / f"frame{i:04d}_view0.npy")[..., :3]

    assert all(np.array_equal(image("ref", i), image("out", i)) for i in range(5))
    worst = min(psnr(image("ref", i), image("out", i)) for i in range(5, 10))
    assert 55 < worst < float("inf")


def test_a_unit_failing_with_a_volren_error_fails_the_job_with_that_line(backend, tmp_path, monkeypatch):
    """Frame 2 of a volume sequence is not a volume: the driver's checks read frames 0 and 1 only, so the unit of
    frame 2 fails in its worker (which found frames 0 and 1 by the driver's relative path); the job fails with the
    loader's line, the unit is not retried, and the complete units stay for a resume."""
    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng(0)
    for i in range(3):
        np.save(tmp_path / f"sim_{i:04d}.npy", rng.random((8, 8, 8), dtype=np.float32))
    (tmp_path / "sim_0002.npy").write_bytes(b"not a volume")
    out = Path("out")
    sent = []
    argv = ("render", "--width", "32", "--height", "24", "--device", "cpu", "--views", "mono", "--volume",
            "sim_####.npy", "--frames", "3", "--out", str(out))
    with pytest.raises(VolrenError) as err:
        run_jobs([Job(RenderSpec.parse(argv))], workers=1, address=None, flag="--workers",
                 on_dispatch=lambda unit, pid: sent.append(unit.start))
    assert "sim_0002.npy" in str(err.value) and "\n" not in str(err.value)
    assert sent.count(2) == 1
    assert set(json.loads((out / MANIFEST).read_text())["units"]) == {"frames 0-0", "frames 1-1"}


def test_more_workers_than_the_cluster_holds_is_refused(backend, tmp_path):
    """Three one-CPU workers on the session's 2-CPU cluster: the third would wait for ever; refused in one line."""
    out = tmp_path / "out"
    refusal = r"^--workers: 3 worker\(s\) need 3 CPU\(s\), Ray has 2: give fewer --workers$"
    with pytest.raises(VolrenError, match=refusal):
        run_jobs([Job(RenderSpec.parse(("render", *SMALL, "--views", "mono", "--frames", "3", "--out", str(out))))],
                 workers=3, address=None, flag="--workers")


def test_a_new_cluster_in_the_same_process_starts_fresh_workers(monkeypatch, tmp_path):
    """The warm workers kept between runs in one process belong to their cluster: after a shutdown and a new
    connection (whose first job id repeats, 01000000), the next run starts its own instead of calling dead ones."""
    from volren.distributed import runtime

    monkeypatch.setattr(engine, "_POOL", [])
    for i, fake in enumerate((InThreadRay(), InThreadRay())):
        monkeypatch.setattr(runtime, "connect", lambda *args, fake=fake, **kwargs: fake)
        argv = ("render", *SMALL, "--views", "mono", "--out", str(tmp_path / f"o{i}"))
        report = run_jobs([Job(RenderSpec.parse(argv))], workers=1, address=None, flag="--workers",
                          keep_workers=True)
        assert (report.units_run, fake.started) == (1, 1)


def test_idle_workers_are_stopped_unless_kept(in_thread_ray, tmp_path):
    """An idle actor holds its CPU (or GPU) of the cluster: left running, it kept a sharded server's actors waiting
    for ever in one process. Stopped at the end by default; kept (warm) only when asked."""
    argv = ("render", *SMALL, "--views", "mono", "--frames", "2")  # a unit for each of the 2 workers
    run_jobs([Job(RenderSpec.parse((*argv, "--out", str(tmp_path / "a"))))], workers=2, address=None, flag="--workers")
    assert in_thread_ray.dead == {10_001, 10_002} and engine._POOL == []
    run_jobs([Job(RenderSpec.parse((*argv, "--out", str(tmp_path / "b"))))], workers=2, address=None,
             flag="--workers", keep_workers=True)
    assert len(engine._POOL) == 2 and in_thread_ray.dead == {10_001, 10_002}


def test_the_manifest_is_rewritten_at_most_once_a_second_and_at_the_end(in_thread_ray, monkeypatch, tmp_path):
    """The manifest is rewritten whole: after every unit that is O(units^2) (0.24 ms per recorded unit); with the
    interval longer than the run, it is written at the first unit and at the end, and still lists all four."""
    writes = []
    real = engine.write_atomically
    monkeypatch.setattr(engine, "MANIFEST_EVERY_S", 1e9)
    monkeypatch.setattr(engine, "write_atomically",
                        lambda path, data: (writes.append(path.name), real(path, data))[1])
    out = tmp_path / "out"
    run_jobs([job(out)], workers=2, address=None, flag="--workers")
    assert writes.count(engine.MANIFEST) == 2
    assert len(json.loads((out / engine.MANIFEST).read_text())["units"]) == 4


def test_a_unit_is_committed_once(tmp_path):
    """A second result for a unit already complete (a retry whose first attempt finished after all) writes nothing:
    the files and the manifest keep the first."""
    out = tmp_path / "out"
    state = engine.plan_job(0, job(out), 2, None)
    state.open_output()
    unit = state.units[0]
    result = {"files": {"frame0000_view0.png": b"first"}, "scene": "smoke", "stats": []}
    report = engine.UnitReport(0, unit.key, unit.start, unit.stop, unit.warmup, "w", 1, 0.1, 0.0, 0.0, 0.1)
    assert state.commit(unit, result, report) == 1
    assert state.commit(unit, {**result, "files": {"frame0000_view0.png": b"second"}}, report) == 0
    assert (out / "frame0000_view0.png").read_bytes() == b"first"


@pytest.mark.timeout(60)
def test_a_manifest_of_another_version_starts_clean_and_the_manifest_holds_the_spec(tmp_path, capsys):
    """batch.json records the job's spec (it can run again from the file); a batch.json of version 1 (a command line,
    no spec) is not resumed, however alike its settings: its files are removed and the run starts clean."""
    out = tmp_path / "out"
    state = engine.plan_job(0, job(out), 2, None)
    state.open_output()
    unit = state.units[0]
    report = engine.UnitReport(0, unit.key, unit.start, unit.stop, unit.warmup, "w", 1, 0.1, 0.0, 0.0, 0.1)
    state.commit(unit, {"files": {"frame0000_view0.png": b"old"}, "scene": "smoke", "stats": []}, report)
    state.save_manifest()
    saved = json.loads((out / MANIFEST).read_text())
    assert saved["version"] == engine.MANIFEST_VERSION == 2
    assert RenderSpec.from_json(saved["spec"]) == state.job.spec
    assert engine.plan_job(0, job(out), 2, None).open_output() is None  # the same version: resumed, nothing said
    assert "starting clean" not in capsys.readouterr().err
    (out / MANIFEST).write_text(json.dumps({**saved, "version": 1}))
    again = engine.plan_job(0, job(out), 2, None)
    again.open_output()
    assert again.manifest["units"] == {} and not (out / "frame0000_view0.png").exists()
    assert f"its {MANIFEST} is of another command: starting clean" in capsys.readouterr().err


@pytest.mark.timeout(30)
def test_a_demo_spec_is_no_batch_job():
    """The engine runs render and animate specs; a demo spec (no --out to resume) is refused in one line."""
    with pytest.raises(VolrenError, match=r"^a batch job is a render or animate run, got 'demo'$"):
        engine.plan_job(0, Job(RenderSpec.parse(["demo", "--device", "cpu"])), 2, None)
