"""README: the quick start tells where `make demo` puts the command, and every repository file it names exists."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np

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


# Every `volren` line of the README's sh blocks runs at a reduced size (the overrides below come last, so argparse
# takes them over the line's own values), in a scratch folder holding stand-ins for the user's files it names.
# Skipped: `volren bench` suites (minutes each even with --quick; tests/test_bench.py runs their configs small).
MARCHERS = ("--samples", "16", "--light-samples", "8")
SMALL = {
    "dssrm": (*MARCHERS, "--light-grid", "16"), "cmsrm": (*MARCHERS, "--light-grid", "16", "--cube-size", "32"),
    "cacrm": (*MARCHERS, "--light-grid", "16", "--cube-size", "32"), "reference": MARCHERS,
    "vpt": ("--spp", "1"), "fog": ("--slices", "16", "--voxel-size", "0.5"),
}
SIZE = ("--width", "32", "--height", "24", "--device", "cpu")


def readme_commands() -> list[list[str]]:
    blocks = re.findall(r"```sh\n(.*?)```", README, flags=re.S)
    lines = "\n".join(blocks).replace("\\\n", " ").splitlines()
    return [words for line in lines if (words := shlex.split(line, comments=True)) and words[0] == "volren"]


def reduced(words: list[str]) -> list[str]:
    args = words[1:]
    if args[0] not in ("render", "animate", "demo"):
        return args
    method = "dssrm" if args[0] == "demo" else args[args.index("--method") + 1] if "--method" in args else "dssrm"
    extra = [*SIZE, *SMALL[method]]
    # only a built-in volume scene takes --resolution: a --volume file and the fog scenes refuse it
    fog = method == "fog" or any(a.startswith("--method=fog") for a in args)
    if not fog and not any(a == "--volume" or a.startswith("--volume=") for a in args):
        extra += ["--resolution", "64"]
    if "--frames" in args or args[0] == "animate":
        extra += ["--frames", "2"]
    if "--switch-tf" in args:
        extra += ["--switch-tf", "1:" + args[args.index("--switch-tf") + 1].split(":", 1)[1]]
    if "--gi-rays" in args:
        extra += ["--gi-rays", "16"]
    if "--shape" in args:
        extra += ["--shape", "16,16,16"]
    return [*args, *extra]


def stand_ins(folder: Path) -> None:
    """The user's files the README names, small."""
    import nibabel as nib
    import nrrd

    from volren.data.procedural import phantom_density
    from volren.transfer import PRESETS

    head = phantom_density(64)
    nrrd.write(str(folder / "head.nrrd"), np.asfortranarray((head * 1000).astype(np.int16).transpose(2, 1, 0)),
               {"space": "left-posterior-superior", "space directions": np.diag([3.0, 3.0, 3.0]).tolist()},
               index_order="F")
    nib.save(nib.Nifti1Image(np.ascontiguousarray(head.transpose(2, 1, 0)), np.diag([3.0, 3.0, 3.0, 1.0])),
             str(folder / "ct.nii.gz"))
    (head[::4, ::4, ::4] * 60000).astype(np.uint16).tofile(folder / "ct.raw")  # 16^3, as --shape 16,16,16 says
    sky = np.ones((16, 32, 3), np.float32) * np.linspace(2.0, 0.2, 16, dtype=np.float32)[:, None, None]
    np.save(folder / "sky.npy", sky)
    np.save(folder / "zbuffer.npy", np.full((24, 32), 3.0, np.float32))
    (folder / "bunny.obj").write_text("v 0 0 0\nv 0.2 0 0\nv 0 0.2 0\nv 0 0 0.2\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    (folder / "my_tf.json").write_text(PRESETS["ct-bone"].to_json())


def out_folder(args: list[str]) -> Path:
    return Path(args[len(args) - 1 - args[::-1].index("--out") + 1]) if "--out" in args else Path("out")


def test_every_readme_command_runs_at_reduced_size(tmp_path, monkeypatch, capsys):
    import imageio.v3 as iio

    from volren.cli import main

    commands = [reduced(w) for w in readme_commands() if w[1] != "bench" or w[2] == "list"]
    # compare reads what the renders wrote, wherever the README puts it
    commands.sort(key=lambda a: a[0] == "compare")
    assert len(commands) >= 35  # 44 volren lines, 8 of them benches
    stand_ins(tmp_path)
    monkeypatch.chdir(tmp_path)
    # `volren serve` builds its scene, render loop and app, then would listen until interrupted: not here
    monkeypatch.setattr("volren.serve.app.serve", lambda app, host, port, token: None)
    failed = []
    for args in commands:
        code = main(args)
        err = capsys.readouterr().err.strip().splitlines()
        if code != 0:
            failed.append(f"volren {' '.join(args)}: exit {code}: {err[-1] if err else ''}")
            continue
        if args[0] in ("render", "animate", "demo"):
            pngs = sorted(out_folder(args).glob("*view0.png"))
            image = iio.imread(pngs[0]).astype(float)
            if image[..., :3].std() < 0.5:  # one flat colour: nothing drawn
                failed.append(f"volren {' '.join(args)}: blank image {pngs[0]}")
    assert not failed, "\n".join(failed)


def test_every_readme_python_block_runs_as_written(tmp_path, monkeypatch):
    """The README's Python examples, sized to finish in seconds, run unchanged on the stand-in files in a scratch
    folder, using the public API only (`import volren as vr`)."""
    from PIL import Image

    blocks = re.findall(r"```python\n(.*?)```", README, flags=re.S)
    assert blocks
    stand_ins(tmp_path)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(Image.Image, "show", lambda image, *args, **kwargs: None)  # Frame.show: no viewer here
    for n, code in enumerate(blocks):
        assert not re.search(r"\b(from|import) volren\.", code), f"README python block {n} imports a private module"
        exec(compile(code, f"README.md python block {n}", "exec"), {"__name__": "readme"})
