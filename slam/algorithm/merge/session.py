"""A session: what a run keeps, besides its submaps' latents, so that a later merge can join it to
other runs without the raw data (docs/design.md §4).

* the pose graph: every anchor's final estimate ``T_W_A``, the odometry factors between
  consecutive anchors and the loop factors the graph kept, each with the 6x6 covariance
  (``[rot, trans]``) of the noise it entered the graph with;
* every frame's anchor and pose relative to it (``T_A_S``) and its timestamp, so a merge can
  write every frame's pose after the anchors moved;
* each submap's place descriptor (:mod:`slam.algorithm.loops.place`);
* the up directions measured on anchor scans (:mod:`slam.algorithm.graph.gravity`), so that a merge
  keeps the gravity factors (optional: absent in runs without them and in older files);
* the sensor setup (JSON: ``sensor``, ``dataset``, ..., and ``session_id``, unique to the run;
  a merge refuses a session given twice) and the fixed map from the loader's frames to the
  dataset's own (``dataset_mirror``), so merged trajectories are written in the dataset's frames.

:meth:`SessionRecord.to_arrays` / :meth:`SessionRecord.from_arrays` turn it into named numpy arrays
and a JSON-able header; :mod:`mapping.map_io` stores them opaquely in the map file. Anchor poses
and factors stay float64 (the graph a merge optimises is the run's own); a frame's pose relative to
its anchor is a float32 unit quaternion and translation (``frame_pose_A_S``: ``[qx, qy, qz, qw,
tx, ty, tz]``; rounding moves a frame by about 1e-7 of its distance from the anchor and turns it
by about 1e-7 rad, far below what a run measures); covariances are float32 and descriptor
positions float16 (they only seed a verification).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from mapping.map_schema import Spec
from slam.algorithm.frame_track import frame_poses
from slam.algorithm.graph.gravity import UpMeasurement
from slam.algorithm.loops.place import PlaceDescriptor
from slam.algorithm.merge.session_checks import check_session

SESSION_ARRAYS: dict[str, Spec] = {
    "node_ids": Spec("K", (), "iu"),
    "T_W_A": Spec("K", (4, 4)),
    "frame_submap": Spec("F", (), "iu"),
    "frame_pose_A_S": Spec("F", (7,)),
    "timestamps": Spec("F", ()),
    "dataset_mirror": Spec(None, (4, 4)),
    "descriptor_ids": Spec("D", (), "iu"),
    "descriptor_planar": Spec("D", (), "b"),
    "descriptor_offsets": Spec("D+1", (), "iu"),
    "descriptor_positions": Spec("M", (3,)),
    "descriptor_bits": Spec("M", (32,), "u"),
    "up_ids": Spec("U", (), "iu", required=False),
    "up_A": Spec("U", (3,), required=False),
    "up_information": Spec("U", (3, 3), required=False),
    **{
        f"{kind}_{name}": spec
        for kind, group in (("odometry", "E"), ("loop", "L"))
        for name, spec in (
            ("ij", Spec(group, (2,), "iu")),
            ("T", Spec(group, (4, 4))),
            ("cov", Spec(group, (6, 6))),
        )
    },
}
"""The session section's arrays as :func:`mapping.map_io.read_map_file` checks them before
reading any (``K`` anchors, ``F`` frames, ``D`` descriptors of ``M`` keypoints, ``U`` up
directions, ``E`` odometry and ``L`` loop factors)."""


def pack_relative_poses(T: np.ndarray) -> np.ndarray:
    """(N, 7) float32 ``[qx, qy, qz, qw, tx, ty, tz]`` of (N, 4, 4) rigid transforms (qw >= 0)."""
    T = np.asarray(T, np.float64).reshape(-1, 4, 4)
    if len(T) == 0:
        return np.zeros((0, 7), np.float32)
    q = Rotation.from_matrix(T[:, :3, :3]).as_quat()
    q *= np.where(q[:, 3:] < 0, -1.0, 1.0)
    return np.hstack([q, T[:, :3, 3]]).astype(np.float32)


def unpack_relative_poses(packed: np.ndarray) -> np.ndarray:
    """(N, 4, 4) float64 transforms of :func:`pack_relative_poses` rows (quaternions normalised)."""
    packed = np.asarray(packed, np.float64)
    if packed.ndim != 2 or packed.shape[1] != 7:
        raise ValueError("session frame poses must be (N, 7) quaternion and translation rows")
    T = np.tile(np.eye(4), (len(packed), 1, 1))
    if len(packed):
        norms = np.linalg.norm(packed[:, :4], axis=1)
        if not np.all(np.isfinite(packed)) or np.any(norms < 0.5):
            raise ValueError("session frame poses hold invalid quaternions")
        T[:, :3, :3] = Rotation.from_quat(packed[:, :4]).as_matrix()
        T[:, :3, 3] = packed[:, 4:]
    return T


@dataclass
class Edge:
    """A factor between anchors ``i`` and ``j``: measurement ``T_Ai_Aj`` and 6x6 covariance."""

    i: int
    j: int
    T_Ai_Aj: np.ndarray
    covariance: np.ndarray


@dataclass
class SessionRecord:
    """One run's pose graph, frames and descriptors (see the module docstring).

    Attributes:
        setup: sensor setup and provenance (``sensor``, ``dataset``, ``sequence``, ...).
        node_ids: (K,) anchor ids in graph order (submap ids).
        T_W_A: (K, 4, 4) final anchor estimates.
        odometry: odometry factors (consecutive anchors of one run).
        loops: loop factors kept by the graph.
        frame_submap: (N,) anchor id of every frame.
        frame_T_A_S: (N, 4, 4) every frame's pose in its anchor frame.
        timestamps: (N,) seconds.
        descriptors: ``{anchor id: PlaceDescriptor}``.
        dataset_mirror: 4x4 map of the loader's frames to the dataset's (``M P M``).
        parts: for a merged run, ``[{"name", "first_row", "rows"}]`` of the runs it joined.
        up: ``{anchor id: UpMeasurement}`` of the anchors with a gravity factor.
    """

    setup: dict
    node_ids: np.ndarray
    T_W_A: np.ndarray
    odometry: list[Edge]
    loops: list[Edge]
    frame_submap: np.ndarray
    frame_T_A_S: np.ndarray
    timestamps: np.ndarray
    descriptors: dict[int, PlaceDescriptor]
    dataset_mirror: np.ndarray = field(default_factory=lambda: np.eye(4))
    parts: list[dict] = field(default_factory=list)
    up: dict[int, UpMeasurement] = field(default_factory=dict)

    @property
    def sensor(self) -> str:
        return str(self.setup.get("sensor", ""))

    @property
    def session_id(self) -> str:
        """The run's own id (``setup["session_id"]``, written since runs have one), else a
        fingerprint of its contents (older files)."""
        return str(self.setup.get("session_id") or self.fingerprint())

    def fingerprint(self) -> str:
        """Hash of the anchors, frames and timestamps: equal for copies of one session."""
        digest = hashlib.sha256()
        for array in (self.node_ids, self.T_W_A, self.frame_submap, self.frame_T_A_S):
            digest.update(np.ascontiguousarray(array).tobytes())
        digest.update(np.ascontiguousarray(self.timestamps, np.float64).tobytes())
        return digest.hexdigest()[:32]

    def identities(self) -> set[str]:
        """Ids of this session, of the runs it joined (a merged run's parts) and its
        fingerprint: two sessions sharing one hold the same frames."""
        parts = {str(p["session_id"]) for p in self.parts if p.get("session_id")}
        return {self.session_id, self.fingerprint(), *parts}

    def anchor_poses(self) -> dict[int, np.ndarray]:
        return {int(n): T for n, T in zip(self.node_ids, self.T_W_A, strict=True)}

    def frame_poses(self, T_W_A: dict[int, np.ndarray] | None = None) -> np.ndarray:
        """(N, 4, 4) frame poses under anchor poses ``T_W_A`` (default: the stored ones), placed
        as the run placed them (:func:`~slam.algorithm.frame_track.frame_poses`; a run with
        ``pose_graph.frames_follow_next_anchor`` off says so in its setup)."""
        anchors = self.anchor_poses() if T_W_A is None else T_W_A
        successors = (
            {e.i: (e.j, e.T_Ai_Aj) for e in self.odometry}
            if self.setup.get("frames_follow_next_anchor", True)
            else {}
        )
        return frame_poses(self.frame_submap, self.frame_T_A_S, anchors, successors)

    def to_dataset_frame(self, poses: np.ndarray) -> np.ndarray:
        M = self.dataset_mirror
        return M @ np.asarray(poses) @ M

    # --- serialisation ------------------------------------------------------------------------

    def to_arrays(self) -> tuple[dict, dict[str, np.ndarray]]:
        """``(header, arrays)`` for :func:`mapping.map_io.save_map`."""

        def edges(items: list[Edge]) -> dict[str, np.ndarray]:
            return {
                "ij": np.array([[e.i, e.j] for e in items], np.int64).reshape(-1, 2),
                "T": np.array([e.T_Ai_Aj for e in items], np.float64).reshape(-1, 4, 4),
                "cov": np.array([e.covariance for e in items], np.float32).reshape(-1, 6, 6),
            }

        ids = sorted(self.descriptors)
        counts = [len(self.descriptors[i]) for i in ids]
        arrays = {
            "node_ids": np.asarray(self.node_ids, np.int64),
            "T_W_A": np.asarray(self.T_W_A, np.float64).reshape(-1, 4, 4),
            "frame_submap": np.asarray(self.frame_submap, np.int64),
            "frame_pose_A_S": pack_relative_poses(self.frame_T_A_S),
            "timestamps": np.asarray(self.timestamps, np.float64),
            "dataset_mirror": np.asarray(self.dataset_mirror, np.float64),
            "descriptor_ids": np.asarray(ids, np.int64),
            "descriptor_planar": np.array([self.descriptors[i].planar for i in ids], bool),
            "descriptor_offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
            "descriptor_positions": np.concatenate(
                [np.zeros((0, 3), np.float16)]
                + [self.descriptors[i].positions_A.astype(np.float16) for i in ids]
            ),
            "descriptor_bits": np.concatenate(
                [np.zeros((0, 32), np.uint8)] + [self.descriptors[i].bits for i in ids]
            ),
        }
        up_ids = sorted(self.up)
        arrays["up_ids"] = np.asarray(up_ids, np.int64)
        arrays["up_A"] = np.array([self.up[i].up_A for i in up_ids], np.float64).reshape(-1, 3)
        arrays["up_information"] = np.array(
            [self.up[i].information_A for i in up_ids], np.float64
        ).reshape(-1, 3, 3)
        for name, items in (("odometry", self.odometry), ("loop", self.loops)):
            for key, value in edges(items).items():
                arrays[f"{name}_{key}"] = value
        return {"setup": self.setup, "parts": self.parts}, arrays

    @classmethod
    def from_arrays(cls, header: dict, arrays: dict[str, np.ndarray]) -> SessionRecord:
        """Inverse of :meth:`to_arrays`; inconsistent arrays or header (any invariant of
        :func:`~slam.algorithm.merge.session_checks.check_session`) raise a one-line
        ``ValueError``."""
        check_session(header, arrays)
        node_ids = arrays["node_ids"].astype(np.int64)
        T_W_A = arrays["T_W_A"].astype(np.float64)
        if T_W_A.shape != (len(node_ids), 4, 4):
            raise ValueError("session anchors and their poses disagree")
        frame_submap = arrays["frame_submap"].astype(np.int64)
        frame_T_A_S = unpack_relative_poses(arrays["frame_pose_A_S"])
        if len(frame_T_A_S) != len(frame_submap) or not set(frame_submap.tolist()) <= set(
            node_ids.tolist()
        ):
            raise ValueError("session frames refer to unknown anchors")

        def edges(name: str) -> list[Edge]:
            ij, T, cov = (arrays[f"{name}_{k}"] for k in ("ij", "T", "cov"))
            if not len(ij) == len(T) == len(cov):
                raise ValueError(f"session {name} factors are inconsistent")
            return [
                Edge(int(a), int(b), t.astype(np.float64), c.astype(np.float64))
                for (a, b), t, c in zip(ij, T, cov, strict=True)
            ]

        ids = arrays["descriptor_ids"]
        offsets = arrays["descriptor_offsets"]
        if offsets.shape != (len(ids) + 1,) or offsets[-1] != len(arrays["descriptor_bits"]):
            raise ValueError("session descriptor offsets disagree with the descriptors")
        descriptors = {
            int(n): PlaceDescriptor(
                arrays["descriptor_positions"][a:b].astype(np.float32),
                arrays["descriptor_bits"][a:b].astype(np.uint8),
                bool(planar),
            )
            for n, a, b, planar in zip(
                ids, offsets[:-1], offsets[1:], arrays["descriptor_planar"], strict=True
            )
        }
        up_ids = arrays.get("up_ids", np.zeros(0, np.int64))
        up_A = arrays.get("up_A", np.zeros((0, 3)))
        up_information = arrays.get("up_information", np.zeros((0, 3, 3)))
        if not len(up_ids) == len(up_A) == len(up_information) or not set(up_ids.tolist()) <= set(
            node_ids.tolist()
        ):
            raise ValueError("session up directions are inconsistent")
        up = {
            int(n): UpMeasurement(u.astype(np.float64), info.astype(np.float64), 0)
            for n, u, info in zip(up_ids, up_A, up_information, strict=True)
        }
        return cls(
            setup=dict(header.get("setup", {})),
            node_ids=node_ids,
            T_W_A=T_W_A,
            odometry=edges("odometry"),
            loops=edges("loop"),
            frame_submap=frame_submap,
            frame_T_A_S=frame_T_A_S,
            timestamps=arrays["timestamps"].astype(np.float64),
            descriptors=descriptors,
            dataset_mirror=arrays["dataset_mirror"].astype(np.float64),
            parts=list(header.get("parts", [])),
            up=up,
        )


def session_from_pipeline(
    pipeline, setup: dict, dataset_mirror: np.ndarray | None
) -> SessionRecord:
    """The session of a finished :class:`~slam.algorithm.pipeline.SlamPipeline`."""
    graph = pipeline.graph
    poses = graph.poses()
    node_ids = np.array(graph.node_ids, dtype=np.int64)
    odometry = [Edge(i, j, T, cov) for i, j, T, cov in graph.odometry_edges()]
    loops = [Edge(e.i, e.j, e.T_Ai_Aj, graph.loop_covariance(e)) for e in graph.loops if e.inlier]
    frame_submap, frame_T_A_S = pipeline.frames.anchors()
    detector = pipeline.loop_detector
    descriptors = {} if detector is None else dict(detector.descriptors)
    setup = {
        **setup,
        "frames_follow_next_anchor": pipeline.cfg.pose_graph.frames_follow_next_anchor,
    }
    return SessionRecord(
        setup=setup,
        node_ids=node_ids,
        T_W_A=np.array([poses[int(n)] for n in node_ids]).reshape(-1, 4, 4),
        odometry=odometry,
        loops=loops,
        frame_submap=frame_submap,
        frame_T_A_S=frame_T_A_S,
        timestamps=pipeline.frames.timestamps(),
        descriptors=descriptors,
        dataset_mirror=np.eye(4) if dataset_mirror is None else np.asarray(dataset_mirror),
        up=dict(graph.up_measurements),
    )
