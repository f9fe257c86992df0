"""The package layout (issue 42 item 1, DESIGN.md): data flows one way, data -> scene -> render -> plan -> front ends,
and nothing imports the CLI. Read from the source's syntax trees, so an import inside a function counts too."""

from __future__ import annotations

import ast
from pathlib import Path

import volren

SRC = Path(volren.__file__).resolve().parent
"""src/volren"""
CLI_ENTRY = {"_entry.py", "cli.py"}
"""the console script, and the CLI itself"""
FRONT_ENDS = ("volren.cli", "volren.serve", "volren.distributed", "volren.bench", "volren.notebook")
"""what builds on the plan: the plan imports none of them"""
CLI_LINES_BEFORE = 1552
"""cli.py's lines before the plan moved out of it (issue 42 item 1)"""
CLI_LINES_AT_MOST = 499
"""the issue's goal: argparse and printing, under 500 lines (336 when the plan moved out)"""


def imported_modules(source: str, package: str) -> list[tuple[int, str]]:
    """(line, module) of every import in ``source``, anywhere in it; ``from A import b`` counts as ``A`` and ``A.b``,
    relative imports resolved against the module's ``package``."""
    package = package.split(".")
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            module = ".".join([*base, *([node.module] if node.module else [])])
            found += [(node.lineno, module)] + [(node.lineno, f"{module}.{alias.name}") for alias in node.names]
    return found


def importers(prefixes: tuple[str, ...], files) -> list[str]:
    """``file:line module`` of each import in ``files`` of a module named by, or under, one of ``prefixes``."""
    return [f"{p.relative_to(SRC)}:{line} {m}" for p in files
            for line, m in imported_modules(p.read_text(), ".".join(["volren", *p.relative_to(SRC).parent.parts]))
            if any(m == x or m.startswith(x + ".") for x in prefixes)]


def test_the_import_finder_sees_imports_inside_functions_and_relative_ones() -> None:
    """The check below can fail: a function-level import, a ``from volren import cli`` and a relative one (of a
    module in volren.distributed) are all found."""
    code = "def f():\n    from volren import cli\n    import volren.cli as c\n    from ..cli import main\n"
    found = [m for _, m in imported_modules(code, "volren.distributed") if m.startswith("volren.cli")]
    assert found == ["volren.cli", "volren.cli", "volren.cli", "volren.cli.main"]


def test_nothing_but_the_console_script_imports_the_cli() -> None:
    files = [p for p in sorted(SRC.rglob("*.py")) if p.relative_to(SRC).as_posix() not in CLI_ENTRY]
    assert len(files) > 50
    assert importers(("volren.cli",), files) == []


def test_the_plan_imports_no_front_end() -> None:
    files = sorted((SRC / "plan").glob("*.py"))
    assert {p.stem for p in files} >= {"__init__", "render", "scene", "views", "renderer"}
    assert importers(FRONT_ENDS, files) == []


def test_the_cli_is_argparse_and_printing_over_the_plan() -> None:
    lines = len((SRC / "cli.py").read_text().splitlines())
    print(f"src/volren/cli.py: {lines} lines (was {CLI_LINES_BEFORE})")
    assert lines < CLI_LINES_BEFORE
    assert lines <= CLI_LINES_AT_MOST, f"cli.py has {lines} lines, over the {CLI_LINES_AT_MOST} of issue 42"
