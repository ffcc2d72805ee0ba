"""Files of a merged run folder besides those a run writes: ``sessions.csv``, ``loops.csv`` with
intra- and inter-session loops, and the Rerun recording of the merge."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from slam.algorithm.merge.merge import MergeResult
from slam.run_folder.outputs import LOOP_FIELDS, loop_fields

LOOP_COLUMNS = (
    "kind",
    "reference_session",
    "query_session",
    "reference_submap",
    "query_submap",
    *LOOP_FIELDS,
)

SESSION_COLOURS = np.array(
    [[230, 80, 60], [60, 140, 230], [80, 190, 90], [230, 180, 40], [170, 90, 210], [40, 190, 190]],
    dtype=np.uint8,
)


def sessions_csv(names: list[str], rows: list[int]) -> str:
    """One line per session: index, run folder, first row in the pose files, rows."""
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(("session", "run_folder", "first_row", "rows"))
    first = 0
    for k, (name, n) in enumerate(zip(names, rows, strict=True)):
        writer.writerow((k, name, first, n))
        first += n
    return buffer.getvalue()


def merge_loops_csv(result: MergeResult) -> str:
    """Stored (intra-session) loop factors and every inter-session candidate, global submap ids."""
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(LOOP_COLUMNS)
    for k, i, j in result.intra_loops:
        T = np.linalg.inv(result.T_W_A[i]) @ result.T_W_A[j]
        writer.writerow(["intra", k, k, i, j, *loop_fields(True, "stored", True, T, {})])
    for c in result.loops:
        fields = loop_fields(c.accepted, c.reason, c.graph_inlier, c.T_Ai_Aj, c.scores)
        writer.writerow(["inter", c.session_i, c.session_j, c.i, c.j, *fields])
    return buffer.getvalue()


def _mesh(rec, path: str, mesh, colour: np.ndarray, T: np.ndarray | None = None) -> None:
    import rerun as rr

    if mesh is None or len(mesh.faces) == 0:
        return
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if T is not None:
        vertices = vertices @ T[:3, :3].T + T[:3, 3]
    rec.log(
        path,
        rr.Mesh3D(
            vertex_positions=vertices.astype(np.float32),
            triangle_indices=np.asarray(mesh.faces, dtype=np.uint32),
            vertex_colors=np.tile(colour, (len(vertices), 1)),
        ),
        static=True,
    )


def write_recording(
    path: Path, result: MergeResult, names: list[str], before_meshes: list, after_mesh
) -> None:
    """Rerun recording: each session's trajectory and mesh before (its own run, placed by the
    initial alignment) and after the merge, coloured per session, and the inter-session loops."""
    import rerun as rr

    from slam.app.rerun_flush import FLUSH_TIMEOUT_S, flush_recording

    rec = rr.RecordingStream("neural-remap-slam-merge")
    rec.save(str(path))
    for k, name in enumerate(names):
        colour = SESSION_COLOURS[k % len(SESSION_COLOURS)]
        positions = result.frame_poses[k][:, :3, 3]
        rec.log(
            f"world/after/session_{k}/trajectory",
            rr.LineStrips3D([positions], colors=[colour], labels=[name]),
            static=True,
        )
        _mesh(rec, f"world/before/session_{k}/mesh", before_meshes[k], colour, result.T_W0_Wk[k])
    _mesh(rec, "world/after/mesh", after_mesh, np.array([200, 200, 200], np.uint8))
    for status, keep in (("accepted", True), ("rejected", False)):
        segments = [
            [result.T_W_A[c.i][:3, 3], result.T_W_A[c.j][:3, 3]]
            for c in result.loops
            if (c.accepted and bool(c.graph_inlier)) == keep
        ]
        if segments:
            colour = [0, 220, 0] if keep else [220, 0, 0]
            rec.log(
                f"world/inter_session_loops/{status}",
                rr.LineStrips3D(segments, colors=[colour]),
                static=True,
            )
    flush_recording(rec, FLUSH_TIMEOUT_S, f"the merged recording {path}")
