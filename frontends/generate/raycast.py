"""First-hit raycasting against a scene mesh (Embree via embreex; trimesh's slow fallback)."""

from __future__ import annotations

import numpy as np
import trimesh


def rotate(R: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """``vectors @ R.T`` for (N, 3) vectors, as explicit element-wise sums.

    Faster than a BLAS call for a 3x3 matrix on a busy machine, and independent of the BLAS
    build, which keeps generated files byte-identical across machines.
    """
    return vectors[:, 0:1] * R[:, 0] + vectors[:, 1:2] * R[:, 1] + vectors[:, 2:3] * R[:, 2]


class Raycaster:
    """Casts batches of rays against one mesh and returns the first hit of each.

    Embree works in float32; coordinates are shifted to the mesh's bounding-box centre first so
    that precision does not degrade far from the world origin (street scenes span kilometres).
    """

    def __init__(self, mesh: trimesh.Trimesh) -> None:
        self.mesh = mesh
        self.face_normals = np.asarray(mesh.face_normals, np.float64)
        """(F, 3) unit face normals (computed once)."""
        self._offset = np.asarray(mesh.bounds, np.float64).mean(axis=0)
        try:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh
        except ImportError:  # pragma: no cover - pure-python fallback, orders of magnitude slower
            from trimesh.ray.ray_triangle import RayMeshIntersector

            self._embree = None
            self._fallback = RayMeshIntersector(mesh)
            return
        self._embree = rtcore_scene.EmbreeScene()
        TriangleMesh(
            scene=self._embree,
            vertices=(np.asarray(mesh.vertices, np.float64) - self._offset).astype(np.float32),
            indices=np.asarray(mesh.faces, np.int32),
        )

    def first_hit(
        self, origins: np.ndarray, directions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Distance along each unit direction to the first hit and the hit face.

        ``origins`` is (N, 3) or one (3,) origin for all rays. Returns ``(distance, face)``: (N,)
        float64 with ``inf`` for misses and (N,) int64 with -1 for misses.
        """
        origins = np.broadcast_to(np.asarray(origins, np.float64), directions.shape)
        if self._embree is None:  # pragma: no cover
            return self._first_hit_fallback(origins, directions)
        result = self._embree.run(
            np.ascontiguousarray(origins - self._offset, dtype=np.float32),
            np.ascontiguousarray(directions, dtype=np.float32),
            output=1,
        )
        face = result["primID"].astype(np.int64)
        distance = np.where(face >= 0, result["tfar"].astype(np.float64), np.inf)
        return distance, face

    def _first_hit_fallback(  # pragma: no cover
        self, origins: np.ndarray, directions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        face = np.asarray(self._fallback.intersects_first(origins, directions), np.int64)
        distance = np.full(len(directions), np.inf)
        hit = face >= 0
        normals = self.face_normals[face[hit]]
        v0 = np.asarray(self.mesh.vertices)[np.asarray(self.mesh.faces)[face[hit], 0]]
        distance[hit] = np.einsum("ij,ij->i", v0 - origins[hit], normals) / np.einsum(
            "ij,ij->i", directions[hit], normals
        )
        return distance, face
