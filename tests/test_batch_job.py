"""``volren batch JOB.toml``: a job file's expansion into jobs, its checks (each a one-line error naming the file and
the key, before anything renders), the in-process run against ``volren render`` of the same flags, the same job on
Ray, and ``volren bench batch`` at a toy size."""

from __future__ import annotations

import json
import os
import shlex
import time
from pathlib import Path

import pytest

from volren.cli import main
from volren.distributed.job import load_batch, write_index
from volren.errors import VolrenError
from volren.plan.spec import RenderSpec

TINY = {"scene": "smoke", "width": 40, "height": 24, "samples": 24, "light-samples": 6, "light-grid": 8,
        "views": "mono"}
"""the flags of a render that takes a fraction of a second"""
SHARED = {k: v for k, v in TINY.items() if k != "views"}
"""`TINY` beside a sweep of views"""


def toml_value(value) -> str:
    return json.dumps(value)  # a JSON string, number, boolean or array of them is TOML too


def job_file(tmp_path: Path, body: str = "", base: dict | None = None, name: str = "job.toml") -> Path:
    lines = [f"out = {toml_value(str(tmp_path / 'batch'))}"]
    lines += [f"{k} = {toml_value(v)}" for k, v in (TINY if base is None else base).items()]
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n" + body)
    return path


def argv(job) -> tuple[str, ...]:
    """The job's command line (its spec's ``line``, without "volren"), checked to be the line its spec is of."""
    words = tuple(shlex.split(job.spec.line)[1:])
    assert RenderSpec.parse(words) == job.spec
    return words


def flag_values(argv: tuple[str, ...], flag: str) -> list[str]:
    return [argv[i + 1] for i, a in enumerate(argv) if a == flag]


def test_expansion_is_the_product_of_the_axes_in_file_order(tmp_path):
    path = job_file(tmp_path, """
[sweep]
method = ["dssrm", "cmsrm"]
[[sweep.light]]
name = "low"
light-irradiance = 1
light-dir = [1, -1, 0]
[[sweep.light]]
light-irradiance = [3, 2.5, 1]
""", base={**TINY, "light-dir": [0, -1, 0]})
    batch = load_batch(path)
    assert batch.folders == ("method-dssrm_light-low", "method-dssrm_light-irradiance-3-2.5-1",
                             "method-cmsrm_light-low", "method-cmsrm_light-irradiance-3-2.5-1")
    assert batch.out == tmp_path / "batch" and batch.frames == (1,) * 4 and batch.views == (1,) * 4
    for job, folder in zip(batch.jobs, batch.folders, strict=True):
        assert argv(job)[0] == "render" and job.out == tmp_path / "batch" / folder
        assert flag_values(argv(job), "--out") == [str(job.out)]
    low, rgb = argv(batch.jobs[2]), argv(batch.jobs[3])
    # an entry's value replaces the shared one (one flag, not two); what an entry does not set stays shared
    assert flag_values(low, "--light-irradiance") == ["1"] and flag_values(low, "--light-dir") == ["1,-1,0"]
    assert flag_values(rgb, "--light-irradiance") == ["3,2.5,1"] and flag_values(rgb, "--light-dir") == ["0,-1,0"]
    assert flag_values(low, "--method") == ["cmsrm"] and flag_values(low, "--width") == ["40"]
    assert batch.varies[1] == {"sweep.method[0]": "dssrm", "sweep.light[1].light-irradiance": [3, 2.5, 1]}
    index = json.loads(write_index(batch).read_text())
    assert list(index["jobs"]) == list(batch.folders) and index["command"] == "render"
    entry = index["jobs"]["method-cmsrm_light-low"]
    assert entry["settings"] == {"sweep.method[1]": "cmsrm", "sweep.light[0].light-irradiance": 1,
                                 "sweep.light[0].light-dir": [1, -1, 0]}
    assert entry["command"] == shlex.join(["volren", *low]) and entry["frames"] == 1 and entry["views"] == 1
    assert RenderSpec.from_json(entry["spec"]) == batch.jobs[2].spec  # the job runs again from its file


def test_a_file_without_a_sweep_is_one_job_into_out_and_switches_and_repeatables_become_flags(tmp_path):
    base = {**TINY, "command": "animate", "frames": 3, "orbit": 90, "no-skip": True, "jitter": False,
            "sphere": [[0, 0, 0, 0.3], "0.5,0,0,0.2"], "views": "stereo"}
    batch = load_batch(job_file(tmp_path, base=base))
    (job,) = batch.jobs
    assert batch.folders == (".",) and job.out == tmp_path / "batch" and argv(job)[0] == "animate"
    assert "--no-skip" in argv(job) and "--jitter" not in argv(job)
    assert flag_values(argv(job), "--sphere") == ["0,0,0,0.3", "0.5,0,0,0.2"]
    assert batch.frames == (3,) and batch.views == (2,)


def test_frames_all_plays_every_frame_of_a_volume_sequence(tmp_path):
    import numpy as np

    for i in range(3):
        np.save(tmp_path / f"sim_{i:04d}.npy", np.full((8, 8, 8), 0.5 + 0.1 * i, np.float32))
    base = {k: v for k, v in TINY.items() if k != "scene"} | {"frames": "all"}
    body = f"[sweep]\nvolume = {toml_value([str(tmp_path / 'sim_####.npy'), str(tmp_path / 'sim_0001.npy')])}\n"
    batch = load_batch(job_file(tmp_path, body, base=base))
    assert batch.folders == ("volume-sim", "volume-sim-0001") and batch.frames == (3, 1)
    assert flag_values(argv(batch.jobs[0]), "--frames") == ["3"]


@pytest.mark.parametrize(("body", "key", "message"), [
    ("widht = 40", "widht", "unknown key 'widht': did you mean 'width'?"),
    ("light_dir = [0, -1, 0]", "light_dir", "did you mean 'light-dir'?"),
    ("jitter = 1", "jitter", "'jitter' is an on/off flag: true or false, got 1"),
    ("density-scale = true", "density-scale", "'density-scale' takes a value, not true"),
    ("camera-pos = [[0, 1], 2]", "camera-pos", "'camera-pos' takes a string, a number or an array of them"),
    ("sphere = \"0,0,0,1\"", "sphere", "'sphere' is repeatable: give an array of its values"),
    ("height = \"tall\"", "height", "--height: invalid int value: 'tall'"),
    ("height = 0", "height", "--height must lie in [1, 16384] pixels, got 0"),
    ("tf = \"ct-bone\"", "tf", "method 'dssrm' does not take --tf"),
    ("orbit = 90", "orbit", "'orbit' is a flag of `volren animate` only: set command = \"animate\""),
    ("workers = 2", "workers", "'workers' is a `volren batch` option"),
    ("command = \"serve\"", "command", "must be one of render, animate, got 'serve'"),
    ("frames = \"all\"", "frames", "--frames \"all\" plays a --volume sequence; this job has no --volume"),
    ("frames = 2.5", "frames", "frames must be a number of frames or \"all\""),
    ("sweep = 3", "sweep", "must be a table of what varies"),
    ("[sweep]\nviews = []", "sweep.views", "is empty: a sweep axis needs at least one value"),
    ("[sweep]\nviews = \"mono\"", "sweep.views", "must be an array of values"),
    ("[sweep]\nmethod = [\"dssrm\", \"vpt\"]\n[[sweep.looks]]\ntf = \"smoke\"", "sweep.looks[0].tf",
     "method 'dssrm' does not take --tf"),
    ("[sweep]\nviews = [\"mono\", \"stereo\", \"four\"]", "sweep.views[2]", "--views"),
    ("[sweep]\nviews = [\"mono\", {views = \"stereo\"}]", "sweep.views", "mixes tables and values"),
    ("[[sweep.albedo]]\nalbedo = 0.5", "sweep.albedo", "'albedo' is a flag: give its values"),
    ("[[sweep.looks]]\nname = \"x\"", "sweep.looks[0]", "sets no flag"),
    ("[[sweep.looks]]\nname = 3\nalbedo = 0.5", "sweep.looks[0].name", "must be a non-empty string"),
    ("[[sweep.looks]]\nout = \"elsewhere\"", "sweep.looks[0].out", "the batch's folder is the top-level out"),
    ("[sweep]\nviews = [\"mono\"]\n[[sweep.rigs]]\nviews = \"4\"\nrig = \"arc\"", "sweep.rigs[0].views",
     "'views' is also set by sweep.views: one axis per flag"),
    ("[sweep]\nwidth = [40, 64]", "sweep.width", "'width' is set at the top of the file too (width = 40), but every "
     "job takes the sweep's value: remove one"),
    ("[[sweep.looks]]\nname = \"a\"\nsamples = 8\n[[sweep.looks]]\nname = \"b\"\nsamples = 16", "sweep.looks",
     "'samples' is set at the top of the file too (samples = 24)"),
    ("[sweep]", "sweep", "is empty: give it an axis (a flag = [values]), or leave [sweep] out for one job"),
    ("[[sweep.looks]]\nname = \"a\"\nalbedo = 0.5\n[[sweep.looks]]\nname = \"a\"\nalbedo = 0.9",
     "sweep.looks[1].albedo", "both write folder 'looks-a'"),
    ("[sweep]\nambient = [\"0.1,0.1,0.1\", [0.1, 0.1, 0.1]]", "sweep.ambient[1]", "both write folder "
     "'ambient-0.1-0.1-0.1'"),
])
def test_every_problem_is_one_line_naming_the_file_and_key(tmp_path, body, key, message):
    path = job_file(tmp_path, body + "\n", base={k: v for k, v in TINY.items() if k not in ("height", "views")})
    with pytest.raises(VolrenError) as refused:
        load_batch(path)
    text = str(refused.value)
    assert text.startswith(f"{path}: {key}: ") and message in text and "\n" not in text, text


def test_a_flag_at_the_top_is_the_default_of_the_entries_that_do_not_set_it(tmp_path):
    """A table axis whose entries set a top-level flag only some of the time: the top value is their default, not a
    flag that does nothing (the refusal is for a flag every entry replaces)."""
    body = "[[sweep.looks]]\nname = \"bright\"\nsamples = 16\n[[sweep.looks]]\nname = \"plain\"\nalbedo = 0.5\n"
    batch = load_batch(job_file(tmp_path, body))
    assert [flag_values(argv(job), "--samples") for job in batch.jobs] == [["16"], ["24"]]


def test_an_empty_job_file_and_a_swept_top_flag_are_one_line_before_anything_runs(tmp_path, capsys, monkeypatch):
    """`volren batch` of an empty file rendered the default smoke; a flag at the top and in a sweep took the sweep's
    value unsaid. Each is now one line naming the file (and the key), exit 2, nothing written."""
    monkeypatch.chdir(tmp_path)  # where the empty file's default out/empty would go
    empty = tmp_path / "empty.toml"
    empty.write_text("# nothing yet\n")
    assert main(["batch", str(empty)]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"volren: error: {empty} has no jobs: it sets no flag and no [sweep] (e.g. scene = \"smoke\", and a [sweep] of "
        "what varies: see examples/turntable-sweep.toml)"]
    both = job_file(tmp_path, "[sweep]\nviews = [\"mono\", \"stereo\"]\n")
    assert main(["batch", str(both)]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"volren: error: {both}: sweep.views: 'views' is set at the top of the file too (views = \"mono\"), but every "
        "job takes the sweep's value: remove one"]
    assert not (tmp_path / "batch").exists() and not (tmp_path / "out").exists()


def test_not_toml_and_a_missing_file_are_one_line(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("width = = 3\n")
    with pytest.raises(VolrenError, match=r"bad.toml: not a valid TOML file: "):
        load_batch(bad)
    with pytest.raises(VolrenError, match=r"cannot read job file '.*missing.toml'"):
        load_batch(tmp_path / "missing.toml")


def test_a_bad_job_anywhere_stops_the_batch_before_anything_renders(tmp_path, capfd):
    # the second job's --tf is refused by dssrm: the first (vpt) must not have rendered
    base = {k: TINY[k] for k in ("scene", "width", "height", "views")}
    path = job_file(tmp_path, "[sweep]\nmethod = [\"vpt\", \"dssrm\"]\ntf = [\"smoke\"]\n", base=base)
    assert main(["batch", str(path)]) == 2
    err = capfd.readouterr().err
    assert err.strip().splitlines() == [f"volren: error: {path}: sweep.tf[0]: method 'dssrm' does not take --tf"]
    assert not (tmp_path / "batch").exists()


def test_dry_run_prints_the_jobs_and_writes_nothing(tmp_path, capfd):
    path = job_file(tmp_path, "[sweep]\nviews = [\"mono\", \"stereo\"]\n", base={**SHARED, "frames": 2})
    assert main(["batch", str(path), "--dry-run"]) == 0
    lines = capfd.readouterr().out.strip().splitlines()
    # one unit per frame: dssrm keeps no history across frames
    assert lines[0].startswith("views-mono: 2 frame(s) x 1 view(s), 2 unit(s): volren render --scene smoke ")
    assert lines[1].startswith("views-stereo: 2 frame(s) x 2 view(s), 2 unit(s): volren render ")
    assert lines[-1] == f"2 job(s), 4 unit(s) into {tmp_path / 'batch'}"
    assert not (tmp_path / "batch").exists()


@pytest.mark.timeout(60)
@pytest.mark.parametrize("axes", [2, 4], ids=["1e6-jobs", "1e12-jobs"])
@pytest.mark.parametrize("dry_run", [True, False], ids=["dry-run", "run"])
def test_a_sweep_past_the_job_limit_is_refused_at_once_without_enumerating(tmp_path, capfd, axes, dry_run):
    """Issue 45 item 4: a sweep of 10^6 (or 10^12) jobs hung, --dry-run too, planning job after job; the product is
    counted first and refused in one line giving the count and the limit, before any job is made."""
    from volren.distributed import job

    flags = ["seed", "samples", "light-samples", "light-grid"][:axes]
    body = "[sweep]\n" + "".join(f"{flag} = {list(range(1, 1001))}\n" for flag in flags)
    path = job_file(tmp_path, body, base={k: v for k, v in TINY.items() if k not in flags})  # no flag set twice
    planned = []
    with pytest.MonkeyPatch.context() as patch:  # a job made at all would be planned
        patch.setattr(job, "_checked_job", lambda *a: planned.append(a) or pytest.fail("a job was made"))
        started = time.monotonic()
        assert main(["batch", str(path), *(["--dry-run"] if dry_run else [])]) == 2
        elapsed = time.monotonic() - started
    count = 1000 ** axes
    assert capfd.readouterr().err.splitlines() == [
        f"volren: error: {path}: sweep: makes {count:,} jobs ({' x '.join(['1000'] * axes)}), more than the "
        f"{job.MAX_JOBS:,} a job file may make (each is checked and planned before anything renders): split it into "
        "several job files"]
    assert elapsed < 1.0, elapsed
    assert not planned and not (tmp_path / "batch").exists()


def test_a_sweep_at_the_job_limit_is_made(tmp_path, monkeypatch):
    from volren.distributed import job

    monkeypatch.setattr(job, "MAX_JOBS", 4)
    path = job_file(tmp_path, "[sweep]\nseed = [1, 2]\nlight-irradiance = [1, 2]\n")
    assert len(load_batch(path).jobs) == 4
    path.write_text(path.read_text().replace("seed = [1, 2]", "seed = [1, 2, 3]"))
    with pytest.raises(VolrenError, match=r"sweep: makes 6 jobs \(3 x 2\), more than the 4 a job file may make"):
        load_batch(path)


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.suffix == ".png"}


def test_in_process_batch_writes_what_render_writes_for_each_job(tmp_path, capfd):
    path = job_file(tmp_path, "[sweep]\nlight-irradiance = [1, 4]\n", base={**TINY, "frames": 2})
    assert main(["batch", str(path)]) == 0
    out = tmp_path / "batch"
    assert json.loads((out / "jobs.json").read_text())["jobs"]["light-irradiance-4"]["settings"] == {
        "sweep.light-irradiance[1]": 4}
    for value in (1, 4):
        flags = [x for k, v in TINY.items() for x in (f"--{k}", str(v))]
        ref = tmp_path / f"ref{value}"
        assert main(["render", *flags, "--frames", "2", "--light-irradiance", str(value), "--out", str(ref)]) == 0
        files = _files(out / f"light-irradiance-{value}")
        assert list(files) == ["frame0000_view0.png", "frame0001_view0.png"] and files == _files(ref)
        stats = json.loads((out / f"light-irradiance-{value}" / "stats.json").read_text())
        assert f"--light-irradiance {value}" in stats["command"] and len(stats["frames"]) == 2
    assert _files(out / "light-irradiance-1") != _files(out / "light-irradiance-4")


def test_the_example_job_file_runs_its_four_jobs_tiny(tmp_path, capfd):
    import tomllib

    example = tomllib.loads((Path(__file__).parents[1] / "examples" / "turntable-sweep.toml").read_text())
    assert example["frames"] == 24 and example["width"] == 320  # as the README gives it
    sweep = example.pop("sweep")
    small = {**example, **TINY, "frames": 2, "out": str(tmp_path / "batch")}
    small.pop("views")  # the sweep's
    lines = [f"{k} = {toml_value(v)}" for k, v in small.items()]
    lines += ["[sweep]", f"views = {toml_value(sweep['views'])}"]
    for entry in sweep["light"]:
        lines += ["[[sweep.light]]", *(f"{k} = {toml_value(v)}" for k, v in entry.items())]
    path = tmp_path / "example.toml"
    path.write_text("\n".join(lines) + "\n")
    assert main(["batch", str(path)]) == 0
    folders = ["views-mono_light-noon", "views-mono_light-dusk", "views-stereo_light-noon", "views-stereo_light-dusk"]
    assert list(json.loads((tmp_path / "batch" / "jobs.json").read_text())["jobs"]) == folders
    for folder in folders:
        names = sorted(p.name for p in (tmp_path / "batch" / folder).iterdir())
        pngs = [f"frame000{i}_{v}.png" for i in range(2)
                for v in (["view0"] if "mono" in folder else ["stereo", "view0", "view1"])]
        assert names == sorted(["animation.mp4", "stats.json", *pngs]), names


@pytest.fixture(params=["in-thread", pytest.param("ray", marks=pytest.mark.xdist_group("ray"))])
def ray_backend(request, monkeypatch):
    """Each Ray test twice: on tests/test_batch.py's `InThreadRay` (the engine's calls into Ray answered in this
    process: no cluster start-up), and on the session's Ray cluster."""
    if request.param == "ray":
        return request.getfixturevalue("ray_cluster")
    from test_batch import InThreadRay
    from volren.distributed import engine, runtime

    fake = InThreadRay()
    fake.shutdown = lambda: None
    monkeypatch.setattr(runtime, "connect", lambda *args, **kwargs: fake)
    monkeypatch.setattr(engine, "_POOL", [])
    monkeypatch.setenv("VOLREN_CPU_THREADS", os.environ.get("VOLREN_CPU_THREADS", ""))  # the workers set it
    return fake


def test_a_job_file_on_ray_writes_the_files_of_the_in_process_run(tmp_path, ray_backend, capfd):
    """A two-job sweep (mono, stereo) run with ``volren batch --workers 2`` writes every job's files, byte for byte
    those of the in-process run (the second job included: ``run_jobs`` runs its ``planned`` states, so a batch
    whose job list and plans disagree is refused rather than half run), and the same index."""
    body = "[sweep]\nviews = [\"mono\", \"stereo\"]\n[[sweep.look]]\nname = \"dim\"\nlight-irradiance = 1\n"
    runs = {}
    for where, extra in (("here", []), ("ray", ["--workers", "2"])):
        folder = tmp_path / where
        folder.mkdir()
        path = job_file(folder, body, base={**SHARED, "frames": 2})
        assert main(["batch", str(path), *extra]) == 0
        runs[where] = folder / "batch"
    assert "2 job(s) into" in capfd.readouterr().out
    for name in ("views-mono_look-dim", "views-stereo_look-dim"):
        assert (runs["ray"] / name).is_dir(), name  # every job ran, not only the first
        here, ray = _files(runs["here"] / name), _files(runs["ray"] / name)
        assert len(here) == (2 if name.startswith("views-mono") else 6) and ray == here  # stereo: 2 eyes + pair
        assert (runs["ray"] / name / "batch.json").is_file()  # the engine's manifest: a re-run resumes
    index = {w: json.loads((runs[w] / "jobs.json").read_text()) for w in runs}
    assert [job["settings"] for job in index["ray"]["jobs"].values()] == [
        job["settings"] for job in index["here"]["jobs"].values()]


def test_run_jobs_refuses_plans_that_are_not_its_jobs(tmp_path):
    """`volren batch --workers` hands the engine its jobs and their plans (made checking the job file), and the
    engine runs the plans: a job list the plans do not match one for one is refused before Ray starts, rather than
    its jobs silently ignored (a batch that ran its first job only, or another's plans)."""
    from volren.distributed.engine import Job, JobState, run_jobs

    jobs = [Job(RenderSpec.parse(("render", "--out", str(tmp_path / name)))) for name in ("a", "b")]
    plans = [JobState(job, None, [], {}) for job in jobs]  # never reached: no plan is run
    for given, planned in ((jobs[:1], plans), (jobs, plans[:1]), (jobs[::-1], plans)):
        with pytest.raises(ValueError, match=r"planned state\(s\) are not those of the \d job\(s\)"):
            run_jobs(given, workers=1, address=None, flag="--workers", planned=planned)
    assert not any(tmp_path.iterdir())  # nothing opened or written


def test_bench_batch_counts_every_unit_and_frame(ray_backend):
    from volren.bench.batch import GOAL_OVERHEAD_MS, GOAL_RAY_RATIO, run_config
    from volren.distributed import engine

    cfg = {"frames": 3, "size": (40, 24), "resolution": 64, "workers": [1, 2],
           "overrides": ["--samples", "24", "--light-samples", "6", "--light-grid", "8"]}
    result = run_config(cfg, "cpu")
    assert engine._POOL == []  # the workers kept warm between its runs are stopped: they held the cluster's CPUs
    rows = result["rows"]
    assert [(r["case"], r["workers"], r["threads"]) for r in rows] == [
        ("in process", None, 1), ("in process", None, "all"), ("local Ray", 1, 1), ("local Ray", 2, 1)]
    for r in rows:
        assert r["frames"] == 3 and r["fps"] == pytest.approx(3 / r["wall_s"])
    walls = {r["threads"]: r["wall_s"] for r in rows[:2]}
    summary, _ = result["summary"]
    for r, s in zip(rows[2:], summary, strict=True):
        # one frame per unit (dssrm keeps no history), one PNG per mono frame, each written once, none retried
        assert r["units"] == 3 and r["files"] == 3 and r["retried"] == 0 and r["same_files"] is True
        assert r["overhead_ms"] == pytest.approx(r["unit_ms"] - r["frame_in_process_ms"])
        assert r["overhead_max_ms"] >= r["overhead_ms"] and r["ray_start_s"] >= 0 and r["setup_ms"] > 0
        assert s["workers"] == r["workers"]
        assert s["ratio"] == pytest.approx(r["wall_s"] / walls[1 if r["workers"] == 1 else "all"])
        met = s["ratio"] <= GOAL_RAY_RATIO and s["overhead_ms"] < GOAL_OVERHEAD_MS
        assert s["goals"] == ("pass" if met else "fail")


def test_a_temporal_method_is_planned_as_one_frame_range_per_worker(tmp_path):
    base = {"scene": "smoke", "method": "vpt", "denoise": "ours", "width": 40, "height": 24, "views": "mono",
            "frames": 4}
    path = job_file(tmp_path, base=base)
    # the denoiser's history: contiguous frames per worker (warm-up paid once each), not a unit per frame
    assert load_batch(path).units == (1,) and load_batch(path, workers=2).units == (2,)


def test_each_job_is_planned_once_in_process(tmp_path, monkeypatch, capfd):
    """The job file's checks plan every job (the CLI's checks and a probe render, `engine.plan_job`); the run uses
    those plans instead of making them again (it made two more per job, each with its probe render)."""
    from volren import plan

    made = []
    real = plan.plan_render

    def counted(args, method):
        made.append(args.out)
        return real(args, method)

    monkeypatch.setattr(plan, "plan_render", counted)
    path = job_file(tmp_path, "[sweep]\nlight-irradiance = [1, 4]\n")
    assert main(["batch", str(path)]) == 0
    assert sorted(map(str, made)) == sorted(str(tmp_path / "batch" / f"light-irradiance-{v}") for v in (1, 4))
    assert len(_files(tmp_path / "batch" / "light-irradiance-4")) == 1
