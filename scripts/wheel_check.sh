#!/usr/bin/env bash
# `make wheel-check`: volren as users get it, `pip install volren`, not `make`. Builds the sdist and, from it, the
# wheel (`python -m build`: a file missing from the sdist breaks the wheel too), fails on any setuptools deprecation
# warning, installs the wheel (no extras) into a fresh venv, and from a folder with no source tree beside it runs
# `volren demo` and the Python API, checking the pictures and the package data (viewer page, VSA fit table).
#
#   bash scripts/wheel_check.sh [PYTHON]     # PYTHON has `build` (the dev extra); default .venv/bin/python
set -euo pipefail
cd "$(dirname "$0")/.."
py=${1:-.venv/bin/python}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
start=$(date +%s)

if ! "$py" -m build --outdir "$work/dist" . >"$work/build.log" 2>&1; then
    cat "$work/build.log"; echo "wheel-check: python -m build failed" >&2; exit 1
fi
if grep -E "SetuptoolsDeprecationWarning|_DeprecatedConfig|deprecated" "$work/build.log"; then
    echo "wheel-check: the build warns of a deprecation (above); setuptools will stop building it" >&2; exit 1
fi
wheel=$(ls "$work"/dist/volren-*.whl)
echo "wheel-check: built $(basename "$wheel") and $(basename "$(ls "$work"/dist/volren-*.tar.gz)")"

base=$("$py" -c "import sys, os; print(os.path.join(sys.base_prefix, 'bin', 'python3'))")
"$base" -m venv "$work/venv"
if ! "$work/venv/bin/python" -m pip install --disable-pip-version-check -q "$wheel" >"$work/pip.log" 2>&1; then
    cat "$work/pip.log"; echo "wheel-check: the wheel does not install into a fresh venv" >&2; exit 1
fi

mkdir "$work/user" && cd "$work/user"  # no src/ beside it: imports must come from the installed wheel
"$work/venv/bin/volren" demo --resolution 64 --width 96 --height 64 --out demo >demo.log
"$work/venv/bin/python" - <<'PY'
import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np

import volren as vr
from volren.render.marching.vsa import VSA_FIT_FILE
from volren.serve.app import STATIC

assert "site-packages" in vr.__file__, f"volren imported from {vr.__file__}, not the installed wheel"
for name in ("index.html", "viewer.js", "viewer.css"):
    assert (STATIC / name).is_file(), f"the wheel lacks the viewer's {name}"
assert json.loads(VSA_FIT_FILE.read_text()), "the wheel lacks the VSA fit table"

# the demo: a stereo pair of the smoke, its plume in the middle of each eye, the corners empty
for v in (0, 1):
    img = iio.imread(f"demo/view{v}.png").astype(float)
    assert img.shape == (64, 96, 3), img.shape
    mid, corner = img[16:48, 32:64].mean(), img[:8, :8].mean()
    assert mid > corner + 20, (v, mid, corner)
assert json.loads(Path("demo/stats.json").read_text())["scene"] == "smoke"

# the Python API: a cloud by CACRM, opaque in the middle, transparent at the rim, the two eyes differ
eyes = vr.views(vr.Camera(position=(0, 0.4, 3.2), width=48, height=32), "stereo")
frame = vr.render(vr.builtin_scene("cloud", 64), eyes, method="cacrm", device="cpu")
alpha = frame.images[0][..., 3]
assert alpha[12:20, 18:30].mean() > 0.5 and alpha[0, 0] < 0.05, (alpha[12:20, 18:30].mean(), alpha[0, 0])
assert not np.array_equal(frame.images[0], frame.images[1])
print(f"wheel-check: volren {vr.__version__} from the wheel rendered the demo and the API's cloud "
      f"(centre alpha {alpha[12:20, 18:30].mean():.2f})")
PY
echo "wheel-check: passed in $(( $(date +%s) - start )) s"
