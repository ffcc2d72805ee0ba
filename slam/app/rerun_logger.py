"""A :class:`~slam.algorithm.viz.Logger` that records a run with Rerun (rerun-sdk 0.41).

Entities follow the frame tree (all in the world frame ``world``)::

    world                          ViewCoordinates (static)
    world/scan                     Points3D, downsampled scan coloured by height (or its colours)
    world/sensor                   Transform3D T_W_S per frame (+ static axes)
    world/sensor/camera            Pinhole of the colour image (static; RGB-D only)
    world/sensor/camera/rgb        EncodedImage (JPEG)
    world/sensor/depth_camera      Pinhole of the (smaller) depth image (static; RGB-D only)
    world/sensor/depth_camera/depth  EncodedDepthImage (16-bit PNG, millimetres) or DepthImage
    world/trajectory/{odometry,optimized,gt}   LineStrips3D, the whole polyline
    world/loop_closures            LineStrips3D, accepted loop edges
    world/loop_closures_rejected   LineStrips3D, rejected candidates
    world/map/voxels               Points3D, voxel centres coloured by weight
    world/map/mesh                 Mesh3D
    world/stored_map/mesh          Mesh3D, static: the map a ``--map`` run continues
    world/stored_map/anchoring     LineStrips3D, live anchor to the stored submaps holding it
    metrics/{timing,error,counts}/<name>   Scalars

Timelines: ``frame`` (sequence) and ``sensor_time`` (a duration, or a timestamp when the source
gives epoch seconds). A recording uses its own :class:`rerun.RecordingStream`, so several can be
written by one process.

Size and time budget: scans and voxel maps are randomly subsampled (own RNG, the pipeline's random
state is never touched), images are shrunk and compressed, and a growing trajectory is re-logged
only now and then (:mod:`slam.app.rerun_trajectories`). The rows of the scan, sensor pose, images,
scalars and trajectories are held back and sent as columns (:mod:`slam.app.rerun_columns`): one
call per entity every few frames instead of one per entity and frame.
"""

from __future__ import annotations

import contextlib
import logging
import math
from pathlib import Path

import numpy as np
import trimesh

from common.geometry import transform_points
from frontends.frame import Intrinsics
from slam.algorithm.viz import Logger, Segments
from slam.app.blueprint import CAMERA_ENTITY, DEPTH_ENTITY, default_blueprint
from slam.app.mesh_decimation import decimate_mesh, display_mesh
from slam.app.recording_summary import summarize_recording
from slam.app.rerun_columns import ColumnBuffer
from slam.app.rerun_flush import FLUSH_TIMEOUT_S, flush_recording
from slam.app.rerun_images import colormap, encode_depth, encode_rgb
from slam.app.rerun_sinks import open_recording
from slam.app.rerun_trajectories import TrajectoryThrottle
from slam.app.web_viewer import check_serve_ports

log = logging.getLogger(__name__)

__all__ = ["RerunLogger", "decimate_mesh", "metric_entity", "summarize_recording"]

TRAJECTORY_COLORS = {
    "gt": (150, 150, 150),
    "odometry": (230, 120, 30),
    "optimized": (40, 160, 250),
}
ACCEPTED_LOOP_COLOR = (40, 220, 80)
REJECTED_LOOP_COLOR = (230, 40, 40)
MAP_ANCHORING_COLOR = (250, 190, 30)
UP_AXES = {"+z": 2, "+y": 1, "-y": 1}
EPOCH_THRESHOLD_S = 1e8
APPLICATION_ID = "neural-remap-slam"
"""Rerun application id (recordings with the same id share blueprints)."""
MAP_MAX_VOXELS = 20_000
"""Voxel centres are randomly subsampled to at most this many."""
MESH_MAX_FACES = 60_000
"""Meshes with more faces are decimated by vertex clustering (display only)."""
IMAGE_MAX_WIDTH = 320
"""Colour images wider than this are shrunk by the smallest integer factor that fits before
encoding (the pinhole is scaled to match)."""
DEPTH_MAX_WIDTH = 160
"""The same for depth images, which have their own pinhole entity (noisy depth compresses
poorly: at 160 px wide a frame is ~20 kB as 16-bit PNG)."""
JPEG_QUALITY = 80
"""JPEG quality of the colour images."""
TRAJECTORY_MOVE_M = 1e-3
"""A trajectory whose already-logged part moved by more than this (an optimisation) is re-logged
at once."""


def metric_entity(name: str) -> str:
    """Entity path of a scalar, grouped by the ``_``-separated words of its name: ``timing``
    (a word ``ms``, ``s`` or ``time``), ``error`` (``ate``, ``rpe``, ``error``, ``err``), else
    ``counts``. E.g. ``odometry_ms`` -> ``metrics/timing/odometry_ms``."""
    words = set(name.lower().split("_"))
    if words & {"ms", "s", "time", "seconds"}:
        group = "timing"
    elif words & {"ate", "rpe", "error", "err"}:
        group = "error"
    else:
        group = "counts"
    return f"metrics/{group}/{name}"


class RerunLogger(Logger):
    """Records a run to an ``.rrd`` file, a spawned viewer and/or a running viewer.

    Args:
        rrd_path: write the recording to this file (parent folders are created).
        spawn: start a local viewer and stream to it.
        connect_url: stream to a running viewer, e.g. ``rerun+http://127.0.0.1:9876/proxy``.
        serve_port: host a gRPC server on this port (``rr.GrpcServerSink``, buffering the whole
            recording for late viewers) and Rerun's web viewer on ``web_port`` over HTTP, both
            bound to ``serve_bind_ip``; ``viewer_url`` is the page to open.
        scan_max_points: scans are randomly subsampled to at most this many points.
        voxel_size_m: drawn radius of a voxel centre is half of this (UI points when None).
        up_axis: ``+z`` (LiDAR, KITTI), ``+y`` or ``-y``; sets the view and the height colouring.
        trajectory_relog_points: a growing trajectory of N poses is re-logged at most every
            ``ceil(N / trajectory_relog_points)`` frames; the newest pending polyline is logged
            on :meth:`close`.
        flush_timeout_s: how long :meth:`close` waits for the recording to be written or sent.
    """

    def __init__(
        self,
        *,
        rrd_path: Path | str | None = None,
        spawn: bool = False,
        connect_url: str | None = None,
        serve_port: int | None = None,
        web_port: int = 9090,
        serve_bind_ip: str = "127.0.0.1",
        scan_max_points: int = 3000,
        voxel_size_m: float | None = None,
        up_axis: str = "+z",
        trajectory_relog_points: int = 500,
        flush_timeout_s: float = FLUSH_TIMEOUT_S,
    ) -> None:
        import rerun as rr

        if rrd_path is None and not spawn and connect_url is None and serve_port is None:
            raise ValueError(
                "RerunLogger needs a sink: pass rrd_path, spawn=True, connect_url or serve_port"
            )
        if up_axis not in UP_AXES:
            raise ValueError(f"up_axis must be one of {sorted(UP_AXES)}, got {up_axis!r}")
        if serve_port is not None:  # before any sink: Rerun would serve on beside a taken port
            check_serve_ports(serve_bind_ip, int(serve_port), int(web_port))
        self.scan_max_points = scan_max_points
        self.voxel_size_m = voxel_size_m
        self.up_axis = up_axis
        self._image_scale = 1
        self._depth_scale = 1
        self._trajectories = TrajectoryThrottle(trajectory_relog_points, TRAJECTORY_MOVE_M)
        self.rrd_path = Path(rrd_path) if rrd_path is not None else None
        self._rng = np.random.default_rng(0)
        self._frame = 0
        self._sensor_time_is_epoch: bool | None = None
        self._height_range: tuple[float, float] | None = None
        self._intrinsics: Intrinsics | None = None
        self._camera_view = False  # added on the first image
        self._metric_names: set[str] = set()
        self._closed = False
        self.flush_timeout_s = flush_timeout_s

        self.rec, self._web_viewer = open_recording(
            APPLICATION_ID,
            self.rrd_path,
            spawn,
            connect_url,
            serve_port,
            web_port,
            serve_bind_ip,
            default_blueprint(self._camera_view),
        )
        self.viewer_url = self._web_viewer.url if self._web_viewer is not None else None
        live = spawn or connect_url is not None or serve_port is not None  # a viewer watches
        self._columns = ColumnBuffer(self.rec, live)

        view = {
            "+z": rr.ViewCoordinates.RIGHT_HAND_Z_UP,
            "+y": rr.ViewCoordinates.RIGHT_HAND_Y_UP,
            "-y": rr.ViewCoordinates.RIGHT_HAND_Y_DOWN,
        }[up_axis]
        self.rec.log("world", view, static=True)
        self.rec.log("world/sensor", rr.TransformAxes3D(0.5), static=True)
        for name in ("turbo", "viridis"):  # import matplotlib before the run, not in its first map
            colormap(name, np.zeros(0))

    # -- time ---------------------------------------------------------------------------------

    def set_time(self, frame_index: int, timestamp_s: float) -> None:
        self._frame = int(frame_index)
        self.rec.set_time("frame", sequence=self._frame)
        if self._sensor_time_is_epoch is None:
            self._sensor_time_is_epoch = float(timestamp_s) > EPOCH_THRESHOLD_S
            self._columns.sensor_time_is_epoch = self._sensor_time_is_epoch
        if self._sensor_time_is_epoch:
            self.rec.set_time("sensor_time", timestamp=float(timestamp_s))
        else:
            self.rec.set_time("sensor_time", duration=float(timestamp_s))
        self._columns.set_time(self._frame, float(timestamp_s))

    # -- per frame ----------------------------------------------------------------------------

    def log_scan(
        self,
        points_W: np.ndarray,
        colors: np.ndarray | None = None,
        T_W_S: np.ndarray | None = None,
    ) -> None:
        import rerun as rr

        points_W = np.asarray(points_W)
        keep = self._subsample(len(points_W), self.scan_max_points)
        points = points_W[keep]
        if T_W_S is not None:  # only the points shown are placed
            points = transform_points(T_W_S, points)
        points = points.astype(np.float32)
        if colors is not None and len(colors) == len(points_W):
            point_colors = np.asarray(colors)[keep]
            if point_colors.dtype != np.uint8:
                point_colors = np.clip(point_colors * 255.0, 0, 255).astype(np.uint8)
        else:
            point_colors = self._height_colors(points)
        self._columns.add(
            "world/scan",
            rr.Points3D,
            {"positions": points, "colors": point_colors},
            radii=rr.Radius.ui_points(1.5),
        )

    def log_sensor(
        self,
        T_W_S: np.ndarray,
        intrinsics: Intrinsics | None = None,
        rgb: np.ndarray | None = None,
        depth_m: np.ndarray | None = None,
    ) -> None:
        import rerun as rr

        T_W_S = np.asarray(T_W_S, dtype=np.float64)
        self._columns.add(
            "world/sensor", rr.Transform3D, translation=T_W_S[:3, 3], mat3x3=T_W_S[:3, :3]
        )
        if intrinsics is None:
            return
        if intrinsics != self._intrinsics:
            self._intrinsics = intrinsics
            self._image_scale = self._log_pinhole(CAMERA_ENTITY, intrinsics, IMAGE_MAX_WIDTH)
            self._depth_scale = self._log_pinhole(DEPTH_ENTITY, intrinsics, DEPTH_MAX_WIDTH)
        if (rgb is not None or depth_m is not None) and not self._camera_view:
            self._camera_view = True
            self.rec.send_blueprint(default_blueprint(with_camera=True))
        if rgb is not None:
            jpeg = encode_rgb(rgb, self._image_scale, JPEG_QUALITY)
            if isinstance(jpeg, bytes):
                self._columns.add(
                    f"{CAMERA_ENTITY}/rgb", rr.EncodedImage, blob=jpeg, media_type="image/jpeg"
                )
            else:  # encoding failed: the shrunk BGR pixels
                self.rec.log(f"{CAMERA_ENTITY}/rgb", rr.Image(jpeg, color_model="BGR"))
        if depth_m is not None:
            png = encode_depth(depth_m, self._depth_scale)
            if isinstance(png, bytes):
                self._columns.add(
                    f"{DEPTH_ENTITY}/depth",
                    rr.EncodedDepthImage,
                    blob=png,
                    media_type="image/png",
                    meter=1000.0,
                )
            else:  # encoding failed: float32 metres
                self.rec.log(f"{DEPTH_ENTITY}/depth", rr.DepthImage(png, meter=1.0))

    def _log_pinhole(self, entity: str, intrinsics: Intrinsics, max_width: int) -> int:
        """Static pinhole of ``intrinsics`` shrunk to at most ``max_width``; returns the factor."""
        import rerun as rr

        scale = max(1, math.ceil(intrinsics.width / max_width))
        K = intrinsics.K.copy()
        K[:2, :2] /= scale
        K[:2, 2] = (K[:2, 2] + 0.5) / scale - 0.5
        self.rec.log(
            entity,
            rr.Pinhole(
                image_from_camera=K,
                resolution=[intrinsics.width // scale, intrinsics.height // scale],
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=0.3,
            ),
            static=True,
        )
        return scale

    # -- trajectories and loops ---------------------------------------------------------------

    def log_trajectory(self, name: str, positions_W: np.ndarray) -> None:
        positions = np.asarray(positions_W, dtype=np.float32).reshape(-1, 3)
        if self._trajectories.due(name, positions, self._frame):
            self._log_trajectory_now(name, positions)

    def _log_trajectory_now(self, name: str, positions: np.ndarray) -> None:
        import rerun as rr

        self._columns.add(
            f"world/trajectory/{name}",
            rr.LineStrips3D,
            {"strips": [positions] if len(positions) >= 2 else []},
            colors=TRAJECTORY_COLORS.get(name, (255, 255, 255)),
            radii=rr.Radius.ui_points(2.0),
        )
        self._trajectories.logged(name, positions, self._frame)

    def log_loop_closures(self, accepted: Segments, rejected: Segments = ()) -> None:
        self._log_segments("world/loop_closures", accepted, ACCEPTED_LOOP_COLOR, 2.5)
        self._log_segments("world/loop_closures_rejected", rejected, REJECTED_LOOP_COLOR, 2.5)

    def log_map_anchoring(self, segments: Segments) -> None:
        self._log_segments("world/stored_map/anchoring", segments, MAP_ANCHORING_COLOR, 1.5)

    def _log_segments(
        self, entity: str, segments: Segments, color: tuple[int, int, int], radius: float
    ) -> None:
        import rerun as rr

        strips = [np.asarray([a, b], dtype=np.float32).reshape(2, 3) for a, b in segments]
        self.rec.log(
            entity, rr.LineStrips3D(strips, colors=[color], radii=rr.Radius.ui_points(radius))
        )

    # -- map ----------------------------------------------------------------------------------

    def log_map(
        self,
        voxel_centers_W: np.ndarray,
        voxel_values: np.ndarray,
        mesh: trimesh.Trimesh | None = None,
    ) -> None:
        import rerun as rr

        centers = np.asarray(voxel_centers_W)
        keep = self._subsample(len(centers), MAP_MAX_VOXELS)
        values = np.asarray(voxel_values, dtype=np.float64).reshape(-1)[keep]
        scaled = np.log1p(np.maximum(values, 0.0))
        top = float(scaled.max()) if len(scaled) else 1.0
        colors = colormap("viridis", scaled / top if top > 0 else scaled)
        radius = (
            0.5 * self.voxel_size_m if self.voxel_size_m is not None else rr.Radius.ui_points(2.0)
        )
        self.rec.log(
            "world/map/voxels",
            rr.Points3D(centers[keep].astype(np.float32), colors=colors, radii=radius),
        )
        if mesh is not None:
            self.log_mesh(mesh)

    def log_mesh(self, mesh: trimesh.Trimesh) -> None:
        """``mesh`` at ``world/map/mesh``, decimated to at most :data:`MESH_MAX_FACES` faces."""
        self._log_mesh("world/map/mesh", mesh, (200, 200, 210, 255))

    def log_stored_map(self, mesh_path: Path) -> None:
        """The continued map's ``mesh.ply`` at ``world/stored_map/mesh`` (static, tinted apart
        from the run's own map); a missing file is logged as a warning, not an error."""
        if not mesh_path.is_file():
            log.warning("%s not found: the continued map is not shown", mesh_path)
            return
        mesh = trimesh.load(mesh_path, force="mesh", process=False)
        mesh.visual = trimesh.visual.ColorVisuals(mesh)  # one tint, not the stored colours
        self._log_mesh("world/stored_map/mesh", mesh, (150, 170, 215, 255), static=True)

    def _log_mesh(
        self, entity: str, mesh: trimesh.Trimesh, albedo: tuple[int, ...], static: bool = False
    ) -> None:
        self.rec.log(entity, display_mesh(mesh, MESH_MAX_FACES, albedo), static=static)

    # -- metrics ------------------------------------------------------------------------------

    def log_metrics(self, **scalars: float) -> None:
        import rerun as rr

        for name, value in scalars.items():
            if value is None or not math.isfinite(float(value)):
                continue
            if name not in self._metric_names:
                self._metric_names.add(name)
                self.rec.log(metric_entity(name), rr.SeriesLines(names=[name]), static=True)
            self._columns.add(metric_entity(name), rr.Scalars, scalars=float(value))

    def flush(self) -> None:
        """Send the newest pending trajectories and every held-back row."""
        for name, positions in list(self._trajectories.pending.items()):
            self._log_trajectory_now(name, positions)
        self._columns.flush()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.flush()
        with contextlib.ExitStack() as stack:  # each step even when an earlier one failed
            if self._web_viewer is not None:
                stack.callback(self._web_viewer.close)
            what = f"the recording {self.rrd_path}" if self.rrd_path else "the recording"
            if flush_recording(self.rec, self.flush_timeout_s, what):
                # else Rerun retries a dead sink at exit; a sink that did not take the data in
                # time would block the disconnect as it blocked the flush
                self.rec.disconnect()

    def __enter__(self) -> RerunLogger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- helpers ------------------------------------------------------------------------------

    def _subsample(self, n: int, limit: int) -> np.ndarray:
        if n <= limit:
            return np.arange(n)
        return np.sort(self._rng.choice(n, limit, replace=False))

    def _height_colors(self, points: np.ndarray) -> np.ndarray:
        """Turbo colours over a height range that only ever widens (stable across frames)."""
        if len(points) == 0:
            return np.zeros((0, 3), np.uint8)
        height = points[:, UP_AXES[self.up_axis]].astype(np.float64)
        if self.up_axis == "-y":
            height = -height
        low, high = np.percentile(height, [2.0, 98.0])
        if self._height_range is not None:
            low, high = min(low, self._height_range[0]), max(high, self._height_range[1])
        self._height_range = (float(low), float(high))
        span = max(high - low, 1e-6)
        return colormap("turbo", (height - low) / span)
