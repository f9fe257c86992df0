"""tests/mutations.toml stays runnable: every mutant's `find` occurs exactly once in its file (`scripts/mutations.py
--list` checks it), so a refactor that changes a line a mutant breaks is caught here, not by the next audit."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.timeout(60)
def test_every_mutant_of_the_catalogue_applies():
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "mutations.py"), "--list"], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    assert len(done.stdout.splitlines()) >= 700  # the catalogue was read whole
