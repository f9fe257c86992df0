"""The plan: what a render is (its scene source, material and light overrides, views or automatic framing, method,
quality and settings, frames and output), every check of it made once, and how its frames are rendered and written.
The front ends build on it: the CLI (argparse and printing), batch jobs and the Ray workers
(`volren.distributed`), the benchmarks (`volren.bench`). Nothing here imports a front end.

- `options`: the names, defaults and limits of the options, `CliError` and the one `warn` line;
- `argv`: the options in the command line's words (argument types, the parser of demo, render and animate);
- `volume`: a ``--volume`` file or sequence, read once; `scene`: the scene and its overrides;
- `views`: the cameras, framing a file whole; `renderer`: the method's config from the preset and the options;
- `render`: `RenderPlan`, `plan_render` (every check, then the plan) and `render_plan` (its frames, written).

Building the parser and the checks that need no data import no renderer, Warp or numpy.
"""

from volren.plan.argv import render_parser
from volren.plan.options import CliError, warn
from volren.plan.render import Rendered, RenderPlan, frame_prefix, plan_render, render_plan, write_plan_frame
from volren.plan.volume import volume_sequence

__all__ = ["CliError", "RenderPlan", "Rendered", "frame_prefix", "plan_render", "render_parser", "render_plan",
           "volume_sequence", "warn", "write_plan_frame"]
