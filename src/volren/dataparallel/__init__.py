"""Data-parallel, sort-last rendering (issue 43): a volume's brick grid split into convex regions by a k-d tree
(`regions`), the order a view's rays meet them (`order`), sort-last compositing of the regions' partial images
(`composite`), a volume cut to one region's bricks (`volume`), and N regions rendered and composited in one process
(`render`: `RegionSet`, and the pieces `volren.distributed.regions` runs one Ray actor per region with). The first
three are numpy only."""

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
