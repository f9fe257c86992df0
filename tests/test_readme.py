"""README: the quick start tells where `make demo` puts the command, and every repository file it names exists."""

from __future__ import annotations

import importlib.util
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()


def test_quick_start_says_where_volren_is():
    quick = README.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    assert ".venv/bin/volren" in quick and "source .venv/bin/activate" in quick


def test_every_repository_file_named_exists():
    named = {m.split("{")[0].rstrip(".,:;)") for m in re.findall(r"\b(?:docs|scripts|src|tests)/[\w./{},-]+", README)}
    named |= set(re.findall(r"\b[A-Z][A-Z_-]+\.md\b", README))  # DESIGN.md, BENCHMARKS-LOG.md, ...
    assert named
    missing = sorted(n for n in named if not (ROOT / n).exists() and not (ROOT / "docs" / n).exists())
    assert not missing, f"README names files not in the repository: {missing}"


# Every `volren` line of the README's sh blocks runs at a reduced size (the overrides below come last, so argparse
# takes them over the line's own values), in a scratch folder holding stand-ins for the user's files it names;
# scripts/readme_examples.py --time runs them as written. `volren bench` lines are parsed and their suites looked
# up, not run (minutes each even with --quick; tests/test_bench.py runs their configs small).
MARCHERS = ("--samples", "16", "--light-samples", "8")
SMALL = {
    "dssrm": (*MARCHERS, "--light-grid", "16"), "cmsrm": (*MARCHERS, "--light-grid", "16", "--cube-size", "32"),
    "cacrm": (*MARCHERS, "--light-grid", "16", "--cube-size", "32"), "reference": MARCHERS,
    "vpt": ("--spp", "1"), "fog": ("--slices", "16", "--voxel-size", "0.5"),
}
SIZE = ("--width", "32", "--height", "24", "--device", "cpu")


def _examples_module():
    spec = importlib.util.spec_from_file_location("readme_examples", ROOT / "scripts" / "readme_examples.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


EXAMPLES = _examples_module()


def readme_commands() -> list[list[str]]:
    return [words for words in EXAMPLES.readme_examples(README) if words[0] == "volren"]


RAY_FLAGS = ("--workers", "--ray-address", "--shards", "--data-parallel")
"""run here without them, in process: tests/test_batch*.py, test_serve_shards.py and test_dataparallel_ray.py run the
Ray paths on the test session's one cluster (each README line would start another, and `--ray-address` names a
cluster that is not here)"""


def in_process(args: list[str]) -> list[str]:
    out, value_of_flag = [], False
    for a in args:
        if not value_of_flag and a.split("=", 1)[0] not in RAY_FLAGS:
            out.append(a)
        value_of_flag = a in RAY_FLAGS  # "--workers 2": skip the 2 as well
    return out


def reduced(words: list[str]) -> list[str]:
    args = in_process(words[1:])
    if args[0] == "batch":  # the example job's renders run tiny in tests/test_batch_job.py
        return args if "--dry-run" in args else [*args, "--dry-run"]
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
    return [*args, *extra]


def out_folder(args: list[str]) -> Path:
    return Path(args[len(args) - 1 - args[::-1].index("--out") + 1]) if "--out" in args else Path("out")


EXAMPLE_PIXEL_FRAMES = 5_000_000
"""width x height x views x frames of a README render as written: 2.2x the largest (fog hall, 16 viewers at 640x360);
the full-size animate examples (60 frames of 640x360 stereo) were 28 M"""
EXAMPLE_PATHS = 4_000_000
"""vpt: pixel-frames x spp as written (the largest: 3.7 M, the phantom at 320x180 stereo, 32 spp)"""
EXAMPLE_REFERENCE_STEPS = 7e10
"""reference: pixel-frames x view steps x shadow steps, as written (the largest: the cloud for the comparison at
320x180, 1024 x 1024, 6.0e10; instances-overlap at 640x360 was 2.4e11)"""


def test_every_readme_render_is_sized_to_finish_in_about_a_minute():
    """Issue 22.5: the README's renders as written stay within the sizes measured to run in about a minute on two
    cores (scripts/readme_examples.py --time); a line that grows back to full size fails here."""
    from volren.cli import build_parser
    from volren.presets import quality_config

    parser = build_parser()
    over = []
    for words in readme_commands():
        if words[1] not in ("render", "animate", "demo"):
            continue
        args = parser.parse_args(words[1:])
        views = {"mono": 1, "stereo": 2}.get(args.views) or int(args.views)
        pixel_frames = args.width * args.height * views * (args.frames or 60)  # animate's default 60
        config = quality_config(getattr(args, "method", "dssrm"), args.quality)
        work = {"pixel-frames": (pixel_frames, EXAMPLE_PIXEL_FRAMES)}
        if hasattr(config, "spp"):
            work["paths"] = (pixel_frames * (args.spp or config.spp), EXAMPLE_PATHS)
        if type(config).__name__ == "ReferenceConfig":
            steps = (args.samples or config.samples) * (args.light_samples or config.light_samples)
            work["reference steps"] = (pixel_frames * steps, EXAMPLE_REFERENCE_STEPS)
        over += [f"{shlex.join(words)}: {n:.2e} {what}" for what, (n, most) in work.items() if n > most]
    assert not over, "README examples too large to finish in about a minute:\n" + "\n".join(over)


def test_every_readme_line_parses_as_written():
    """The lines `reduced` changes (Ray flags dropped, batch jobs dry-run) still parse whole: a flag renamed fails."""
    from volren.cli import build_parser

    parser = build_parser()
    lines = [w for w in readme_commands() if any(a.split("=", 1)[0] in RAY_FLAGS for a in w) or w[1] == "batch"]
    assert len(lines) >= 5
    for words in lines:
        parser.parse_args(words[1:])


def test_every_readme_bench_line_names_a_suite():
    from volren.bench.runner import all_suites
    from volren.cli import build_parser

    benches = [w[1:] for w in readme_commands() if w[1] == "bench"]
    assert len(benches) >= 10
    parser = build_parser()
    for args in benches:
        parsed = parser.parse_args(args)
        assert parsed.suite == "list" or parsed.suite in all_suites(), args


def test_every_readme_command_runs_at_reduced_size(tmp_path, monkeypatch, capsys):
    import imageio.v3 as iio

    from volren.cli import main

    commands = [reduced(w) for w in readme_commands() if w[1] != "bench" or w[2] == "list"]
    # compare reads what the renders wrote, wherever the README puts it
    commands.sort(key=lambda a: a[0] == "compare")
    assert len(commands) >= 35  # 44 volren lines, 8 of them benches
    EXAMPLES.stand_ins(tmp_path, 32, 24)
    monkeypatch.chdir(tmp_path)
    # `volren serve` builds its scene, render loop and app, then would listen until interrupted: not here
    monkeypatch.setattr("volren.serve.app.serve", lambda app, host, port, token, source="--token": None)
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


@pytest.mark.xdist_group("ray")
def test_every_readme_python_block_runs_as_written(ray_cluster, tmp_path, monkeypatch):
    """The README's Python examples, sized to finish in seconds, run unchanged on the stand-in files in a scratch
    folder, using the public API only (`import volren as vr`; ``data_parallel=`` on the test session's Ray)."""
    from PIL import Image

    blocks = re.findall(r"```python\n(.*?)```", README, flags=re.S)
    assert blocks
    EXAMPLES.stand_ins(tmp_path, 32, 24)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(Image.Image, "show", lambda image, *args, **kwargs: None)  # Frame.show: no viewer here
    for n, code in enumerate(blocks):
        assert not re.search(r"\b(from|import) volren\.", code), f"README python block {n} imports a private module"
        exec(compile(code, f"README.md python block {n}", "exec"), {"__name__": "readme"})
