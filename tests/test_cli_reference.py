"""docs/CLI.md is the parser's help (issue 42 item 4): regenerated here and compared, so a flag added, renamed or
reworded without `python scripts/cli_reference.py --out docs/CLI.md` fails."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_committed_cli_reference_is_the_parsers_help(monkeypatch):
    monkeypatch.setenv("COLUMNS", "60")  # the script fixes the width itself: a narrow terminal changes nothing
    spec = importlib.util.spec_from_file_location("cli_reference", ROOT / "scripts" / "cli_reference.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    text = module.reference()
    committed = (ROOT / "docs" / "CLI.md").read_text()
    assert text == committed, "docs/CLI.md is stale: run python scripts/cli_reference.py --out docs/CLI.md"
    for command in ("demo", "render", "animate", "scenes", "compare", "serve", "bench", "batch"):
        assert f"## `volren {command}`" in text and f"usage: volren {command}" in text, command
    assert "--max-viewers-per-client" in text and "--tick-ms" in text and "--token-file" in text
