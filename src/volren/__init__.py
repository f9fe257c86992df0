"""volren: multi-view volumetric density rendering with NVIDIA Warp (CPU or CUDA).

The public API (model: a thin ``__all__`` over private modules, as Newton and pygfx have)::

    import volren as vr

    scene = vr.Scene([vr.load("ct.nrrd")])
    frame = vr.render(scene, vr.Camera(position=(0, 0.4, 3.2)), method="dssrm")
    frame.save("out")  # what `volren render` writes: view0.png, stats.json

Every name is imported on first use (PEP 562), so ``import volren`` and ``volren --help`` load neither Warp nor
numpy. ``volren.render`` is the API's function (`volren._api.render`: ``help`` shows its signature and docstring),
although the renderer subpackage has the same name: the import system binds a subpackage to its parent's
attribute, so this package's class keeps that attribute a property (`_Package`); the subpackage is in
``sys.modules["volren.render"]`` and ``from volren.render import ...`` reads it as ever.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import Any

_EXPORTS: dict[str, str] = {
    "__version__": "volren._version",
    "load": "volren._api",
    "builtin_scene": "volren._api",
    "views": "volren._api",
    "Renderer": "volren._api",
    "Scene": "volren.scene",
    "Volume": "volren.scene",
    "Channels": "volren.render.compositing.channels",
    "VolumeSequence": "volren.plan.volume",
    "DirectionalLight": "volren.scene",
    "PointLight": "volren.scene",
    "SpotLight": "volren.scene",
    "RectLight": "volren.scene",
    "Environment": "volren.scene",
    "Camera": "volren.camera",
    "Frame": "volren.render.frame",
    "DSSRMConfig": "volren.render.marching.dssrm",
    "CMSRMConfig": "volren.render.marching.cmsrm",
    "CACRMConfig": "volren.render.marching.cacrm",
    "ReferenceConfig": "volren.render.reference",
    "VPTConfig": "volren.render.vpt.tracer",
    "FogConfig": "volren.render.fog.renderer",
    "GIConfig": "volren.render.gi.ambient",
    "Viewer": "volren.notebook",
    "VolrenError": "volren.errors",
}
"""public name -> the module that defines it"""

__all__ = [*_EXPORTS, "render"]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'volren' has no attribute '{name}'")
    home = importlib.import_module(module)
    value = getattr(home, name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(__all__)


class _Package(types.ModuleType):
    """volren's module class: ``render`` is the API's function whatever the import system binds to it."""

    @property
    def render(self) -> Any:
        from volren._api import render

        return render

    @render.setter
    def render(self, subpackage: types.ModuleType) -> None:
        """``import volren.render`` binds the subpackage here; it stays in sys.modules only."""


sys.modules[__name__].__class__ = _Package
