"""Data-parallel rendering's Ray-free foundation (issue 43): a volume's brick grid split into convex regions by a k-d
tree (`regions`), the order a view's rays meet them (`order`), and sort-last compositing of the regions' partial
images (`composite`). numpy only: the Ray actors that own the regions build on it."""

from volren.dataparallel.composite import composite_max, composite_nearest, composite_over
from volren.dataparallel.order import visibility_order, visibility_order_direction
from volren.dataparallel.regions import (
    Region,
    RegionTree,
    Split,
    box_in_voxels,
    bricks_per_axis,
    local_box,
    plane_local,
    split_regions,
)

__all__ = [
    "Region",
    "RegionTree",
    "Split",
    "box_in_voxels",
    "bricks_per_axis",
    "composite_max",
    "composite_nearest",
    "composite_over",
    "local_box",
    "plane_local",
    "split_regions",
    "visibility_order",
    "visibility_order_direction",
]
