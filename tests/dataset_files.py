"""Small files in the on-disk layouts of the datasets, shared by the source tests."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def real(path: str) -> Path:
    full = DATA / path
    if not full.exists():
        pytest.skip(f"real data {full} is absent")
    return full


def assert_one_line_error(exc: pytest.ExceptionInfo, *needles: str) -> None:
    message = str(exc.value)
    assert "\n" not in message
    for needle in needles:
        assert needle in message, f"{needle!r} not in {message!r}"


def random_pose(rng: np.random.Generator, step: float = 0.1) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.2, 3)).as_matrix()
    pose[:3, 3] = rng.normal(0, step, 3)
    return pose


def write_depth(path: Path, depth_m: np.ndarray, scale: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.round(depth_m * scale).astype(np.uint16))


def write_rgb(path: Path, shape=(480, 640), value: int = 128) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    image = np.full((*shape, 3), value, np.uint8)
    image[..., 0] = 10  # blue channel in OpenCV order
    assert cv2.imwrite(str(path), image)


def tum_row(stamp: float, pose: np.ndarray) -> str:
    q = Rotation.from_matrix(pose[:3, :3]).as_quat()
    return f"{stamp:.6f} " + " ".join(f"{v:.9f}" for v in (*pose[:3, 3], *q))


def make_tum(folder: Path, n: int = 4) -> np.ndarray:
    """A TUM RGB-D folder of ``n`` frames (plus a depth image without a colour partner);
    returns the ground-truth poses written to ``groundtruth.txt``."""
    rng = np.random.default_rng(2)
    rgb_lines, depth_lines, gt_lines = ["# rgb"], ["# depth"], ["# gt"]
    for i in range(n):
        t = 100.0 + i / 30
        write_rgb(folder / "rgb" / f"{t:.6f}.png")
        write_depth(folder / "depth" / f"{t + 0.004:.6f}.png", np.full((480, 640), 1.0 + i), 5000)
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t + 0.004:.6f} depth/{t + 0.004:.6f}.png")
    # Extra depth image far in time: no colour partner.
    write_depth(folder / "depth" / "200.000000.png", np.full((480, 640), 1.0), 5000)
    depth_lines.append("200.000000 depth/200.000000.png")
    poses = []
    for k in range(3 * n + 3):
        pose = random_pose(rng)
        poses.append(pose)
        gt_lines.append(tum_row(99.99 + k / 100, pose))
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (folder / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    return np.stack(poses)


# --------------------------------------------------------------------------------------- KITTI
