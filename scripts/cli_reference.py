"""The CLI reference, docs/CLI.md, generated from the parser (issue 42 item 4): every command's usage and options as
`volren CMD --help` prints them at 120 columns. `tests/test_cli_reference.py` checks the committed file matches, so
the reference cannot drift from the flags.

    python scripts/cli_reference.py                      # print it
    python scripts/cli_reference.py --out docs/CLI.md    # rewrite the committed file
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

COLUMNS = 120
"""argparse wraps help to the terminal's width: fixed here, so the file is the same on every machine"""
HEADER = """# Command-line reference

Generated from the parser by `python scripts/cli_reference.py --out docs/CLI.md` (a test checks it is current): each
command's `--help` as printed at {columns} columns. The README groups examples by task; this page lists every flag.
"""


def reference() -> str:
    """docs/CLI.md's text."""
    os.environ["COLUMNS"] = str(COLUMNS)  # read by argparse's formatter when it is made, i.e. at each format_help
    from volren.cli import build_parser

    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    parts = [HEADER.format(columns=COLUMNS), "## `volren`\n", "```text\n" + parser.format_help().rstrip() + "\n```\n"]
    for name, sub in commands.items():
        parts += [f"## `volren {name}`\n", "```text\n" + sub.format_help().rstrip() + "\n```\n"]
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="write it there (default: print it)")
    args = ap.parse_args(argv)
    text = reference()
    if args.out is None:
        sys.stdout.write(text)
    else:
        args.out.write_text(text)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
