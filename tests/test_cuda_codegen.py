"""Every Warp kernel module also compiles for CUDA (PTX for sm_90, the H100/H200), even on a machine without a GPU:
Warp's NVRTC compiler works without a driver. This catches CUDA-only codegen errors before a GPU ever runs them."""

from __future__ import annotations

import importlib

import pytest
import warp as wp

from volren.device import init_warp

KERNEL_MODULES = [
    "volren.render.marching.dssrm",
    "volren.render.reference",
    "volren.render.lightmap",
    "volren.render.compositing.surfaces",
    "volren.render.marching.cubemap",
    "volren.render.marching.cmsrm",
    "volren.render.marching.cacrm",
    "volren.render.marching.interleave",
    "volren.render.marching.culling",
    "volren.render.compositing.oit",
    "volren.render.fog.renderer",
    "volren.render.fog.froxels",
    "volren.render.vpt.tracer",
    "volren.render.vpt.denoise",
    "volren.render.gi.passes",
    "volren.simulate",
    "volren.data.loaders",
]


@pytest.mark.parametrize("name", KERNEL_MODULES)
def test_kernel_module_compiles_to_ptx(name, tmp_path):
    init_warp()
    importlib.import_module(name)
    try:
        paths = wp.compile_aot_module(name, arch=90, module_dir=tmp_path, use_ptx=True)
    except RuntimeError as exc:
        if "nvrtc" in str(exc).lower():
            pytest.skip(f"this Warp build has no NVRTC: {exc}")
        raise
    ptx = [p for p in paths if p.suffix == ".ptx"]
    assert ptx and ".entry" in ptx[0].read_text()
