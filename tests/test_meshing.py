"""Meshing of the neural map: lattice blending, marching cubes, incremental chunks."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from common.voxel_keys import unpack_keys
from mapping.analytic_prior import planar_prior
from mapping.config import MapConfig
from mapping.field import decode_lattice
from mapping.mesh_lattice import lattice_offsets
from mapping.networks import DEFAULT_WEIGHTS, PriorModel
from mapping.neural_map import NeuralMap

V = 0.1


def _cfg(**kw) -> MapConfig:
    base = {"min_points_per_voxel": 1, "min_weight_to_decode": 1.0, "device": "cpu"}
    base.update(kw)
    return MapConfig(**base)


def _surface_distance(vertices: np.ndarray, mesh: trimesh.Trimesh) -> np.ndarray:
    samples, _ = trimesh.sample.sample_surface_even(mesh, 200000, seed=0)
    return cKDTree(samples).query(vertices)[0]


def test_marching_cubes_mask_is_read_at_the_upper_cell_corner() -> None:
    """meshing.py relies on this scikit-image convention to skip cells with unobserved corners."""
    from skimage.measure import marching_cubes

    x = np.arange(6.0)
    volume = np.broadcast_to(x[:, None, None] - 2.5, (6, 6, 6)).copy()
    mask = np.zeros(volume.shape, dtype=bool)
    mask[3, 3, 3] = True
    verts, faces, _, _ = marching_cubes(volume, 0.0, mask=mask)
    assert len(faces) > 0
    assert verts.min(0) == pytest.approx([2.5, 2.0, 2.0]) and verts.max(0) == pytest.approx(
        [2.5, 3.0, 3.0]
    )


@pytest.mark.parametrize("subdivisions", [1, 2, 3, 4])
def test_lattice_covers_the_open_2v_cube(subdivisions: int) -> None:
    idx, q, tent = lattice_offsets(subdivisions)
    assert (q.abs() < 1).all() and (tent > 0).all()
    count = 2 * subdivisions - 1 if subdivisions % 2 == 0 else 2 * subdivisions
    assert q.shape == (count**3, 3)
    # node m of voxel g sits at m h with h = V / s; its offset from the centre is q
    g = torch.tensor([3, -5, 7])
    m = g * subdivisions + idx
    assert torch.allclose((m / subdivisions - (g + 0.5)).float(), q, atol=1e-6)


def test_plane_mesh_lies_on_the_plane() -> None:
    nm = NeuralMap(_cfg(), planar_prior())
    rng = np.random.default_rng(0)
    n = 30000
    points = np.c_[rng.uniform(-0.6, 0.6, (n, 2)), np.full(n, 0.0437)]
    nm.fuse(nm.encode(0, points, np.tile([0.0, 0.0, 1.0], (n, 1)), np.eye(4)))
    mesh = nm.extract_mesh()
    assert len(mesh.faces) > 1000
    assert np.abs(mesh.vertices[:, 2] - 0.0437).max() < 1e-4
    assert np.all(mesh.face_normals[:, 2] > 0.99)  # oriented towards +SDF (the normals' side)
    # the mesh stays within about a voxel of the observed points
    assert np.abs(mesh.vertices[:, :2]).max() < 0.6 + 1.5 * V


def test_sphere_mesh_is_closed_and_close_to_the_surface() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.45)
    points, face = trimesh.sample.sample_surface_even(sphere, 25000, seed=0)
    nm = NeuralMap(_cfg(), planar_prior())
    nm.fuse(nm.encode(0, points, sphere.face_normals[face], np.eye(4)))
    mesh = nm.extract_mesh()
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0
    radial = np.abs(np.linalg.norm(mesh.vertices, axis=1) - 0.45)
    assert radial.mean() < 0.006 and radial.max() < 0.015
    # mesh vertices are zeros of the queried field (same blending as query_sdf)
    sdf, _, valid = nm.query_sdf(mesh.vertices[::7])
    assert valid.all() and np.abs(sdf).max() < 0.1 * V


def test_coarse_to_fine_meshing_matches_the_full_lattice() -> None:
    from mapping.meshing import ChunkMesher

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.27)
    points, face = trimesh.sample.sample_surface_even(sphere, 8000, seed=5)
    nm = NeuralMap(_cfg(), planar_prior())
    nm.fuse(nm.encode(0, points, sphere.face_normals[face], np.eye(4)))
    dirty = nm._store.take_dirty()
    meshes = []
    for c2f in (True, False):
        mesher = ChunkMesher(V, 4, 8, nm.cfg.mesh_max_sigma_vu, 1.0, coarse_to_fine=c2f)
        mesher.update(nm._store, nm.model.decoder, dirty)
        meshes.append(mesher.mesh())
    assert len(meshes[0].faces) == len(meshes[1].faces) > 100
    assert np.abs(np.sort(meshes[0].vertices, 0) - np.sort(meshes[1].vertices, 0)).max() < 1e-4


def test_incremental_meshing_only_touches_dirty_chunks() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    pa, fa = trimesh.sample.sample_surface_even(sphere, 10000, seed=1)
    na = sphere.face_normals[fa]
    nm = NeuralMap(_cfg(), planar_prior())
    a = nm.encode(0, pa, na, np.eye(4))
    nm.fuse(a)
    first = nm.extract_mesh()
    assert nm.extract_mesh().vertices.shape == first.vertices.shape  # nothing dirty: same mesh
    far = np.eye(4)
    far[:3, 3] = [3.0, 0.0, 0.0]
    b = nm.encode(1, pa, na, far)
    nm.fuse(b)
    both = nm.extract_mesh()
    remeshed = unpack_keys(nm._mesher.last_remeshed).numpy() * (V * nm.cfg.mesh_chunk_voxels)
    assert len(remeshed) > 0 and (remeshed[:, 0] > 1.5).all()  # only chunks near the new submap
    assert len(both.faces) == pytest.approx(2 * len(first.faces), rel=0.02)
    nm.remove(b)
    again = nm.extract_mesh()
    assert len(again.faces) == len(first.faces)
    assert np.allclose(np.sort(again.vertices, axis=0), np.sort(first.vertices, axis=0))


def test_high_sigma_triangles_are_dropped() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    points, face = trimesh.sample.sample_surface_even(sphere, 8000, seed=2)
    normals = sphere.face_normals[face]
    kept = NeuralMap(_cfg(mesh_max_sigma_vu=0.2), planar_prior())  # planar prior: sigma 0.137 vu
    kept.fuse(kept.encode(0, points, normals, np.eye(4)))
    dropped = NeuralMap(_cfg(mesh_max_sigma_vu=0.1), planar_prior())
    dropped.fuse(dropped.encode(0, points, normals, np.eye(4)))
    assert len(kept.extract_mesh().faces) > 0 and len(dropped.extract_mesh().faces) == 0


def test_light_voxels_are_not_decoded() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    points, face = trimesh.sample.sample_surface_even(sphere, 8000, seed=2)
    nm = NeuralMap(_cfg(min_weight_to_decode=1e9), planar_prior())
    nm.fuse(nm.encode(0, points, sphere.face_normals[face], np.eye(4)))
    assert len(nm.extract_mesh().faces) == 0
    assert not nm.query_sdf(points[:10])[2].any()


def test_shipped_prior_meshes_a_box_accurately() -> None:
    box = trimesh.creation.box(extents=[0.9, 0.7, 0.5])
    points, face = trimesh.sample.sample_surface_even(box, 40000, seed=3)
    nm = NeuralMap(_cfg(), PriorModel.load(DEFAULT_WEIGHTS))
    nm.fuse(nm.encode(0, points, box.face_normals[face], np.eye(4)))
    mesh = nm.extract_mesh()
    assert len(mesh.faces) > 500
    dist = _surface_distance(mesh.vertices, box)
    assert np.mean(dist) < 0.01


def _sphere_map() -> NeuralMap:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    points, face = trimesh.sample.sample_surface_even(sphere, 8000, seed=3)
    nm = NeuralMap(_cfg(), planar_prior())
    nm.fuse(nm.encode(0, points, sphere.face_normals[face], np.eye(4)))
    return nm


def test_welded_mesh_is_watertight_across_chunks() -> None:
    """Only vertices on chunk faces are welded; the sphere must come out closed."""
    nm = _sphere_map()
    mesh = nm.extract_mesh()
    assert nm._mesher.num_chunks > 1  # the sphere spans several chunks
    assert len(mesh.faces) > 100 and mesh.is_watertight
    merged = mesh.copy()
    merged.merge_vertices()  # trimesh's own weld finds nothing left to merge
    assert len(merged.vertices) == len(mesh.vertices)


def test_meshing_on_threads_gives_the_same_mesh() -> None:
    """Chunk batches meshed on two threads assemble into the mesh of one thread: the same
    vertices and faces."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    points, face = trimesh.sample.sample_surface_even(sphere, 8000, seed=3)
    meshes = []
    for threads in (1, 2):
        nm = NeuralMap(_cfg(mesh_chunk_voxels=2), planar_prior())  # > 32 chunks: several batches
        nm.fuse(nm.encode(0, points, sphere.face_normals[face], np.eye(4)))
        meshes.append(nm.extract_mesh(threads=threads))
    assert nm._mesher.num_chunks > 32  # CHUNKS_PER_BATCH: more than one batch
    assert len(meshes[0].faces) > 100
    np.testing.assert_array_equal(meshes[0].faces, meshes[1].faces)
    np.testing.assert_array_equal(meshes[0].vertices, meshes[1].vertices)


def test_meshing_in_larger_batches_gives_the_same_mesh(monkeypatch) -> None:
    """All chunks in one batch: the same vertices and faces as batches of 32, with each voxel
    decoded once (in batches of 32 the voxels on the batches' shared chunk faces twice)."""
    import mapping.meshing as meshing

    decoded = []

    def counted(decoder, F, q, terms=None):
        decoded.append(F.shape[0])
        return decode_lattice(decoder, F, q, terms)

    monkeypatch.setattr(meshing, "decode_lattice", counted)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    points, face = trimesh.sample.sample_surface_even(sphere, 8000, seed=3)
    meshes, rows = [], []
    for chunks_per_batch in (32, 10_000):
        decoded.clear()
        nm = NeuralMap(_cfg(mesh_chunk_voxels=2), planar_prior())
        nm.fuse(nm.encode(0, points, sphere.face_normals[face], np.eye(4)))
        meshes.append(nm.extract_mesh(chunks_per_batch=chunks_per_batch))
        rows.append(sum(decoded))
    assert nm._mesher.num_chunks > 32 and len(meshes[0].faces) > 100
    assert rows[1] == int((nm._store.weights64() >= nm.cfg.min_weight_to_decode).sum())
    assert rows[0] > rows[1]
    np.testing.assert_array_equal(meshes[0].faces, meshes[1].faces)
    np.testing.assert_array_equal(meshes[0].vertices, meshes[1].vertices)


def test_failed_marching_cubes_is_reported(monkeypatch, caplog) -> None:
    import skimage.measure

    nm = _sphere_map()
    reference = nm.extract_mesh()
    chunks = nm._mesher.num_chunks
    real = skimage.measure.marching_cubes
    calls = []

    def failing_once(*args, **kwargs):
        calls.append(1)
        if len(calls) == 1:
            raise ValueError("simulated failure")
        return real(*args, **kwargs)

    fresh = _sphere_map()
    monkeypatch.setattr(skimage.measure, "marching_cubes", failing_once)
    with caplog.at_level("WARNING", logger="mapping.meshing"):
        mesh = fresh.extract_mesh()
    assert fresh._mesher.failed_chunks == 1
    assert fresh._mesher.num_chunks == chunks - 1  # the failed chunk is missing ...
    assert 0 < len(mesh.faces) < len(reference.faces)
    warning = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warning) == 1 and f"failed on 1 of {chunks} " in warning[0]  # ... and said so
    assert "simulated failure" in warning[0]


def test_no_surface_in_observed_cells_is_an_empty_chunk_not_a_failure() -> None:
    from mapping.meshing import ChunkMesher

    mesher = ChunkMesher(V, 2, 4, max_sigma_vu=1.0, min_weight=1.0)
    n = 9
    sdf = np.broadcast_to(np.arange(n, dtype=np.float32)[:, None, None] - 4.5, (n, n, n)).copy()
    sdf[4:6] = 1.0  # nodes 4 and 5 unobserved: the sign change lies only in their cells ...
    mask = np.zeros((n, n, n), dtype=bool)
    mask[1:4, 1:, 1:] = mask[7:, 1:, 1:] = True  # ... which are not marched (upper corners)
    out = mesher._march(sdf, np.full((n, n, n), 0.1, np.float32), mask)
    assert out is None and mesher.failed_chunks == 0


def test_chunk_cache_is_compact_and_each_mesh_is_a_new_copy() -> None:
    """Chunks are cached as float32 lattice vertices and small-integer faces; the world vertices
    are exactly ``(lattice + corner node) * h`` in float64; a returned mesh is the caller's own."""
    nm = _sphere_map()
    first = nm.extract_mesh()
    mesher = nm._mesher
    h = V / mesher.subdivisions
    assembled = {row.tobytes() for row in first.vertices}
    for key in sorted(mesher._chunks):
        local, faces, on_face = mesher._chunks[key]
        assert local.dtype == np.float32 and faces.dtype.itemsize <= 2
        assert on_face.shape == (len(local),) and int(faces.max()) < len(local)
        corner = unpack_keys(np.array([key]))[0] * (mesher.chunk_voxels * mesher.subdivisions)
        world = (local.astype(np.float64) + corner) * h
        # the assembled mesh holds each chunk's interior vertices unchanged
        assert all(row.tobytes() in assembled for row in world[~on_face])
    first.vertices[:] = 0.0  # the caller's copy: changing it changes nothing cached
    second = nm.extract_mesh()
    assert len(second.faces) == len(first.faces) and np.abs(second.vertices).max() > 0.1
