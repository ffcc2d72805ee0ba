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
        "--terrain-relief", type=float, default=0.0, help="height (m) of hills beside the road"
    )
    rgbd = sub.add_parser("rgbd", help="RGB-D room sequence in TUM RGB-D layout")
    rgbd.add_argument("root", type=Path, help="sequence folder to create")
    rgbd.add_argument("--width", type=int, default=640)
    rgbd.add_argument("--height", type=int, default=480)
    for p in (lidar, rgbd):
        p.add_argument("--frames", type=int, required=True, help="number of frames")
        p.add_argument("--seed", type=int, default=0)
        p.add_argument("--workers", type=int, default=None, help="processes (default: up to 2)")
        p.add_argument("--overwrite", action="store_true", help="replace an existing sequence")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    t0 = time.perf_counter()
    try:
        if args.kind == "lidar":
            out = generate_lidar_sequence(
                args.root,
                sequence=args.sequence,
                num_frames=args.frames,
                trajectory=args.trajectory,
                kitti_poses=args.kitti_poses,
                kitti_calib=args.kitti_calib,
                start=args.start,
                step=args.step,
                seed=args.seed,
                azimuth_steps=args.azimuth_steps,
                terrain_relief_m=args.terrain_relief,
                overwrite=args.overwrite,
                workers=args.workers,
            )
        else:
            out = generate_rgbd_sequence(
                args.root,
                num_frames=args.frames,
                seed=args.seed,
                width=args.width,
                height=args.height,
                overwrite=args.overwrite,
                workers=args.workers,
            )
    except DatasetError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.frames} frames to {out} in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
