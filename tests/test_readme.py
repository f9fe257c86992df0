"""README: the quick start tells where `make demo` puts the command, and every repository file it names exists."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()


def test_quick_start_says_where_volren_is():
    quick = README.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    assert ".venv/bin/volren" in quick and "source .venv/bin/activate" in quick


def test_every_repository_file_named_exists():
    named = {m.split("{")[0].rstrip(".,:;)") for m in re.findall(r"\b(?:docs|scripts|src|tests)/[\w./{},-]+", README)}
    named |= set(re.findall(r"\b[A-Z][A-Z_]+\.md\b", README))  # DESIGN.md, BENCHMARKS.md, ...
    assert named
    missing = sorted(n for n in named if not (ROOT / n).exists() and not (ROOT / "docs" / n).exists())
    assert not missing, f"README names files not in the repository: {missing}"
