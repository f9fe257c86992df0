"""Where DSSRM's march spends its time on CUDA: 4.1M threads adding 3 times into int64 counters at 1, 64 or 4096
addresses (the work counters' pattern), and the 1080p stereo march at (1,1), (100,48) and (360,96) facing the
smoke and looking away from it. Needs a CUDA GPU; the H200 figures are in docs/bench/cuda-atomics-h200.txt.

    python scripts/cuda_atomics.py
"""

import time

import warp as wp

from volren.bench import measure
from volren.camera import Camera, make_views
from volren.data import builtin_scene
from volren.render import DSSRM, DSSRMConfig

wp.init()
wp.config.enable_backward = False
dev = "cuda:0"

@wp.kernel
def add(counters: wp.array2d(dtype=wp.int64), spread: int, adds: int):
    r, c = wp.tid()
    slot = (r * 7 + c) % spread
    for k in range(adds):
        wp.atomic_add(counters, slot, k, wp.int64(r + 1))

@wp.kernel
def noop(counters: wp.array2d(dtype=wp.int64), spread: int, adds: int):
    r, _c = wp.tid()
    if r < 0:
        counters[0, 0] = wp.int64(adds)

for kern in (noop, add):
    for spread in (1, 64, 4096):
        counters = wp.zeros((4096, 4), dtype=wp.int64, device=dev)
        for _rep in range(4):
            wp.synchronize_device(dev)
            t = time.perf_counter()
            wp.launch(kern, dim=(2160, 1920), inputs=[counters, spread, 3], device=dev)
            wp.synchronize_device(dev)
            ms = (time.perf_counter() - t) * 1e3
        print(f"{kern.key} spread={spread}: {ms:.3f} ms for 4.1M threads x 3 adds", flush=True)

scene = builtin_scene("smoke", 256)
views = make_views(Camera(position=(0.0, 0.4, 3.2), width=1920, height=1080), "stereo")
far = make_views(Camera(position=(0.0, 0.4, 3.2), look_at=(0.0, 0.4, 10.0), width=1920, height=1080), "stereo")
for name, vs in (("facing", views), ("looking away", far)):
    for v, lsamp in ((1, 1), (100, 48), (360, 96)):
        row = measure(DSSRM(DSSRMConfig(samples=v, light_samples=lsamp, light_grid=128), dev), scene, vs, 5)
        print(f"{name} DSSRM:{v}:{lsamp} march {row['march_ms']:.2f} ms, density samples {row['density_samples']:,}",
              flush=True)
