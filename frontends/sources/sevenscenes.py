"""Microsoft 7-Scenes sequences.

Layout (one scene folder as ``root``)::

    root/seq-XX/frame-NNNNNN.color.png (or .color.jpg)
    root/seq-XX/frame-NNNNNN.depth.png    uint16 millimetres; 0 and 65535 are invalid
    root/seq-XX/frame-NNNNNN.pose.txt     4x4 camera-to-world, metres
    root/camera-intrinsics.txt            optional 3x3 K (default fx=fy=585, cx=320, cy=240)

The intrinsics are those of the depth camera. The colour camera is a different, uncalibrated
camera: ``Frame.rgb`` and the per-point colours are only approximately registered to depth (a few
pixels off, more near depth edges); use them for display and features, not for geometry.
7-Scenes has no timestamps: a frame's timestamp is its frame number / 30 (the Kinect rate).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from common.geometry import orthonormalize
from frontends.frame import Intrinsics
from frontends.sources._io import (
    DepthOptions,
    RgbdFrames,
    RgbdSource,
    fail,
    frame_number,
    load_table,
    require_dir,
    require_file,
)

log = logging.getLogger(__name__)

SEVEN_SCENES_INTRINSICS = Intrinsics(fx=585.0, fy=585.0, cx=320.0, cy=240.0, width=640, height=480)
FRAME_RATE_HZ = 30.0


def sequence_folder_name(sequence: str) -> str:
    """``"seq-01"``, ``"01"`` or ``"1"`` -> ``"seq-01"``."""
    text = str(sequence)
    if text.startswith("seq-"):
        return text
    if text.isdigit():
        return f"seq-{int(text):02d}"
    return text


class SevenScenesSource(RgbdSource):
    """One 7-Scenes sequence.

    Args:
        root: scene folder holding ``seq-XX/`` (e.g. ``.../redkitchen``).
        sequence: ``"seq-01"`` or ``"1"``.
        frames: optional slice of frames.
        depth_options: how depth is lifted to points.
    """

    depth_scale = 1000.0
    invalid_depth_values = (0, 65535)

    def __init__(
        self,
        root: str | Path,
        sequence: str,
        frames: slice | None = None,
        *,
        depth_options: DepthOptions | dict | None = None,
    ) -> None:
        root = Path(root).expanduser()
        name = sequence_folder_name(sequence)
        super().__init__(f"7scenes-{name}", frames, depth_options)
        require_dir(root, "a 7-Scenes scene folder holding seq-XX/")
        self.folder = require_dir(root / name, f"{name}/ with frame-NNNNNN.* files")
        intrinsics_file = root / "camera-intrinsics.txt"
        self.intrinsics = SEVEN_SCENES_INTRINSICS
        if intrinsics_file.is_file():
            K = load_table(intrinsics_file, 3, "a 3x3 camera matrix")
            if K.shape != (3, 3) or K[0, 0] <= 0 or K[1, 1] <= 0:
                raise fail(intrinsics_file, "not a 3x3 camera matrix with fx, fy > 0", "fix it")
            self.intrinsics = Intrinsics(
                fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=640, height=480
            )

        depth = sorted(self.folder.glob("frame-*.depth.png"))
        if not depth:
            raise fail(self.folder, "no frame-NNNNNN.depth.png files", "extract the sequence here")
        numbers = [frame_number(p, r"frame-(\d+)\.depth\.png") for p in depth]
        color: list[Path] = []
        for path, number in zip(depth, numbers, strict=True):
            stem = self.folder / f"frame-{number:06d}"
            found = next(
                (c for c in (Path(f"{stem}.color.png"), Path(f"{stem}.color.jpg")) if c.is_file()),
                None,
            )
            if found is None:
                raise fail(
                    f"{stem}.color.png", "colour image missing for " + path.name, "restore it"
                )
            color.append(found)
        pose_files = sorted(self.folder.glob("frame-*.pose.txt"))
        if len(pose_files) != len(depth):
            raise fail(
                self.folder,
                f"{len(pose_files)} pose files for {len(depth)} depth images",
                "every frame-NNNNNN.depth.png needs its frame-NNNNNN.pose.txt",
            )
        gt = np.stack(
            [
                _read_pose(require_file(self.folder / f"frame-{n:06d}.pose.txt", "a 4x4 pose"))
                for n in numbers
            ]
        )
        stamps = np.asarray([n / FRAME_RATE_HZ for n in numbers])
        self._set_frames(RgbdFrames(stamps, color, depth), gt)


def _read_pose(path: Path) -> np.ndarray:
    pose = load_table(path, 4, "a 4x4 camera-to-world matrix")
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise fail(path, "not a finite 4x4 matrix", "restore the pose file")
    if not np.allclose(pose[3], [0, 0, 0, 1], atol=1e-6):
        raise fail(path, "last row is not 0 0 0 1", "restore the pose file")
    # The KinectFusion poses are stored with ~1e-4 of non-orthogonality: project onto SO(3).
    rigid = orthonormalize(pose)
    if np.abs(rigid[:3, :3] - pose[:3, :3]).max() > 1e-2:  # also a reflection
        raise fail(path, "rotation block is not a rotation", "restore the pose file")
    return rigid
