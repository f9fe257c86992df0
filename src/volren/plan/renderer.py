"""A render's renderer: the method's config from the quality preset and the options that override it, animate's
sequence, and an isosurface value chosen from the data."""

from __future__ import annotations

import argparse
import dataclasses
import sys

from volren.plan.options import CliError, check_method, warn
from volren.plan.volume import _volume_from_args


def renderer_from_args(args: argparse.Namespace, method: str):
    from volren.presets import quality_options
    from volren.render import METHODS
    from volren.render.gi.ambient import GIConfig

    check_method(method)
    cls, config_cls = METHODS[method]
    fields = {f.name for f in dataclasses.fields(config_cls)}
    # config field -> (value given on the command line or None, the flag that gives it)
    given = {
        "samples": (args.samples, "--samples"),
        "light_samples": (args.light_samples, "--light-samples"),
        "light_grid": (args.light_grid, "--light-grid"),
        "jitter": (args.jitter or None, "--jitter"),
        "cube_faces": (args.cube_faces, "--cube-faces"),
        "cube_size": (args.cube_size, "--cube-size"),
        "adaptive_lod": (False if args.no_lod else None, "--no-lod"),
        "hybrid": (False if args.no_hybrid else None, "--no-hybrid"),
        "cull_tiles": (False if args.no_cull else None, "--no-cull"),
        "skip_empty": (False if args.no_skip else None, "--no-skip"),
        "tile_lod": (args.tile_lod or None, "--tile-lod"),
        "k_z": (args.k_z, "--k-z"),
        "coupling": (False if args.no_coupling else None, "--no-coupling"),
        "share_voxels": (False if args.no_share else None, "--no-share"),
        "vsa": (False if args.no_vsa else None, "--no-vsa"),
        "k_a": (args.k_a, "--k-a"),
        "interleave": (False if args.no_interleave else None, "--no-interleave"),
        "mode": (None if args.mode in (None, "dvr") else args.mode, "--mode"),
        "iso_value": (args.iso_value, "--iso-value"),
        "oit": (args.oit, "--oit"),
        "oit_k": (args.oit_k, "--oit-k"),
        "spp": (args.spp, "--spp"),
        "max_bounces": (args.max_bounces, "--max-bounces"),
        "shading": (args.shading, "--shading"),
        "transfer": (args.tf, "--tf"),
        "ambient": (args.vpt_ambient or None, "--vpt-ambient"),
        "clip": (args.clip, "--clip"),
        "denoise": (args.denoise, "--denoise"),
        "sharing": (args.fog_sharing, "--fog-sharing"),
        "voxel_size": (args.voxel_size, "--voxel-size"),
        "slices": (args.slices, "--slices"),
        "tile": (args.froxel_size, "--froxel-size"),
        "far": (args.fog_far, "--fog-far"),
        "trilinear": (args.trilinear or None, "--trilinear"),
        "temporal": (False if args.no_temporal else None, "--no-temporal"),
    }
    if args.iso_value is not None and args.mode != "iso":
        raise CliError("--iso-value needs --mode iso")
    if args.k_a is not None and (args.no_vsa or args.mode not in (None, "dvr")):
        raise CliError("--k-a sets VSA's ramp, which marches in --mode dvr only and not with --no-vsa")
    gi = {"method": (args.gi, "--gi"), "order": (args.gi_order, "--gi-order"), "rays": (args.gi_rays, "--gi-rays"),
          "volumes_per_frame": (args.gi_volumes, "--gi-volumes")}
    gi_options = {k: v for k, (v, _) in gi.items() if v is not None}
    if gi_options:
        if gi_options.get("method", "none") == "none" and len(gi_options) > (1 if "method" in gi_options else 0):
            raise CliError("--gi-order, --gi-rays and --gi-volumes need --gi with a method other than none")
        given["gi"] = (GIConfig(**gi_options), ", ".join(flag for k, (v, flag) in gi.items() if v is not None))
    # the preset first: a flag given on the command line overrides the field it sets
    options = quality_options(method, args.quality)
    options |= {k: v for k, (v, _) in given.items() if v is not None and k in fields}
    ignored = [flag for k, (v, flag) in given.items() if v is not None and k not in fields]
    if ignored:
        raise CliError(f"method '{method}' does not take {', '.join(ignored)}")
    if args.tf is not None:
        replaced = [flag for k, flag in (("density_scale", "--density-scale"), ("albedo", "--albedo"),
                                         ("emission", "--emission")) if getattr(args, k, None) is not None]
        if replaced:
            raise CliError(f"--tf gives the extinction, albedo and emission: {', '.join(replaced)} would do nothing")
    if "seed" in fields:
        options["seed"] = args.seed
    channels = len(_volume_from_args(args).channels) if getattr(args, "volume", None) is not None else 0
    if channels:  # each channel its own renderer, the images added
        from volren.render.compositing.channels import AdditiveChannels

        return AdditiveChannels(lambda: cls(config_cls(**options), device=args.device), channels)
    return cls(config_cls(**options), device=args.device)


def sequence_from_args(args: argparse.Namespace):
    """``volren animate``'s sequence; None for ``render``."""
    if args.command != "animate":
        return None
    from volren.animate import Sequence

    switch_frame = switch_tf = None
    if args.switch_tf is not None:
        frame, sep, tf = args.switch_tf.partition(":")
        if not sep or not frame.strip().isdecimal():
            raise CliError(f"--switch-tf must be FRAME:TF, got '{args.switch_tf}'")
        switch_frame, switch_tf = int(frame), tf
    return Sequence(frames=args.frames, orbit=args.orbit, light_orbit=args.light_orbit, switch_frame=switch_frame,
                    switch_transfer=switch_tf, fps=args.fps)


def iso_value_from_data(args: argparse.Namespace, scene, renderer) -> dict:
    """``--mode iso``: without --iso-value, V is Otsu's threshold of the scene's densities (`otsu_iso_value`), set in
    the renderer's config and ``args`` and said in one line; a given V outside the densities is warned of in one line
    (`iso_range_message`) before any rendering. Returns stats.json's ``iso_value`` entry when V was chosen here."""
    if getattr(renderer.config, "mode", "dvr") != "iso":
        return {}
    from volren.render.marching.modes import iso_range_message, otsu_iso_value

    densities = [v.density for v in scene.volumes]
    lo, hi = min(float(d.min()) for d in densities), max(float(d.max()) for d in densities)
    if args.iso_value is not None:
        message = iso_range_message(args.iso_value, lo, hi)
        if message:
            warn(message)
        return {}
    value = otsu_iso_value(densities)
    args.iso_value = value  # for the renderers made from args later (the run-time probe)
    renderer.config = dataclasses.replace(renderer.config, iso_value=value)
    print(f"volren: --mode iso without --iso-value: the isosurface is at density {value:.4g}, Otsu's threshold of "
          f"the densities {lo:.4g} to {hi:.4g} (give --iso-value to choose)", file=sys.stderr)
    return {"iso_value": {"value": value, "rule": "otsu", "densities": [lo, hi]}}
