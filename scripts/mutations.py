"""Mutation catalogue runner: every paper part has a small edit that breaks it, and a test that must catch it.

Reads `tests/mutations.toml` (one ``[[mutant]]`` table per part: ``name``, ``part``, ``file``, ``find`` (source text
that occurs exactly once), ``replace``, ``tests`` (pytest node ids or files)). For each mutant it copies the tracked
and untracked-but-not-ignored files into a scratch folder, applies the edit, and runs the listed tests there against
the scratch copy's sources. A mutant is *killed* when pytest reports failing tests (exit status 1, "failed" in its
summary); it *survives* when they pass, and it is *invalid* when the edit does not apply, pytest cannot even collect
(an import or syntax error proves nothing about the tests) or only errors in set-up (a fixture's cluster that did not
start). Exit status 0 only when every mutant selected is killed.

    python scripts/mutations.py                   # the whole catalogue, 2 mutants at a time
    python scripts/mutations.py --only fog- -j 1  # names starting with "fog-"
    python scripts/mutations.py --list
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FIELDS = {"name", "part", "file", "find", "replace", "tests"}


@dataclass(frozen=True)
class Mutant:
    name: str
    part: str
    file: str
    find: str
    replace: str
    tests: tuple[str, ...]


@dataclass(frozen=True)
class Outcome:
    mutant: Mutant
    verdict: str
    """killed | survived | invalid"""
    seconds: float
    detail: str


def load(path: Path, only: list[str]) -> list[Mutant]:
    """Parse and check the catalogue (the mutants whose names start with a prefix in ``only``, or all): unknown or
    missing fields, duplicate names and edits that do not apply are errors before any test runs."""
    try:
        tables = tomllib.loads(path.read_text())["mutant"]
    except (OSError, tomllib.TOMLDecodeError, KeyError) as exc:
        sys.exit(f"error: {path}: {exc}")
    mutants, problems = [], []
    for i, t in enumerate(tables):
        label = t.get("name", f"#{i}")
        if set(t) != FIELDS:
            problems.append(f"{label}: fields {sorted(set(t) ^ FIELDS)} missing or unknown")
            continue
        m = Mutant(t["name"], t["part"], t["file"], t["find"], t["replace"], tuple(t["tests"]))
        if only and not any(m.name.startswith(p) for p in only):
            mutants.append(m)  # kept for the duplicate-name check only
            continue
        source = ROOT / m.file
        count = source.read_text().count(m.find) if source.is_file() else -1
        if count != 1:
            problems.append(f"{m.name}: `find` occurs {count} times in {m.file}" if count >= 0
                            else f"{m.name}: no file {m.file}")
        if m.find == m.replace or not m.tests:
            problems.append(f"{m.name}: the edit changes nothing or no tests are named")
        mutants.append(m)
    names = [m.name for m in mutants]
    problems += [f"{n}: duplicate name" for n in sorted({n for n in names if names.count(n) > 1})]
    if problems:
        sys.exit("error: tests/mutations.toml:\n  " + "\n  ".join(problems))
    return mutants


def project_files() -> list[str]:
    out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"], cwd=ROOT,
                         check=True, capture_output=True).stdout.decode()
    return [f for f in out.split("\0") if f and (ROOT / f).is_file()]


def scratch_copy(files: list[str], into: Path) -> None:
    for f in files:
        (into / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / f, into / f)


def run_one(m: Mutant, files: list[str], timeout: float) -> Outcome:
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix=f"mutant-{m.name}-") as tmp:
        work = Path(tmp)
        scratch_copy(files, work)
        target = work / m.file
        target.write_text(target.read_text().replace(m.find, m.replace, 1))
        # The scratch sources shadow the editable install: PYTHONPATH comes before site-packages' finders.
        env = {**os.environ, "PYTHONPATH": str(work / "src"), "PYTHONDONTWRITEBYTECODE": "1"}
        cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", "-p", "no:randomly", *m.tests]
        try:
            proc = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return Outcome(m, "invalid", time.perf_counter() - start, f"tests ran past {timeout:.0f} s")
        tail = (proc.stdout + proc.stderr).strip().splitlines()[-1:] or [""]
        verdict = {0: "survived", 1: "killed"}.get(proc.returncode, "invalid")
        summary = proc.stdout.strip().splitlines()[-1:] or [""]  # pytest's "1 failed, 2 passed in 3.0s"
        if verdict == "killed" and " failed" not in summary[0]:  # only errors: a fixture's Ray start that timed out
            verdict = "invalid"
        return Outcome(m, verdict, time.perf_counter() - start, f"pytest exit {proc.returncode}: {tail[0]}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--catalogue", type=Path, default=ROOT / "tests" / "mutations.toml")
    ap.add_argument("--only", action="append", default=[], metavar="PREFIX",
                    help="run mutants whose name starts with PREFIX (repeatable)")
    ap.add_argument("-j", "--jobs", type=int, default=2, help="mutants run at once (default 2)")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per mutant's tests (default 900)")
    ap.add_argument("--list", action="store_true", help="list the catalogue and exit")
    args = ap.parse_args(argv)
    mutants = load(args.catalogue, args.only)
    if args.only:
        mutants = [m for m in mutants if any(m.name.startswith(p) for p in args.only)]
        if not mutants:
            sys.exit(f"error: --only: no mutant name starts with {' or '.join(args.only)}")
    if args.list:
        for m in mutants:
            print(f"{m.name:40s} {m.part}")
        return 0
    files = project_files()
    counts = {"killed": 0, "survived": 0, "invalid": 0}
    start = time.perf_counter()
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        for o in pool.map(lambda m: run_one(m, files, args.timeout), mutants):
            counts[o.verdict] += 1
            print(f"{o.verdict:8s} {o.seconds:6.1f} s  {o.mutant.name}  ({o.mutant.part})"
                  + ("" if o.verdict == "killed" else f"\n         {o.detail}"), flush=True)
    print(f"{counts['killed']} killed, {counts['survived']} survived, {counts['invalid']} invalid of "
          f"{len(mutants)} in {time.perf_counter() - start:.0f} s")
    return 0 if counts["killed"] == len(mutants) else 1


if __name__ == "__main__":
    sys.exit(main())
