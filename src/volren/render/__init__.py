"""Renderers, one module per method; `METHODS` maps the CLI's --method names to their classes.

Called, this package is the public API's ``volren.render(scene, views, method=..., quality=..., **settings)``
(`volren._api.render`): the import system binds the subpackage to the name ``volren.render``, where it would hide a
function.
"""

import sys
import types
from typing import Any

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


class _CallablePackage(types.ModuleType):
    def __call__(self, *args: Any, **kwargs: Any) -> Frame:
        from volren._api import render

        return render(*args, **kwargs)


sys.modules[__name__].__class__ = _CallablePackage

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
