"""``volren batch JOB.toml``: a sweep of renders described by one TOML file, expanded into `Job`s (one ``volren render``
or ``animate`` command line each, into its own sub-folder) and run in-process or on Ray (`engine.run_jobs`).

A job file gives the options every job shares, as ``volren render`` / ``animate`` take them (any flag by its long
name: ``scene = "smoke"``, ``width = 320``, ``no-skip = true``), and a ``[sweep]`` table of what varies::

    command = "animate"           # render (default) or animate
    out = "out/turntables"        # the batch's folder (default: out/<the file's stem>), relative to the working folder
    scene = "smoke"
    width = 320
    frames = 64                   # a number, or "all": every frame of a --volume sequence
    [sweep]
    views = ["mono", "stereo"]    # a flag and its values: one axis
    [[sweep.looks]]               # an array of tables (named as you like): one axis whose flags change together
    name = "warm"                 # optional: the folder part (default: its flags and values)
    light-irradiance = [3, 2, 1]

Values are strings, numbers, ``true``/``false`` (on/off flags only) or arrays: an array of numbers or strings is one
comma-separated value (``camera-pos = [0, 0.4, 3.2]``); a repeatable flag (``sphere``, ``mesh``, ``rect-light``,
``mesh-alpha``) takes an array of its values.

The jobs are the cartesian product of the axes, in the file's order (the last axis varies fastest). A product, not a
zip: axes are independent (methods x transfer functions x views is what a sweep is for), and flags that must change
together are one table of a table axis, which says so in the file instead of relying on two lists' positions. Each
job writes ``<out>/<folder>``, named from what varies: ``<flag>-<value>`` for a flag axis, ``<axis>-<name>`` for a
table axis (a table without ``name``: ``<flag>-<value>`` of its flags), joined by ``_`` (``views-stereo_looks-warm``).
A top-level flag is the default of a table axis's entries that do not set it; one that every entry of an axis sets
would do nothing and is refused. A file without ``[sweep]`` is one job written into ``<out>`` itself.
``<out>/jobs.json`` maps each folder to its settings and command line.

A sweep makes at most `MAX_JOBS` jobs: the product of its axes' lengths is counted before any job is made, and a
file past the limit is refused with one line giving the count (``--dry-run`` too), at once.

A job renders frames 0 to N - 1 (``frames = N``) as ``volren render --frames N`` would. Without ``--workers`` or
``--ray-address`` the jobs run in this process one after another; on Ray the engine splits each into work units (a
frame each; a temporal method one frame range per worker) and every job's folder also holds its ``batch.json``
manifest, so running the file again resumes where it stopped. The files are the same either way.

Everything is checked before any Ray start or render, each problem one `VolrenError` naming the file and the key:
a file with no flag and no sweep, unknown keys (with the closest flag), wrong types, an empty [sweep] or axis, a flag
two axes set, a top-level flag that every entry of an axis replaces, two jobs in one folder, and every
expanded command line through the plan's parser and checks (`volren.plan.plan_render`, as ``volren render``
would run them).
"""

from __future__ import annotations

import argparse
import difflib
import itertools
import json
import math
import os
import re
import shlex
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from volren.distributed.engine import Job, JobState, plan_job
from volren.errors import VolrenError
from volren.plan.spec import RenderSpec

COMMANDS = ("render", "animate")
RESERVED = ("command", "out", "sweep")
"""top-level keys that are not flags: which command, the batch's folder, what varies"""
BATCH_FLAGS = {"out": "the batch's folder is the top-level out; each job writes a sub-folder of it",
               **{flag: "a `volren batch` option" for flag in ("workers", "ray-address", "gpus-per-worker")}}
"""render/animate flags a job file may not set, and why"""
ALL_FRAMES = "all"
"""``frames = "all"``: every frame of the --volume sequence"""
MAX_JOBS = 1000
"""jobs a job file may make: each is checked and planned in the driver before anything renders, ~27 ms and ~1 MB
each (the plan holds its scene) for the smallest, a 32x24 ``smoke``: 1,000 jobs take ~30 s and ~1 GB before the
first frame (10,000 would take ~5 min and ~10 GB; a real volume more). Past it, split the sweep into several files."""
FOLDER_CHARS = re.compile(r"[^A-Za-z0-9.+-]+")
FLAG_IN_MESSAGE = re.compile(r"--([a-z][a-z0-9-]*)")


@dataclass(frozen=True)
class Setting:
    """One flag's value and the key of the job file that gives it (``width``, ``sweep.looks[1].tf``)."""

    flag: str
    value: Any
    key: str


@dataclass(frozen=True)
class Batch:
    """An expanded, checked job file."""

    source: Path
    out: Path
    command: str
    jobs: tuple[Job, ...]
    folders: tuple[str, ...]
    varies: tuple[dict[str, Any], ...]
    """per job: what its folder varies (job-file key -> value)"""
    frames: tuple[int, ...]
    views: tuple[int, ...]
    units: tuple[int, ...]
    """per job: the work units the engine splits it into (`engine.plan_job`); in process a job is one run"""
    devices: tuple[str, ...]
    """per job: where it renders (``--gpus-per-worker`` needs CUDA)"""
    states: tuple[JobState, ...]
    """per job: the engine's plan of it (`engine.plan_job`), which the run uses: a job is planned once"""


class Flags:
    """The long flags of ``volren <command>`` and how each takes its value (argparse's own actions)."""

    def __init__(self, command: str) -> None:
        from volren.plan import render_parser
        from volren.plan.argv import command_options

        self.parser, self.command = render_parser(), command
        self.actions: dict[str, argparse.Action] = {}
        for action in command_options(command):
            names = [o[2:] for o in action.option_strings if o.startswith("--")]
            if names and names[0] not in BATCH_FLAGS:
                self.actions[names[0]] = action

    def kind(self, flag: str) -> str:
        action = self.actions[flag]
        if isinstance(action, argparse._StoreTrueAction):
            return "switch"
        return "repeatable" if isinstance(action, argparse._AppendAction) else "value"


def load_batch(path: Path, workers: int | None = None) -> Batch:
    """Read, expand and check the job file ``path`` (see the module docstring); ``workers``: how many the units are
    planned for (temporal methods get one frame range per worker)."""
    try:
        doc = tomllib.loads(path.read_text())
    except OSError as exc:
        raise VolrenError(f"cannot read job file '{path}': {exc.strerror}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise VolrenError(f"{path}: not a valid TOML file: {exc}") from None
    fail = _failer(path)
    command = doc.get("command", "render")
    if command not in COMMANDS:
        fail("command", f"must be one of {', '.join(COMMANDS)}, got {command!r}")
    flags = Flags(command)
    folder = doc.get("out", f"out/{path.stem}")
    if not isinstance(folder, str) or not folder.strip():
        fail("out", "must be a folder name")
    out = Path(folder)
    base = {}
    for key, value in doc.items():
        if key not in RESERVED:
            base[key] = _setting(fail, flags, key, key, value)
    sweep = doc.get("sweep", {})
    if not isinstance(sweep, dict):
        fail("sweep", "must be a table of what varies ([sweep])")
    if not base and not sweep:
        raise VolrenError(f"{path} has no jobs: it sets no flag and no [sweep] (e.g. scene = \"smoke\", and a [sweep] "
                          "of what varies: see examples/turntable-sweep.toml)")
    if "sweep" in doc and not sweep:
        fail("sweep", "is empty: give it an axis (a flag = [values]), or leave [sweep] out for one job")
    axes = [_axis(fail, flags, name, values) for name, values in sweep.items()]
    _check_axes_disjoint(fail, axes)
    _check_top_not_swept(fail, base, sweep, axes)
    count = math.prod(len(axis) for axis in axes)  # counted, not enumerated: a product can be astronomical
    if count > MAX_JOBS:
        fail("sweep", f"makes {count:,} jobs ({' x '.join(str(len(axis)) for axis in axes)}), more than the "
             f"{MAX_JOBS:,} a job file may make (each is checked and planned before anything renders): split it into "
             "several job files")
    jobs, folders, varies, states = [], [], [], []
    seen: dict[str, str] = {}
    for combo in itertools.product(*axes) if axes else [()]:
        settings = dict(base)
        for _, entry in combo:
            settings |= {s.flag: s for s in entry}
        folder = "_".join(part for part, _ in combo) or "."
        vary = {s.key: s.value for _, entry in combo for s in entry}
        if folder in seen:
            fail(next(iter(vary)), f"jobs {seen[folder]} and {_describe(vary)} both write folder '{folder}': "
                 "name the table axes' entries apart (name = ...)")
        seen[folder] = _describe(vary)
        state = _checked_job(fail, flags, command, settings, out / folder, folder, len(jobs), workers)
        jobs.append(state.job)
        folders.append(folder)
        varies.append(vary)
        states.append(state)
    if out.exists() and not out.is_dir():
        fail("out", f"'{out}' is a file, not a folder")
    return Batch(path, out, command, tuple(jobs), tuple(folders), tuple(varies),
                 tuple(s.plan.args.frames for s in states), tuple(len(s.plan.views) for s in states),
                 tuple(len(s.units) for s in states), tuple(s.plan.renderer.device for s in states), tuple(states))


def _failer(path: Path):
    def fail(key: str, message: str):
        raise VolrenError(f"{path}: {key}: {message}")

    return fail


def _describe(vary: dict[str, Any]) -> str:
    return "(" + ", ".join(f"{k} = {json.dumps(v)}" for k, v in vary.items()) + ")"


def _setting(fail, flags: Flags, key: str, flag: str, value: Any) -> Setting:
    """``flag = value`` at job-file key ``key``, its TOML type checked against how the flag takes its value."""
    if flag not in flags.actions:
        if flag in BATCH_FLAGS:
            fail(key, f"'{flag}' is {BATCH_FLAGS[flag]}")
        if flags.command == "render" and flag in Flags("animate").actions:
            fail(key, f"'{flag}' is a flag of `volren animate` only: set command = \"animate\"")
        close = difflib.get_close_matches(flag, [*flags.actions, *RESERVED], n=1)
        fail(key, f"unknown key '{flag}'" + (f": did you mean '{close[0]}'?" if close else ""))
    kind, bad = flags.kind(flag), []
    if kind == "switch":
        if not isinstance(value, bool):
            fail(key, f"'{flag}' is an on/off flag: true or false, got {json.dumps(value, default=str)}")
    elif isinstance(value, bool):
        fail(key, f"'{flag}' takes a value, not {json.dumps(value)}")
    elif kind == "repeatable":
        if not isinstance(value, list):
            fail(key, f"'{flag}' is repeatable: give an array of its values, e.g. {flag} = [...]")
        bad = [item for item in value if _text(item) is None]
    else:
        bad = [value] if _text(value) is None else []
    if bad:
        fail(key, f"'{flag}' takes a string, a number or an array of them, got {json.dumps(bad[0], default=str)}")
    if flag == "frames" and value != ALL_FRAMES and not isinstance(value, int):
        fail(key, f"frames must be a number of frames or \"{ALL_FRAMES}\" (a --volume sequence's), got "
             f"{json.dumps(value, default=str)}")
    return Setting(flag, value, key)


def _text(value: Any) -> str | None:
    """The command-line text of one value: a string or number, or a non-empty array of them joined by commas; None
    for anything else (a table, a boolean, nested arrays, a date)."""
    if isinstance(value, list):
        parts = [_text(v) for v in value if not isinstance(v, list)]
        return ",".join(parts) if value and len(parts) == len(value) and None not in parts else None
    if isinstance(value, bool) or not isinstance(value, str | int | float):
        return None
    return repr(value) if isinstance(value, float) else str(value)


def _axis(fail, flags: Flags, name: str, values: Any) -> list[tuple[str, tuple[Setting, ...]]]:
    """One axis of ``[sweep]``: its entries as (folder part, the settings the entry makes)."""
    key = f"sweep.{name}"
    if not isinstance(values, list):
        fail(key, "must be an array of values (one job each)")
    if not values:
        fail(key, "is empty: a sweep axis needs at least one value")
    tables = [isinstance(v, dict) for v in values]
    if any(tables) and not all(tables):
        fail(key, "mixes tables and values: an axis is either an array of tables or a flag's values")
    if not any(tables):  # a flag's values
        return [(f"{name}-{_folder_text(v)}", (_setting(fail, flags, f"{key}[{i}]", name, v),))
                for i, v in enumerate(values)]
    if name in flags.actions:
        fail(key, f"'{name}' is a flag: give its values (an axis of tables needs a name of its own)")
    entries = []
    for i, table in enumerate(values):
        entry_key = f"{key}[{i}]"
        label = table.get("name")
        if label is not None and not (isinstance(label, str) and _folder_text(label)):
            fail(f"{entry_key}.name", "must be a non-empty string (the job's folder part)")
        settings = tuple(_setting(fail, flags, f"{entry_key}.{flag}", flag, v)
                         for flag, v in table.items() if flag != "name")
        if not settings:
            fail(entry_key, "sets no flag")
        part = f"{name}-{_folder_text(label)}" if label else "-".join(f"{s.flag}-{_folder_text(s.value)}"
                                                                    for s in settings)
        entries.append((part, settings))
    return entries


def _folder_text(value: Any) -> str:
    """A value as a folder-name part: a path by its stem, other characters than letters, digits, . + - as '-'."""
    if isinstance(value, list):
        value = "-".join(_folder_text(v) for v in value)
    text = str(value)
    if "/" in text or "\\" in text:
        text = Path(text).stem
    return FOLDER_CHARS.sub("-", text).strip("-.")


def _check_axes_disjoint(fail, axes: list) -> None:
    """No flag set by two axes: which would win would depend on their order."""
    owner: dict[str, str] = {}
    for axis in axes:
        flags_here = {s.flag: s.key for _, entry in axis for s in entry}
        for flag, key in flags_here.items():
            if flag in owner and owner[flag].split("[")[0] != key.split("[")[0]:
                fail(key, f"'{flag}' is also set by {owner[flag].split('[')[0]}: one axis per flag")
            owner.setdefault(flag, key)


def _check_top_not_swept(fail, base: dict[str, Setting], sweep: dict[str, Any], axes: list) -> None:
    """No flag both at the top of the file and in every entry of a sweep axis: every job would take the sweep's value
    and the top one would do nothing. (An axis of tables whose entries set a flag only some of the time takes the top
    value as the others' default.)"""
    for name, axis in zip(sweep, axes, strict=True):
        for flag in [f for f in base if all(any(s.flag == f for s in entry) for _, entry in axis)]:
            fail(f"sweep.{name}", f"'{flag}' is set at the top of the file too ({flag} = "
                 f"{json.dumps(base[flag].value)}), but every job takes the sweep's value: remove one")


def _argv(flags: Flags, command: str, settings: dict[str, Setting], out: Path) -> tuple[list[str], dict[str, str]]:
    """The command line of one job and, per flag on it, the job-file key that set it."""
    argv, origin = [command], {}
    for flag, s in settings.items():
        origin[flag] = s.key
        kind = flags.kind(flag)
        if kind == "switch":
            argv += [f"--{flag}"] if s.value else []
        elif kind == "repeatable":
            for item in s.value:
                argv += [f"--{flag}", _text(item)]
        elif not (flag == "frames" and s.value == ALL_FRAMES):
            argv += [f"--{flag}", _text(s.value)]
    return [*argv, "--out", str(out)], origin


def _checked_job(fail, flags: Flags, command: str, settings: dict[str, Setting], out: Path, folder: str,
                 index: int, workers: int | None):
    """The job of ``settings``, planned by the engine (`engine.plan_job`: the plan's parser and every check
    ``volren render`` makes before rendering, then its units); an error names the job-file key of the flag it is
    about."""
    from volren.plan import volume_sequence

    argv, origin = _argv(flags, command, settings, out)

    def refuse(message: str):
        named = [f for f in FLAG_IN_MESSAGE.findall(message) if f in origin]
        where = origin[named[0]] if named else f"job '{folder}'"
        fail(where, message.removeprefix("argument "))

    all_frames = "frames" in settings and settings["frames"].value == ALL_FRAMES
    if all_frames and "volume" not in settings:
        refuse(f"--frames \"{ALL_FRAMES}\" plays a --volume sequence; this job has no --volume")
    try:
        args = flags.parser.parse_args(argv)  # the job file's flags read once, here: the job carries its spec
        if all_frames:  # the sequence's length; one frame of a single volume file
            played = volume_sequence(args)
            args.frames = 1 if played is None else len(played)
            argv[-2:-2] = ["--frames", str(args.frames)]
        return plan_job(index, Job(RenderSpec.from_args(args, shlex.join(["volren", *argv]))), workers, None)
    except VolrenError as exc:
        refuse(str(exc))


def write_index(batch: Batch) -> Path:
    """``<out>/jobs.json``: folder -> what varies and the command line (written beside and renamed over)."""
    index = {"source": str(batch.source), "command": batch.command,
             "jobs": {folder: {"settings": vary, "frames": frames, "views": views, "command": job.spec.line,
                               "spec": job.spec.to_json()}
                      for folder, vary, frames, views, job in zip(batch.folders, batch.varies, batch.frames,
                                                                  batch.views, batch.jobs, strict=True)}}
    batch.out.mkdir(parents=True, exist_ok=True)
    path = batch.out / "jobs.json"
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(index, indent=2) + "\n")
    os.replace(tmp, path)
    return path


def run_batch(args: argparse.Namespace) -> int:
    """``volren batch``: check the whole job file, then run its jobs in process or on Ray."""
    on_ray = args.workers is not None or args.ray_address is not None
    flag = "--workers" if args.workers is not None else "--ray-address"
    if on_ray:
        from volren.distributed.runtime import import_ray

        import_ray(flag, local=args.ray_address is None)  # missing: one line before the checks' seconds of work
    if args.workers is not None and args.workers < 1:
        raise VolrenError(f"--workers must be >= 1, got {args.workers}")
    if args.gpus_per_worker is not None and not on_ray:
        raise VolrenError("--gpus-per-worker shares a GPU among Ray workers: give --workers or --ray-address")
    batch = load_batch(args.job, args.workers)
    if args.gpus_per_worker is not None and not any(d.startswith("cuda") for d in batch.devices):
        raise VolrenError("--gpus-per-worker shares a GPU among workers: the workers render on the CPU here")
    if args.dry_run:
        for folder, frames, views, units, job in zip(batch.folders, batch.frames, batch.views, batch.units,
                                                     batch.jobs, strict=True):
            print(f"{folder}: {frames} frame(s) x {views} view(s), {units} unit(s): {job.spec.line}")
        print(f"{len(batch.jobs)} job(s), {sum(batch.units)} unit(s) into {batch.out}")
        return 0
    if args.ray_address is not None:  # nothing answering there: refused before the batch's folder is touched
        from volren.distributed.runtime import check_address

        check_address(args.ray_address)
    index = write_index(batch)
    if on_ray:
        from volren.distributed.engine import run_jobs

        report = run_jobs(batch.jobs, workers=args.workers, address=args.ray_address, flag=flag,
                          gpus_per_worker=args.gpus_per_worker or 1.0, planned=batch.states)
        print(f"{len(batch.jobs)} job(s) into {batch.out} in {report.wall_seconds:.2f} s on {report.workers} "
              f"worker(s) (Ray start-up {report.ray_start_seconds:.1f} s): {report.units_run} unit(s) run, "
              f"{report.units_skipped} skipped, {report.units_retried} retried; index {index}")
        return 0
    from volren.output import print_summary
    from volren.plan import render_plan

    for i, (folder, state) in enumerate(zip(batch.folders, batch.states, strict=True)):
        print(f"job {i + 1}/{len(batch.jobs)}: {folder}", file=sys.stderr)
        plan = state.plan
        done = render_plan(plan, state.job.spec.line)
        print_summary(plan.method, plan.scene.name, len(plan.views), plan.args.frames, done.wall,
                      done.frames[-1].stats, done.files, done.stats)
    print(f"{len(batch.jobs)} job(s) into {batch.out}; index {index}")
    return 0
