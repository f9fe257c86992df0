"""scripts/vpt_fire_bias.py (issue 47 item 4): VPT against the reference on fire, at the pixel centres and
box-filtered, with the seeds' standard error."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_fire_bias_probe_reports_vpt_against_both_references(capsys):
    spec = importlib.util.spec_from_file_location("vpt_fire_bias", ROOT / "scripts" / "vpt_fire_bias.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.main(["--seeds", "6", "--spp", "32", "--supersample", "4", "--size", "16"]) == 0
    row = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert row["seeds"] == 6 and row["supersample"] == 4
    # the pixel filter moves the sum by a few percent at most (1.8% at 16 px, 0.17% at 40); VPT lands within 5
    # standard errors of the box-filtered reference, the standard error itself a few percent at this size
    assert 0.97 < row["box_over_centres"] < 1.03
    box = row["vpt_over_box_filtered"]
    assert 0 < box["se"] < 0.03 and abs(box["ratio"] - 1.0) < 5 * box["se"]
    assert abs(row["vpt_over_centres"]["ratio"] / row["box_over_centres"] - box["ratio"]) < 1e-4
