"""scripts/k_a_sweep.py: Eq. 4's ramp k_a against the reference at the default N (issue 24's k_a default)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_sweep_reports_each_ramp_against_the_reference(capsys):
    spec = importlib.util.spec_from_file_location("k_a_sweep", ROOT / "scripts" / "k_a_sweep.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main(["--scenes", "cloud", "--resolution", "64", "--size", "48x27", "--frames", "0", "--reference", "64",
                 "--k-a", "0,3", "--uniform", "24"])
    row = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert row["scene"] == "cloud" and row["frames"] == [0]
    flat, paper = row["CACRM:360 k_a 0"], row["CACRM:360 k_a 3"]
    # the paper's ramp takes fewer gathers than none; every method is close to the reference (not a blank image)
    assert paper["gathers"] < 0.8 * flat["gathers"]
    assert row["CACRM:24 uniform"]["gathers"] < flat["gathers"]
    keys = ("CMSRM:360:96", "CACRM:360 k_a 0", "CACRM:360 k_a 3", "CACRM:24 uniform")
    assert all(row[key]["psnr"] > 30.0 for key in keys)
