"""Write the big-data example files (issue 41) into a folder, as `volren bench bigdata` makes and caches them, and print
their paths: the issue's OpenVDB file (two balls in a 2000^3 index box, written by OpenVDB itself: needs Debian's
python3-openvdb) or a uint8 OME-Zarr pyramid of N^3 voxels (fine structure, 2x2x2 means down to 64^3), written chunk
by chunk (never a whole level in memory; 4096^3 is 64 GiB of voxels, larger than this machine's memory)."""

from __future__ import annotations

import argparse
import sys

from volren.bench.bigdata import QUICK, make_file, make_pyramid
from volren.errors import VolrenError


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("kind", choices=("two-balls", "pyramid"))
    ap.add_argument("--out", required=True, help="the folder to write into (files already there are reused)")
    ap.add_argument("--size", type=int, help="two-balls: the index box's edge (default 2000); pyramid: level 0's "
                    "edge (default 512)")
    ap.add_argument("--radius", type=int, default=100, help="two-balls: the balls' radius in voxels (default 100)")
    args = ap.parse_args()
    cfg = {**QUICK, "cache": args.out}
    try:
        if args.kind == "two-balls":
            info = make_file("two-balls", {**cfg, "two_balls": [args.size or 2000, args.radius]}, dense=False)
        else:
            info = make_pyramid({**cfg, "outofcore": args.size or 512})
    except VolrenError as exc:
        print(f"bigdata_files: {exc}", file=sys.stderr)
        return 1
    print(info["path"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
