"""Out-of-core multiscale streaming, the data side (issue 41 item 3): OME-Zarr pyramids read brick by brick from a
folder, a zip or an fsspec URL (`source`), the level each brick wants and the order they load in (`lod`), what is
resident within a memory budget (`cache`), and a reader pool that loads bricks on demand without ever making a frame
wait (`streamer`), and the density a volume streams (`density`). numpy, zarr, fsspec and threads, no Warp of its own
(importing `volren.data.ngff` for the NGFF helpers runs `volren.data`'s package import, which loads Warp today): the
renderers' page table builds on it (`volren.render.streaming`).

Source -> cache -> renderer, one way (DESIGN.md): the renderer says what it needs each frame and draws what is
resident (`BrickStreamer.best_resident`), the finest resident ancestor where a brick has not come yet.
"""

from volren.stream.cache import BrickCache
from volren.stream.layout import BRICK, PyramidLayout
from volren.stream.lod import BrickNeed, frame_needs, pixel_footprint, wanted_level
from volren.stream.source import PyramidSource
from volren.stream.streamer import BrickStreamer

__all__ = [
    "BRICK",
    "BrickCache",
    "BrickNeed",
    "BrickStreamer",
    "PyramidLayout",
    "PyramidSource",
    "frame_needs",
    "pixel_footprint",
    "wanted_level",
]
