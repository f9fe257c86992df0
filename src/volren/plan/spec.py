"""A render as plain data (`RenderSpec`): the command (demo, render, animate) and the value of every option, which
the batch engine's jobs and Ray workers receive instead of a command line to parse again. It pickles for Ray and
round-trips through JSON (`to_json`, `from_json`: ``jobs.json`` and the manifests hold it), so a job can be re-run
from its file, and `namespace` gives the options `plan_render` takes. A command line becomes a spec once, in the
process that read it (`parse`: the CLI's words, the batch file's flags); nothing downstream parses text again."""

from __future__ import annotations

import argparse
import functools
import shlex
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from volren.errors import VolrenError

COMMANDS = ("demo", "render", "animate")


@functools.cache
def _schema(command: str) -> dict[str, tuple[bool, Any]]:
    """Per option of ``command``: (it repeats, the parser's type where its values are paths, else None), from the
    parser's actions (no parsing)."""
    from volren.plan.argv import command_options, out_folder
    from volren.store import volume_path

    paths = (Path, out_folder, volume_path)
    return {a.dest: (isinstance(a, argparse._AppendAction), a.type if a.type in paths else None)
            for a in command_options(command)}


def _plain(value: Any) -> Any:
    """``value`` as JSON has it: paths as text, tuples as lists."""
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def _typed(value: Any, path: Any) -> Any:
    """A JSON value back as the parser gives it: a path (by the option's own type: ``path``), or a tuple where JSON
    has a list."""
    if value is None:
        return None
    if path is not None:
        return path(value)
    if isinstance(value, list):
        return tuple(_typed(v, None) for v in value)
    return value


@dataclass(frozen=True)
class RenderSpec:
    """``volren <command>`` with ``options`` (every option's value by its name, as `namespace` gives them: sorted
    (name, value) pairs, so two specs of the same render compare equal). ``line``: the command line as its user
    gave it, for stats.json and messages; never parsed."""

    command: str
    options: tuple[tuple[str, Any], ...]
    line: str = ""

    @classmethod
    def from_args(cls, args: argparse.Namespace, line: str = "") -> RenderSpec:
        """The spec of options already parsed (``args.command`` one of `COMMANDS`); attributes that are not options
        of the command are left out."""
        if getattr(args, "command", None) not in COMMANDS:
            raise VolrenError(f"a render spec is one of {', '.join(COMMANDS)}, got {getattr(args, 'command', None)}")
        names = _schema(args.command)
        return cls(args.command, tuple(sorted((k, v) for k, v in vars(args).items() if k in names)), line)

    @classmethod
    def parse(cls, argv: Sequence[str]) -> RenderSpec:
        """``volren <argv>`` (``argv[0]`` the command) read by the CLI's parser: the one place text becomes a spec."""
        from volren.plan.argv import render_parser

        argv = list(argv)
        if not argv or argv[0] not in COMMANDS:
            raise VolrenError(f"a render spec is one of {', '.join(COMMANDS)}, got '{' '.join(argv[:1])}'")
        return cls.from_args(render_parser().parse_args(argv), shlex.join(["volren", *argv]))

    def namespace(self, **changes: Any) -> argparse.Namespace:
        """The options as `plan_render` takes them (a fresh object: the plan sets animate's --frames on it), with
        ``changes`` (option names) on top."""
        unknown = set(changes) - set(_schema(self.command))
        if unknown:
            raise VolrenError(f"{self.command} has no option {sorted(unknown)[0]}")
        return argparse.Namespace(**{"command": self.command, **dict(self.options), **changes})

    def replace(self, **changes: Any) -> RenderSpec:
        """This spec with ``changes`` (option names); ``line`` as before."""
        return RenderSpec.from_args(self.namespace(**changes), self.line)

    @property
    def out(self) -> Path:
        return dict(self.options)["out"]

    def to_json(self) -> dict[str, Any]:
        return {"command": self.command, "options": {k: _plain(v) for k, v in self.options}, "line": self.line}

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> RenderSpec:
        """`to_json`'s dict back as the spec it was: each option typed as the parser types it."""
        command = doc.get("command")
        if command not in COMMANDS:
            raise VolrenError(f"a render spec is one of {', '.join(COMMANDS)}, got {command!r}")
        schema, options = _schema(command), doc.get("options", {})
        if set(options) != set(schema):
            wrong = sorted(set(options) ^ set(schema))
            raise VolrenError(f"the {command} spec's options differ from this volren's: {', '.join(wrong[:3])}")
        typed = {}
        for name, value in options.items():
            repeats, path = schema[name]
            typed[name] = [_typed(v, path) for v in value] if repeats else _typed(value, path)
        return cls(command, tuple(sorted(typed.items())), doc.get("line", ""))
