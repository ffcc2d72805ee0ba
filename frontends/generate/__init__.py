"""Generated sequences: scenes as meshes, a simulated LiDAR or RGB-D camera with realistic noise,
trajectories with loops, written in the real KITTI / TUM on-disk layouts with a ground-truth mesh.

Entry points: :func:`generate_lidar_sequence`, :func:`generate_rgbd_sequence`, and the CLI
``python -m frontends.generate {lidar,rgbd} OUT ...``.
"""

from frontends.generate.camera import RgbdCameraConfig
from frontends.generate.lidar import LidarConfig
from frontends.generate.sequences import generate_lidar_sequence, generate_rgbd_sequence
from frontends.generate.writers import INTRINSICS_FILE, read_intrinsics

__all__ = [
    "INTRINSICS_FILE",
    "LidarConfig",
    "RgbdCameraConfig",
    "generate_lidar_sequence",
    "generate_rgbd_sequence",
    "read_intrinsics",
]
