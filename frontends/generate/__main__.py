"""Write a generated sequence to a folder.

    python -m frontends.generate lidar OUT_ROOT --frames 186                  # loop, KITTI layout
    python -m frontends.generate lidar OUT_ROOT --trajectory kitti --frames 400 \\
        --kitti-poses /data/kitti/poses/00.txt --kitti-calib /data/kitti/sequences/00/calib.txt
    python -m frontends.generate rgbd OUT_FOLDER --frames 300                # room, TUM layout
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from frontends.errors import DatasetError
from frontends.generate import generate_lidar_sequence, generate_rgbd_sequence


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m frontends.generate",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="kind", required=True)
    lidar = sub.add_parser("lidar", help="LiDAR street sequence in KITTI odometry layout")
    lidar.add_argument(
        "root", type=Path, help="KITTI root to write sequences/NN and poses/NN.txt into"
    )
    lidar.add_argument("--sequence", default="00", help="sequence name (default 00)")
    lidar.add_argument("--trajectory", choices=["loop", "kitti"], default="loop")
    lidar.add_argument("--kitti-poses", type=Path, help="KITTI poses/NN.txt (trajectory kitti)")
    lidar.add_argument(
        "--kitti-calib", type=Path, help="KITTI sequences/NN/calib.txt (trajectory kitti)"
    )
    lidar.add_argument("--start", type=int, default=0, help="first KITTI frame")
    lidar.add_argument("--step", type=int, default=1, help="KITTI frame step")
    lidar.add_argument("--azimuth-steps", type=int, default=2048, help="firings per revolution")
    lidar.add_argument(
        "--terrain-relief",
        dest="terrain_relief_m",
        type=float,
        default=0.0,
        help="height (m) of hills beside the road",
    )
    lidar.set_defaults(generate=generate_lidar_sequence)
    rgbd = sub.add_parser("rgbd", help="RGB-D room sequence in TUM RGB-D layout")
    rgbd.add_argument("root", type=Path, help="sequence folder to create")
    rgbd.add_argument("--width", type=int, default=640)
    rgbd.add_argument("--height", type=int, default=480)
    rgbd.set_defaults(generate=generate_rgbd_sequence)
    for p in (lidar, rgbd):
        p.add_argument(
            "--frames", dest="num_frames", type=int, required=True, help="number of frames"
        )
        p.add_argument("--seed", type=int, default=0)
        p.add_argument("--workers", type=int, default=None, help="processes (default: up to 2)")
        p.add_argument("--overwrite", action="store_true", help="replace an existing sequence")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    t0 = time.perf_counter()
    options = vars(args)
    del options["kind"]
    try:
        out = options.pop("generate")(**options)
    except DatasetError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.num_frames} frames to {out} in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
