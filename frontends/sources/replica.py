"""Replica scenes in the NICE-SLAM layout.

Layout::

    root/cam_params.json                  {"camera": {w, h, fx, fy, cx, cy, scale}} (optional)
    root/<scene>/results/frameNNNNNN.jpg  colour
    root/<scene>/results/depthNNNNNN.png  uint16 depth / scale (6553.5) = metres
    root/<scene>/traj.txt                 16 values a row: camera-to-world of frame NNNNNN = row N
    root/<scene>_mesh.ply                 optional ground-truth mesh

Frame numbers index the trajectory rows, so a folder holding only some of the frames (with the
full ``traj.txt``) is fine; a frame without a trajectory row is an error. Replica has no
timestamps: a frame's timestamp is its frame number.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from frontends.frame import Intrinsics
from frontends.sources._io import (
    DepthOptions,
    RgbdFrames,
    RgbdSource,
    fail,
    frame_number,
    load_table,
    require_dir,
)

REPLICA_INTRINSICS = Intrinsics(fx=600.0, fy=600.0, cx=599.5, cy=339.5, width=1200, height=680)
"""NICE-SLAM's Replica camera (as in its cam_params.json)."""
REPLICA_DEPTH_SCALE = 6553.5


def read_cam_params(path: Path) -> tuple[Intrinsics, float]:
    """NICE-SLAM ``cam_params.json`` -> (intrinsics, depth scale)."""
    try:
        camera = json.loads(path.read_text())["camera"]
        intrinsics = Intrinsics(
            fx=float(camera["fx"]),
            fy=float(camera["fy"]),
            cx=float(camera["cx"]),
            cy=float(camera["cy"]),
            width=int(camera["w"]),
            height=int(camera["h"]),
        )
        scale = float(camera.get("scale", REPLICA_DEPTH_SCALE))
    except (ValueError, KeyError, TypeError) as err:
        raise fail(
            path,
            f"malformed camera parameters ({type(err).__name__}: {err})",
            "expected {'camera': {w, h, fx, fy, cx, cy, scale}}",
        ) from None
    if intrinsics.fx <= 0 or intrinsics.fy <= 0 or scale <= 0:
        raise fail(path, "fx, fy and scale must be positive", "fix the camera parameters")
    return intrinsics, scale


class ReplicaSource(RgbdSource):
    """One Replica scene (e.g. ``office0``) in the NICE-SLAM layout.

    Args:
        root: folder holding ``<scene>/`` (and ``cam_params.json``, ``<scene>_mesh.ply``).
        sequence: scene name, e.g. ``office0``.
        frames: optional slice of frames.
        depth_options: how depth is lifted to points (default max depth 10 m).
    """

    def __init__(
        self,
        root: str | Path,
        sequence: str,
        frames: slice | None = None,
        *,
        depth_options: DepthOptions | dict | None = None,
    ) -> None:
        root = Path(root).expanduser()
        super().__init__(f"replica-{sequence}", frames, depth_options)
        self.root = root
        self.scene = sequence
        require_dir(root, "the Replica root holding <scene>/ and cam_params.json")
        scene_dir = require_dir(root / sequence, f"the scene folder {sequence}/")
        results = require_dir(scene_dir / "results", "frameNNNNNN.jpg and depthNNNNNN.png")

        params = next(
            (p for p in (root / "cam_params.json", scene_dir / "cam_params.json") if p.is_file()),
            None,
        )
        if params is None:
            self.intrinsics, self.depth_scale = REPLICA_INTRINSICS, REPLICA_DEPTH_SCALE
        else:
            self.intrinsics, self.depth_scale = read_cam_params(params)

        depth = sorted(results.glob("depth*.png"))
        color = sorted(results.glob("frame*.jpg")) or sorted(results.glob("frame*.png"))
        if not depth:
            raise fail(results, "no depthNNNNNN.png images", "extract the scene here")
        depth_numbers = [frame_number(p, r"depth(\d+)\.png") for p in depth]
        color_numbers = [frame_number(p, r"frame(\d+)\.(?:jpg|png)") for p in color]
        if depth_numbers != color_numbers:
            unpaired = sorted(set(depth_numbers) ^ set(color_numbers))
            raise fail(
                results,
                f"{len(color)} colour and {len(depth)} depth images; unpaired frame numbers "
                f"{unpaired[:5]}",
                "every frameNNNNNN.jpg needs its depthNNNNNN.png",
            )
        traj_file = scene_dir / "traj.txt"
        table = load_table(traj_file, 16, "16 values a row, camera-to-world")
        if max(depth_numbers) >= len(table):
            raise fail(
                traj_file,
                f"{len(table)} poses but frame number {max(depth_numbers)} exists",
                "use the traj.txt of this scene",
            )
        numbers = np.asarray(depth_numbers)
        gt = table.reshape(-1, 4, 4)[numbers]
        if not np.all(np.isfinite(gt)):
            raise fail(traj_file, "non-finite poses", "use the traj.txt of this scene")
        self._set_frames(RgbdFrames(numbers.astype(np.float64), color, depth), gt)

    @property
    def gt_mesh_path(self) -> Path | None:
        for path in (self.root / f"{self.scene}_mesh.ply", self.root / self.scene / "mesh.ply"):
            if path.is_file():
                return path
        return None
