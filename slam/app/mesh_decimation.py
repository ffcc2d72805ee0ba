"""A mesh for display: decimated (a viewer needs a bounded face count, not the full mesh) and
built as a Rerun ``Mesh3D``."""

from __future__ import annotations

import math

import numpy as np
import trimesh

from common.voxel_keys import KEY_BITS, KEY_LIMIT, pack_keys

FACES_PER_CHUNK = 1 << 18
"""Faces whose corners are gathered at once to sum the mesh area: the whole map's final mesh
(about 2 million faces) gathered at once was a 400 MB peak of a recorded run."""


def _area(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Total area of the faces, gathered :data:`FACES_PER_CHUNK` at a time."""
    total = 0.0
    for start in range(0, len(faces), FACES_PER_CHUNK):
        corners = vertices[faces[start : start + FACES_PER_CHUNK]]
        edges = corners[:, 1:] - corners[:, :1]
        total += 0.5 * np.linalg.norm(np.cross(edges[:, 0], edges[:, 1]), axis=1).sum()
    return float(total)


def decimate_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    max_faces: int,
    vertex_colors: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Vertex-clustering decimation for display: vertices are merged per cell of a grid (cell
    size from the mesh area, ``sqrt(2 area / max_faces)``, grown until the face budget holds),
    collapsed and duplicate faces dropped. Meshes within budget are returned unchanged. Vertex
    indices are held as int32 while faces are collapsed: a mesh of the whole map is decimated
    in about a quarter of its size again."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) <= max_faces:
        return vertices, faces, vertex_colors
    cell = max(math.sqrt(1.2 * _area(vertices, faces) / max(max_faces, 1)), 1e-9)
    extent = float(np.ptp(vertices, axis=0).max())
    cell = max(cell, extent / (KEY_LIMIT - 1))  # fewer than KEY_LIMIT cells per axis
    origin = vertices.min(axis=0)
    while True:
        keys = pack_keys(np.floor((vertices - origin) / cell).astype(np.int64))
        _, cluster, counts = np.unique(keys, return_inverse=True, return_counts=True)
        cluster = cluster.ravel().astype(np.int32)
        new_faces = cluster[faces]
        keep = (
            (new_faces[:, 0] != new_faces[:, 1])
            & (new_faces[:, 1] != new_faces[:, 2])
            & (new_faces[:, 0] != new_faces[:, 2])
        )
        new_faces = new_faces[keep]
        ordered = np.sort(new_faces, axis=1)
        if len(counts) < KEY_LIMIT:  # vertex-index triples (>= 0) pack like voxel coordinates
            a, b, c = (ordered[:, k].astype(np.int64) for k in range(3))
            ordered = (a << (2 * KEY_BITS)) | (b << KEY_BITS) | c
        _, first = np.unique(ordered, axis=0 if ordered.ndim == 2 else None, return_index=True)
        new_faces = new_faces[np.sort(first)]
        if len(new_faces) <= max_faces:
            break
        cell *= 1.15
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, cluster, vertices)
    new_vertices = sums / counts[:, None]
    new_colors = None
    if vertex_colors is not None:
        color_sums = np.zeros((len(counts), 3))
        np.add.at(color_sums, cluster, np.asarray(vertex_colors, dtype=np.float64)[:, :3])
        new_colors = np.round(color_sums / counts[:, None]).astype(np.uint8)
    used = np.unique(new_faces)
    remap = np.full(len(counts), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    colors_out = None if new_colors is None else new_colors[used]
    return new_vertices[used], remap[new_faces], colors_out


def display_mesh(mesh: trimesh.Trimesh, max_faces: int, albedo: tuple[int, ...]) -> object:
    """``mesh`` as a Rerun ``Mesh3D``, vertex-clustered to at most ``max_faces`` faces, with
    vertex normals; its vertex colours, else the ``albedo`` tint."""
    import rerun as rr

    vertex_colors = None
    if mesh.visual is not None and mesh.visual.kind == "vertex":
        vertex_colors = np.asarray(mesh.visual.vertex_colors)[:, :3]
    vertices, faces, vertex_colors = decimate_mesh(
        np.asarray(mesh.vertices), np.asarray(mesh.faces), max_faces, vertex_colors
    )
    normals = None
    if len(faces):
        shown = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
        normals = np.asarray(shown.vertex_normals, dtype=np.float32)
    return rr.Mesh3D(
        vertex_positions=vertices.astype(np.float32),
        triangle_indices=faces.astype(np.uint32),
        vertex_normals=normals,
        vertex_colors=vertex_colors,
        albedo_factor=None if vertex_colors is not None else albedo,
    )
