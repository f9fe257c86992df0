"""Scene data: built-in procedural scenes and volume file loaders."""

from volren.data.loaders import load_volume_file
from volren.data.meshes import load_mesh_file
from volren.data.procedural import (
    BUILTIN_SCENES,
    COUNTED_SCENES,
    MAX_RESOLUTION,
    MIN_RESOLUTION,
    MULTI_COUNTS,
    BuiltinScene,
    builtin_scene,
    classic_look,
    cloud_density,
    density_field,
    instances_layout,
    multi_layout,
    phantom_density,
    smoke_density,
)

__all__ = [
    "BUILTIN_SCENES",
    "COUNTED_SCENES",
    "MAX_RESOLUTION",
    "MIN_RESOLUTION",
    "MULTI_COUNTS",
    "BuiltinScene",
    "builtin_scene",
    "classic_look",
    "cloud_density",
    "density_field",
    "instances_layout",
    "load_mesh_file",
    "load_volume_file",
    "multi_layout",
    "phantom_density",
    "smoke_density",
]
