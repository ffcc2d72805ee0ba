"""``python -m slam.run lidar PATH --dataloader NAME`` on real files written with the real
libraries (trimesh PLY scans, ROS2 and ROS1 bags and an MCAP file with sensor_msgs/PointCloud2
written by ``rosbags``), made from the first scans of the generated street, run end to end (in
this process); the estimated poses are scored against the generated ground truth.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from frontends.errors import DatasetError
from frontends.sources import make_source
from slam.run_folder.trajectory_io import write_kitti
from tests.helpers import call_main

REPO_ROOT = Path(__file__).resolve().parents[1]
STREET = {"kind": "lidar", "num_frames": 150, "seed": 0, "azimuth_steps": 1024}
NUM_SCANS = 30
POINT_STEP = 2  # every 2nd point: a smaller file, the same geometry
START_TIME_NS = 1_700_000_000 * 10**9
PERIOD_NS = 100_000_000
TOPIC = "/velodyne_points"
ATE_BOUND_M = 0.1  # measured: 0.037 m on these 30 scans (~37 m), the same for PLY, bag and MCAP


@pytest.fixture(scope="module")
def street_scans() -> tuple[list[np.ndarray], np.ndarray]:
    """The first NUM_SCANS scans of the generated street (sensor frame) and their ground truth."""
    source = make_source("generated", frames=slice(0, NUM_SCANS), **STREET)
    scans = [np.asarray(frame.points[::POINT_STEP], dtype=np.float32) for frame in source]
    return scans, np.asarray(source.gt_poses)


def _write_ply_folder(folder: Path, scans: list[np.ndarray]) -> None:
    folder.mkdir()
    for i, points in enumerate(scans):
        trimesh.PointCloud(points).export(folder / f"{i:06d}.ply")


def _pointcloud2(typestore, points: np.ndarray, stamp_ns: int, seq: int | None = None):
    types = typestore.types
    stamp = types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    if seq is None:  # ROS2
        header = types["std_msgs/msg/Header"](stamp=stamp, frame_id="velodyne")
    else:  # ROS1 headers carry a sequence number
        header = types["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id="velodyne")
    field = types["sensor_msgs/msg/PointField"]
    fields = [field(name=n, offset=4 * k, datatype=7, count=1) for k, n in enumerate("xyz")]
    data = np.ascontiguousarray(points, dtype=np.float32).view(np.uint8).reshape(-1)
    return types["sensor_msgs/msg/PointCloud2"](
        header=header,
        height=1,
        width=len(points),
        fields=fields,
        is_bigendian=False,
        point_step=12,
        row_step=12 * len(points),
        data=data,
        is_dense=True,
    )


def _write_ros2_bag(path: Path, scans: list[np.ndarray], storage: str) -> None:
    """A ROS2 bag (sqlite3 or MCAP storage) with one PointCloud2 per scan, plus a distractor
    topic of another type."""
    pytest.importorskip("rosbags", reason='the rosbag extra: pip install -e ".[rosbag]"')
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    msgtype = "sensor_msgs/msg/PointCloud2"
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        clouds = writer.add_connection(TOPIC, msgtype, typestore=typestore)
        string = typestore.types["std_msgs/msg/String"]
        notes = writer.add_connection("/notes", "std_msgs/msg/String", typestore=typestore)
        for i, points in enumerate(scans):
            stamp = START_TIME_NS + i * PERIOD_NS
            message = _pointcloud2(typestore, points, stamp)
            writer.write(clouds, stamp, typestore.serialize_cdr(message, msgtype))
            note = typestore.serialize_cdr(string(data=f"scan {i}"), "std_msgs/msg/String")
            writer.write(notes, stamp + 1, note)


def _write_ros1_bag(path: Path, scans: list[np.ndarray]) -> None:
    """A ROS1 ``.bag`` with one PointCloud2 per scan."""
    pytest.importorskip("rosbags", reason='the rosbag extra: pip install -e ".[rosbag]"')
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS1_NOETIC)
    msgtype = "sensor_msgs/msg/PointCloud2"
    with Writer(path) as writer:
        clouds = writer.add_connection(TOPIC, msgtype, typestore=typestore)
        for i, points in enumerate(scans):
            stamp = START_TIME_NS + i * PERIOD_NS
            message = _pointcloud2(typestore, points, stamp, seq=i)
            writer.write(clouds, stamp, typestore.serialize_ros1(message, msgtype))


def _run(args: list[str], out: Path) -> dict:
    """``python -m slam.run ARGS`` (in this process) with the LiDAR config, no loop closure."""
    from slam.app.cli import main

    command = [
        *args,
        "--config",
        str(REPO_ROOT / "configs" / "lidar.yaml"),
        "--no-viz",
        "--no-progress",
        "--out",
        str(out),
        "--set",
        "loop_closure.enabled=false",
        "--set",
        "mapping.device=cpu",
        "--set",
        "output.write_map=false",
        "--set",
        "output.mesh_samples=2000",
    ]
    result = call_main(main, command)
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads((out / "metrics.json").read_text())


def _ate_against(out: Path, gt: np.ndarray) -> float:
    from slam.evaluation.metrics.trajectory import ate_rmse
    from slam.run_folder.trajectory_io import read_kitti

    return ate_rmse(read_kitti(out / "poses_slam.kitti.txt"), gt)


@pytest.mark.slow
def test_ply_folder_runs_end_to_end(tmp_path: Path, street_scans) -> None:
    scans, gt = street_scans
    folder = tmp_path / "scans"
    _write_ply_folder(folder, scans)
    write_kitti(tmp_path / "gt.txt", gt)
    metrics = _run(
        [
            "lidar",
            str(folder),
            "--dataloader",
            "generic",
            "--set",
            f"source.lidar.gt_poses={tmp_path / 'gt.txt'}",
        ],
        tmp_path / "run",
    )
    assert metrics["num_frames"] == NUM_SCANS
    assert metrics["trajectory"]["slam"]["ate_rmse_m"] < ATE_BOUND_M
    # The same number from the written trajectory against the generated ground truth.
    assert _ate_against(tmp_path / "run", gt) < ATE_BOUND_M
    # Scaled from the first scan: the resolved config holds the derived voxel sizes.
    config = (tmp_path / "run" / "config.yaml").read_text()
    assert "scale_from_first_scan: true" in config


@pytest.mark.slow
@pytest.mark.parametrize(
    ("dataloader", "storage"),
    [("rosbag", "sqlite3"), ("rosbag", "mcap"), ("mcap", "mcap"), ("rosbag", "ros1")],
)
def test_bag_runs_end_to_end(tmp_path: Path, street_scans, dataloader: str, storage: str) -> None:
    """ROS2 bags (sqlite3, MCAP storage), the standalone MCAP file, and a ROS1 bag."""
    scans, gt = street_scans
    if storage == "ros1":
        path = tmp_path / "recording.bag"
        _write_ros1_bag(path, scans)
    else:
        path = tmp_path / "recording"  # the ROS2 bag folder
        _write_ros2_bag(path, scans, storage)
    if dataloader == "mcap":
        pytest.importorskip("mcap_ros2", reason='the mcap extra: pip install -e ".[mcap]"')
        (path,) = path.glob("*.mcap")  # the standalone MCAP file inside the bag
    out = tmp_path / "run"
    metrics = _run(["lidar", str(path), "--dataloader", dataloader, "--topic", TOPIC], out)
    assert metrics["num_frames"] == NUM_SCANS
    assert "trajectory" not in metrics  # a bag carries no ground truth
    stamps = np.loadtxt(out / "poses_slam.tum.txt")[:, 0]
    np.testing.assert_allclose(stamps, (START_TIME_NS + np.arange(NUM_SCANS) * PERIOD_NS) / 1e9)
    assert _ate_against(out, gt) < ATE_BOUND_M


def test_mcap_dataloader_reads_pointcloud2(tmp_path: Path, street_scans) -> None:
    """KISS-ICP's standalone ``mcap`` dataloader on the .mcap file of a ROS2 bag."""
    pytest.importorskip("mcap_ros2", reason='the mcap extra: pip install -e ".[mcap]"')
    scans, _ = street_scans
    bag = tmp_path / "recording"
    _write_ros2_bag(bag, scans[:3], "mcap")
    (mcap_file,) = bag.glob("*.mcap")
    source = make_source("lidar", root=mcap_file, dataloader="mcap", topic=TOPIC)
    assert len(source) == 3
    frames = [source[i] for i in (0, 2, 1)]  # out of order: the source rewinds
    np.testing.assert_allclose(frames[1].points, scans[2], atol=1e-6)
    np.testing.assert_allclose(frames[2].points, scans[1], atol=1e-6)
    assert frames[1].timestamp == pytest.approx((START_TIME_NS + 2 * PERIOD_NS) / 1e9)


def test_bag_with_unknown_topic_is_one_line_error(tmp_path: Path, street_scans) -> None:
    scans, _ = street_scans
    bag = tmp_path / "recording"
    _write_ros2_bag(bag, scans[:2], "sqlite3")
    with pytest.raises(DatasetError, match="could not open it") as info:
        make_source("lidar", root=bag, dataloader="rosbag", topic="/nope")
    assert "\n" not in str(info.value) and str(bag) in str(info.value)


def test_npy_folder_and_missing_extra_hint(tmp_path: Path, street_scans) -> None:
    scans, gt = street_scans
    folder = tmp_path / "npy"
    folder.mkdir()
    for i, points in enumerate(scans[:3]):
        np.save(folder / f"{i}.npy", points)
    write_kitti(tmp_path / "gt.txt", gt[:3])
    source = make_source("lidar", root=folder, dataloader="npy", gt_poses=tmp_path / "gt.txt")
    np.testing.assert_allclose(source[1].points, scans[1], atol=1e-6)
    np.testing.assert_allclose(source.gt_poses, gt[:3])
    assert source[2].timestamp == pytest.approx(0.2)  # nominal 10 Hz without stamps
    with pytest.raises(DatasetError, match=r"pip install .*\[nuscenes\]"):
        try:
            import nuscenes  # noqa: F401
        except ImportError:
            make_source("lidar", root=folder, dataloader="nuscenes", sequence="0")
        else:
            raise DatasetError("nuscenes is installed: pip install x[nuscenes]")
