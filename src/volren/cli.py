"""``volren`` command line: demo, render, scenes, compare, bench. Argparse and printing over the plan
(`volren.plan`), which makes every check of a render.

Every user error (bad file, bad number, no GPU, ...) is printed as one line on stderr with exit status 2.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import signal
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from volren.errors import VolrenError, VolrenWarning
from volren.plan.argv import add_device, add_volume_args, command_parser
from volren.plan.options import (
    DEFAULT_RESOLUTION,
    DEFAULT_SCENE,
    CliError,
    _warned,
    check_scene_name,
    warn,
)
from volren.plan.render import check_render_args, plan_render, render_plan
from volren.plan.served import served_volume


def _show_warning(show, message, category, filename, lineno, file=None, line=None) -> None:
    """`warnings.showwarning` while a command runs: a `VolrenWarning` (a renderer's or a loader's) as `warn`'s one
    line, anything else as Python shows it."""
    if issubclass(category, VolrenWarning):
        warn(str(message))
    else:
        show(message, category, filename, lineno, file, line)


def add_serve_args(p: argparse.ArgumentParser) -> None:
    from volren.presets import QUALITIES
    from volren.serve.rates import TICK_MS

    p.add_argument("--scene", help=f"built-in scene (default {DEFAULT_SCENE}; see `volren scenes`)")
    add_volume_args(p)
    p.add_argument("--resolution", type=int, help=f"built-in volume scenes: voxels per axis, 64-512 (default: "
                   f"{DEFAULT_RESOLUTION})")
    p.add_argument("--method", help="dssrm, cmsrm, cacrm, vpt or fog (default: dssrm, fog for fog scenes)")
    p.add_argument("--quality", default="interactive", choices=QUALITIES, help="starting preset (viewers may switch)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on; any but loopback needs a token "
                   "(--token-file, VOLREN_TOKEN or --token)")
    p.add_argument("--port", type=int, default=8000, help="TCP port, in [1, 65535]")
    p.add_argument("--token-file", metavar="PATH", help="a file holding the secret every request must carry (as "
                   "?token=T, or the cookie the page gets with it), 16-256 URL-safe characters (default: none; "
                   "without --token-file and --token, the environment variable VOLREN_TOKEN if set)")
    p.add_argument("--token", help="the secret itself, as --token-file's content (visible to every local user in "
                   "the process list: prefer --token-file or VOLREN_TOKEN; default: none)")
    p.add_argument("--allow-host", action="append", default=[], metavar="NAME", help="a further name the Host "
                   "header may give (repeatable; default: the bound address, and localhost on loopback)")
    p.add_argument("--allow-origin", action="append", default=[], metavar="ORIGIN", help="a further page origin, "
                   "http://host:port, allowed to open /ws (repeatable; default: the server's own only)")
    p.add_argument("--lock-settings", action="store_true", help="viewers may not change the shared method, "
                   "quality, transfer function, light or playback")
    p.add_argument("--max-viewers", type=int, default=16, help="viewers connected at once, in [1, 1024]")
    p.add_argument("--max-viewers-per-client", type=int, help="viewers connected at once from one address, so one "
                   "neighbour cannot take every slot (on loopback each 127.x.y.z counts apart; default: 4, at most "
                   "--max-viewers)")
    p.add_argument("--max-width", type=int, default=1920, help="[px] largest viewer image (stereo: both eyes)")
    p.add_argument("--max-height", type=int, default=1080, help="[px] largest viewer image")
    p.add_argument("--pixel-budget", type=int, default=1920 * 1080, help="[px] rendered per tick for all viewers "
                   "at most")
    p.add_argument("--tick-ms", type=float, default=TICK_MS, help="[ms] with several viewers, the tick time aimed "
                   "at: each gets an equal share of it, a viewer whose frame costs more gets a smaller one (0: share "
                   f"the pixel budget only; default {TICK_MS:g})")
    s = p.add_argument_group("beyond one process (Ray: pip install 'volren[ray]')")
    s.add_argument("--shards", type=int, help="render on N >= 1 Ray actors, each a render loop for the viewers "
                   "placed on it (a stereo pair whole, viewers of one part of the scene together); a local Ray is "
                   "started (default: none, one render loop in process)")
    s.add_argument("--data-parallel", type=int, metavar="N", help="--volume FILE split into N >= 1 regions, each "
                   "held and rendered by its own Ray actor, the images composited (dssrm: modes dvr, mip, iso; a "
                   "local Ray is started) (default: none, the volume in process)")
    s.add_argument("--ray-address", help="with --shards or --data-parallel: run the actors on the Ray cluster at "
                   "ADDR (host:port, or 'auto') (default: a local Ray)")
    add_device(p)


def served_file(args: argparse.Namespace) -> dict:
    """`build_loop`'s scene, camera and play step for ``serve --volume`` (none without, `served_volume`): a sequence
    plays its frames in a loop."""
    served = served_volume(args)
    if served is None:
        return {}
    from volren.serve.loop import sequence_player

    animate = None if served.frames == 1 else sequence_player(served.frames, served.scene_at)
    return {"scene": served.scene, "camera": served.camera, "animate": animate}


def data_parallel_engine(args: argparse.Namespace, scene, animate):
    """``serve --data-parallel N``'s region actors: each reads ``--volume`` itself and keeps its region."""
    import os

    from volren.distributed.regions import RegionEngine
    from volren.distributed.runtime import import_ray
    from volren.plan.served import ServedScene
    from volren.presets import quality_config
    from volren.render import DSSRM

    if animate is not None:
        raise CliError(f"--data-parallel splits one volume: the sequence {args.volume} changes it every frame")
    import_ray("--data-parallel", local=not args.ray_address)
    renderer = DSSRM(quality_config("dssrm", args.quality, reuse_light_map=True), device=args.device)
    return RegionEngine(ServedScene(args, os.getcwd()), scene, args.data_parallel, renderer,
                        address=args.ray_address)


def run_serve(args: argparse.Namespace) -> int:
    # the checks that need no data first: the imports below take seconds
    if not 1 <= args.port <= 65535:
        raise CliError(f"--port must lie in [1, 65535], got {args.port}")
    if args.ray_address is not None and args.shards is None and args.data_parallel is None:
        raise CliError("--ray-address needs --shards N or --data-parallel N (the server renders in process without "
                       "them)")
    if args.data_parallel is not None:
        if args.shards is not None:
            raise CliError("--data-parallel splits the volume and --shards the viewers: give one of them")
        if args.data_parallel < 1:
            raise CliError(f"--data-parallel must be >= 1 regions, got {args.data_parallel}")
        if args.volume is None:
            raise CliError("--data-parallel splits the volume of --volume FILE (a built-in scene's smoke is advected "
                           "every tick)")
        if args.method not in (None, "dssrm"):
            raise CliError(f"--data-parallel renders with dssrm only: method {args.method} has cube maps, paths or "
                           "grids that cross the regions")
    if args.shards is not None and args.shards < 1:
        raise CliError(f"--shards must be at least 1, got {args.shards}")
    check_scene_name(args.scene)
    from volren.serve.heap import one_arena

    one_arena()  # before the imports below start threads
    from volren.serve.app import TOKEN_ENV, build_loop, check_bind, make_app, read_token, serve
    from volren.serve.viewers import Limits

    token, source = read_token(args.token, args.token_file)
    check_bind(args.host, token, tuple(args.allow_origin), source or "--token")
    if source == "--token":
        warn(f"--token is visible to every local user in the process list (ps, /proc/PID/cmdline): prefer --token-file "
             f"PATH or {TOKEN_ENV}")
    per_client = args.max_viewers_per_client
    if per_client is not None and per_client > args.max_viewers:
        raise CliError(f"--max-viewers-per-client {per_client} exceeds --max-viewers {args.max_viewers}: it would "
                       "limit nothing")
    limits = Limits(args.max_viewers, args.max_width, args.max_height, args.pixel_budget,
                    max_per_client=per_client or min(Limits.max_per_client, args.max_viewers),
                    tick_ms=args.tick_ms or None)
    name = args.scene or DEFAULT_SCENE
    served = served_file(args)
    engine = None if args.data_parallel is None else data_parallel_engine(args, served["scene"], served["animate"])
    loop = build_loop(name, args.method, args.quality, args.resolution or DEFAULT_RESOLUTION, args.device, limits,
                      args.lock_settings, **served, shards=args.shards, ray_address=args.ray_address,
                      data_parallel=engine)
    name = args.volume.name if args.volume is not None else name
    serve(make_app(loop, name, token, hosts=(args.host, *args.allow_host), origins=tuple(args.allow_origin)),
          args.host, args.port, token, source)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p, sub = command_parser()
    sub.add_parser("scenes", help="list the built-in scenes")
    c = sub.add_parser("compare", help="PSNR, SSIM, FLIP of TEST against REF, and an error heat map")
    c.add_argument("ref", type=Path, help="reference image: .npy linear, or PNG/JPEG; its peak must be > 0")
    c.add_argument("test", type=Path, help="image to measure, same size and kind as REF")
    c.add_argument("--heatmap", type=Path, help="heat map PNG (default: next to TEST, *_error.png)")
    add_serve_args(sub.add_parser("serve", help="serve a scene live to browsers: each viewer steers its own "
                                  "camera; one render call per tick serves them all"))
    b = sub.add_parser("bench", help="run a benchmark suite; writes JSON and a Markdown table")
    b.add_argument("suite", help="suite name (see `volren bench list`)")
    b.add_argument("--quick", action="store_true", help="small sizes for a CPU")
    b.add_argument("--out", type=Path, default=None,
                   help="folder for the JSON and Markdown (default out/bench; --out docs/bench updates the committed "
                        "tables)")
    b.add_argument("--repeats", type=int, help="timed frames per case instead of the suite's own (at least 1; the "
                   "frame-timed suites: a full-size run on a CPU cuts repeats, not sizes) (default: the suite's)")
    b.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="settings",
                   help="replace an entry of the suite's configuration (repeatable; VALUE as JSON, e.g. frames=12: "
                   "a full-size run on a CPU cuts a camera path's frames, not its sizes) (default: none)")
    b.add_argument("--shards", help="bench serve: COUNTS, comma-separated (e.g. 1,2): the sharded server on a local "
                   "Ray with each count of shards, against the loop in process (default: no shards)")
    add_device(b)
    j = sub.add_parser("batch", help="run a sweep of renders a TOML job file describes: in process, or on Ray with "
                       "--workers or --ray-address")
    j.add_argument("job", type=Path, help="job file: render/animate options and a [sweep] of what varies (see "
                   "examples/turntable-sweep.toml)")
    j.add_argument("--workers", type=int, help="run on a local Ray with N >= 1 workers (default: none, in process)")
    j.add_argument("--ray-address", help="run on the Ray cluster at ADDR (host:port, or 'auto') (default: none)")
    j.add_argument("--gpus-per-worker", type=float, help="CUDA: the GPU share each worker asks, in (0, 1] "
                   "(default 1)")
    j.add_argument("--dry-run", action="store_true", help="check the job file, print its jobs and render nothing")
    return p


def run_render(args: argparse.Namespace, method: str, command: str) -> int:
    """``volren render``/``animate``: on Ray with --workers or --ray-address, else in this process."""
    check_render_args(args, method)  # before the imports of either path
    if getattr(args, "data_parallel", None) is not None:
        from volren.distributed.regions import run_data_parallel

        return run_data_parallel(args, method, command)
    if getattr(args, "workers", None) is not None or getattr(args, "ray_address", None) is not None:
        from volren.distributed.engine import run_command_on_ray

        return run_command_on_ray(args, command)
    plan = plan_render(args, method)
    from volren.output import print_summary

    done = render_plan(plan, command)
    print_summary(method, plan.scene.name, len(plan.views), args.frames, done.wall, done.frames[-1].stats, done.files,
                  done.stats)
    return 0


def run_scenes() -> int:
    from volren.data import BUILTIN_SCENES
    from volren.data.fog_scenes import FOG_SCENES

    width = max(len(n) for n in [*BUILTIN_SCENES, *FOG_SCENES])
    for name, spec in BUILTIN_SCENES.items():
        print(f"{name:<{width}}  {spec.description}")
    for name, description in FOG_SCENES.items():
        print(f"{name:<{width}}  {description} (meshes and fog: --method fog)")
    return 0


def run_compare(args: argparse.Namespace) -> int:
    from volren.metrics import compare_files

    heatmap = args.heatmap or args.test.with_name(args.test.stem + "_error.png")
    result = compare_files(args.ref, args.test, heatmap)
    print(f"PSNR {result['psnr']:.2f} dB  SSIM {result['ssim']:.5f}  FLIP {result['flip']:.5f}  "
          f"max |error| {result['max_abs_error']:.4g}")
    print(f"  heat map (per-pixel L1 of normalised RGB, 0..25%): {heatmap}")
    return 0


def bench_overrides(settings: list[str]) -> dict[str, Any]:
    """``--set KEY=VALUE`` entries: VALUE read as JSON (numbers, lists), else as a string."""
    out: dict[str, Any] = {}
    for item in settings:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise CliError(f"--set takes KEY=VALUE, got '{item}'")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def run_bench(args: argparse.Namespace) -> int:
    from volren.bench.runner import all_suites, run_suite

    if args.suite == "list":
        for name, suite in all_suites().items():
            print(f"{name}: {suite.description}")
        return 0
    suite = None
    if args.shards is not None:
        if args.suite != "serve":
            raise CliError(f"--shards: bench serve only (the sharded server), not bench {args.suite}")
        from volren.bench.serve import shard_suite

        try:
            suite = shard_suite([int(n) for n in args.shards.split(",")])
        except ValueError:
            raise CliError(f"--shards must be comma-separated shard counts like 1,2, got {args.shards}") from None
    json_path, md_path, table = run_suite(suite.name if suite else args.suite, quick=args.quick, device=args.device,
                                          out=args.out, suite=suite, repeats=args.repeats,
                                          overrides=bench_overrides(args.settings))
    print(table)
    print(f"wrote {json_path} and {md_path}")
    return 0


def run_command(args: argparse.Namespace, command: str) -> int:
    if args.command == "demo":
        return run_render(args, "dssrm", command)
    if args.command in ("render", "animate"):
        return run_render(args, args.method, command)
    if args.command == "scenes":
        return run_scenes()
    if args.command == "compare":
        return run_compare(args)
    if args.command == "serve":
        return run_serve(args)
    if args.command == "batch":
        from volren.distributed.job import run_batch

        return run_batch(args)
    return run_bench(args)


def main(argv: Sequence[str] | None = None) -> int:
    from volren.errors import Terminated

    console = argv is None  # the volren command, not a caller in Python
    argv = list(sys.argv[1:] if argv is None else argv)
    command = " ".join(["volren", *argv])
    try:
        args = build_parser().parse_args(argv)
        _warned.clear()
        with warnings.catch_warnings():
            warnings.simplefilter("always", VolrenWarning)  # `warn` says each once
            warnings.showwarning = functools.partial(_show_warning, warnings.showwarning)
            code = run_command(args, command)
        sys.stdout.flush()  # a reader that left shows here, not in Python's exit-time flush
        if console and "warp" in sys.modules:
            # every output is closed by now; the interpreter's teardown with Warp loaded waits 2-4 s in native code
            sys.stderr.flush()
            os._exit(code)
        return code
    except BrokenPipeError:
        # `volren scenes | head -1`: the reader has all it wanted. Stop quietly with the status SIGPIPE would give,
        # and point stdout at /dev/null so the exit-time flush has nowhere to fail.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except VolrenError as exc:
        print(f"volren: error: {exc}", file=sys.stderr)
        return 2
    except MemoryError:
        print("volren: error: out of memory (try a smaller image, resolution or view count)", file=sys.stderr)
        return 2
    except OSError as exc:  # what no loader or writer turned into a VolrenError: stdout on a full disk, mostly
        print(f"volren: error: cannot write {exc.filename or 'stdout'}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except Terminated:  # SIGTERM during a run on Ray: stopped as Ctrl-C stops it (below), 128 + SIGTERM
        print("volren: terminated", file=sys.stderr)
        if console:
            sys.stderr.flush()
            os._exit(128 + signal.SIGTERM)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print("volren: interrupted", file=sys.stderr)
        if console:  # run_output has removed any partial run; the interpreter's exit would wait seconds on Warp
            sys.stderr.flush()
            os._exit(130)
        return 130


if __name__ == "__main__":
    sys.exit(main())
