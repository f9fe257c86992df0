"""Renderers, one module per method; `METHODS` maps the CLI's --method names to their classes. (The public API's
``volren.render`` is the function `volren._api.render`: see `volren`'s docstring.)"""

from volren.render.base import Renderer
from volren.render.fog.renderer import FogConfig, FogRenderer
from volren.render.frame import COUNTERS, Frame, Stats
from volren.render.marching.cacrm import CACRM, CACRMConfig
from volren.render.marching.cmsrm import CMSRM, CMSRMConfig
from volren.render.marching.dssrm import DSSRM, DSSRMConfig
from volren.render.reference import Reference, ReferenceConfig
from volren.render.vpt.tracer import VPT, VPTConfig

METHODS: dict[str, tuple[type[Renderer], type]] = {
    "dssrm": (DSSRM, DSSRMConfig),
    "cmsrm": (CMSRM, CMSRMConfig),
    "cacrm": (CACRM, CACRMConfig),
    "reference": (Reference, ReferenceConfig),
    "fog": (FogRenderer, FogConfig),
    "vpt": (VPT, VPTConfig),
}


__all__ = [
    "CACRM",
    "CMSRM",
    "COUNTERS",
    "DSSRM",
    "METHODS",
    "VPT",
    "CACRMConfig",
    "CMSRMConfig",
    "DSSRMConfig",
    "FogConfig",
    "FogRenderer",
    "Frame",
    "Reference",
    "ReferenceConfig",
    "Renderer",
    "Stats",
    "VPTConfig",
]
