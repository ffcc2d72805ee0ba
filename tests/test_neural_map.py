"""Encoding, exact fusion/removal, moving submaps and querying the neural map."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.transform import Rotation

from mapping.analytic_prior import planar_prior
from mapping.config import MapConfig
from mapping.encoding import encode_points, point_voxel_pairs
from mapping.networks import PriorModel
from mapping.neural_map import NeuralMap
from mapping.transform import transform_block

V = 0.1


def _random_model(seed: int = 0) -> PriorModel:
    torch.manual_seed(seed)
    return PriorModel().eval()


def _sphere(n: int, radius: float = 0.4, centre=(0.03, 0.41, -0.2), seed: int = 0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * radius + np.asarray(centre), d


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _cfg(**kw) -> MapConfig:
    base = {"min_points_per_voxel": 1, "min_weight_to_decode": 1.0, "device": "cpu"}
    base.update(kw)
    return MapConfig(**base)


def test_encode_assigns_every_point_to_its_eight_voxels() -> None:
    model = _random_model()
    points, normals = _sphere(3000)
    block = encode_points(model, torch.from_numpy(points), torch.from_numpy(normals), V)
    assert block.weights.sum().item() == 8 * 3000
    grid, r = point_voxel_pairs(torch.from_numpy(points), V)
    assert (r.abs() <= 1.0).all()  # inside the 2V cube of each of its voxels
    expected = torch.unique(grid.reshape(-1, 3), dim=0)
    assert torch.equal(block.keys, expected)
    counts = torch.unique(grid.reshape(-1, 3), dim=0, return_counts=True)[1]
    assert torch.equal(block.weights, counts.float())
    assert torch.isfinite(block.latents).all() and torch.isfinite(block.jacobians).all()


def test_pruning_drops_points_of_sparse_voxels() -> None:
    model = _random_model()
    points, normals = _sphere(2000)
    lonely = np.array([[5.05, 5.05, 5.05]])
    pts = np.vstack([points, lonely])
    nrm = np.vstack([normals, [[0.0, 0.0, 1.0]]])
    nm = NeuralMap(_cfg(min_points_per_voxel=2), model)
    sub = nm.encode(0, pts, nrm, np.eye(4))
    centres = sub.original.centers(V)
    assert np.linalg.norm(centres - lonely, axis=1).min() > 0.3
    kept = NeuralMap(_cfg(min_points_per_voxel=1), model).encode(0, pts, nrm, np.eye(4))
    assert np.linalg.norm(kept.original.centers(V) - lonely, axis=1).min() < 0.1


def test_stored_jacobian_matches_finite_differences() -> None:
    model = _random_model(5).double()
    points, normals = _sphere(1500, radius=0.25)
    pts = torch.from_numpy(points)
    nrm = torch.from_numpy(normals)
    block = encode_points(model, pts, nrm, V)
    grid, r = point_voxel_pairs(pts, V)
    keys, inverse = torch.unique(grid.reshape(-1, 3), dim=0, return_inverse=True)
    assert torch.equal(keys, block.keys)
    r = r.reshape(-1, 3)
    n8 = nrm.repeat_interleave(8, dim=0)
    counts = torch.bincount(inverse).double().view(-1, 1, 1)

    def voxel_means(shift: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            f = model.encoder(r + shift, n8)
        return (
            torch.zeros(keys.shape[0], *f.shape[1:], dtype=f.dtype).index_add_(0, inverse, f)
            / counts
        )

    delta = 1e-6
    fd = torch.stack(
        [
            (voxel_means(delta * e) - voxel_means(-delta * e)) / (2 * delta)
            for e in torch.eye(3, dtype=torch.float64)
        ],
        dim=-1,
    )  # (M, C, 3, 3) with the last index the derivative direction
    err = (block.jacobians.double() - fd).flatten(1).norm(dim=1)
    scale = fd.flatten(1).norm(dim=1)
    assert (scale > 1e-3).all()
    assert (err / scale).max() < 1e-3


def test_capped_jacobian_is_the_mean_over_an_even_subset_of_pairs() -> None:
    """With ``jacobian_pairs_per_voxel`` the latents and weights are those of every pair; each
    voxel's Jacobian is the exact mean of dF/dr over at most that many of its pairs, every
    ``ceil(c / cap)``-th in Z-order, and voxels with fewer pairs keep their exact Jacobian."""
    from common.voxel_keys import pack_keys
    from mapping.encoding import jacobian_pair_mask
    from mapping.span_encoder import point_latents

    cap = 5
    model = _random_model(4).double()
    points, normals = _sphere(2000, radius=0.25)
    pts, nrm = torch.from_numpy(points), torch.from_numpy(normals)
    full = encode_points(model, pts, nrm, V)
    capped = encode_points(model, pts, nrm, V, jacobian_pairs_per_voxel=cap)
    assert torch.equal(capped.keys, full.keys)
    assert torch.equal(capped.weights, full.weights)
    assert torch.allclose(capped.latents, full.latents, rtol=0, atol=1e-12)

    grid, r = point_voxel_pairs(pts, V)
    _, inverse = torch.unique(pack_keys(grid.reshape(-1, 3)), return_inverse=True)
    counts = torch.bincount(inverse)
    assert (counts > 3 * cap).any() and (counts <= cap).any()
    mask = jacobian_pair_mask(inverse, counts, r.reshape(-1, 3), cap)
    kept = torch.bincount(inverse[mask], minlength=len(counts))
    assert torch.equal(kept, -(-counts // -(-counts // cap)))  # ceil(c / ceil(c / cap))
    assert (kept <= cap).all()
    # spread over the voxel: every octant holding at least `stride` of a voxel's pairs is sampled
    stride = -(-counts // cap)
    octant = ((r.reshape(-1, 3) >= 0).long() * torch.tensor([1, 2, 4])).sum(1)
    cell = inverse * 8 + octant
    in_cell = torch.bincount(cell, minlength=8 * len(counts))
    sampled = torch.bincount(cell[mask], minlength=8 * len(counts))
    crowded = in_cell >= stride.repeat_interleave(8)
    assert crowded.sum() > 100 and (sampled[crowded] > 0).all()

    _, dF = point_latents(model.encoder, r.reshape(-1, 3), nrm.repeat_interleave(8, dim=0), True)
    jac = torch.zeros(len(counts), *dF.shape[1:], dtype=dF.dtype)
    jac.index_add_(0, inverse[mask], dF[mask])
    expected = (jac / kept.view(-1, 1, 1, 1)).permute(0, 3, 1, 2)
    assert torch.allclose(capped.jacobians.double(), expected, rtol=0, atol=1e-6)
    small = counts <= cap
    assert torch.allclose(capped.jacobians[small], full.jacobians[small], rtol=0, atol=1e-6)
    assert not torch.allclose(capped.jacobians[~small], full.jacobians[~small], atol=1e-3)


@pytest.mark.parametrize("moves", [0, 2])
def test_fuse_then_remove_restores_the_map(moves: int) -> None:
    """The placed block is not stored: removal recomputes it and must subtract exactly what was
    added, also after the submaps were moved around."""
    nm = NeuralMap(_cfg(), _random_model())
    pa, na = _sphere(4000, seed=1)
    pb, nb = _sphere(3000, centre=(0.2, 0.5, -0.1), seed=2)
    a = nm.encode(0, pa, na, np.eye(4))
    b = nm.encode(1, pb, nb, _pose([0.1, -0.2, 0.3], [0.05, 0.02, -0.01]))
    nm.fuse(a)
    before = nm.voxel_block()
    nm.fuse(b)
    assert nm.num_voxels > before.num_voxels
    poses = [_pose([0.2, 0.1, -0.3], [0.031, -0.17, 0.05]), _pose([0.0, 0.4, 0.1], [0.3, 0, 0])]
    for T in poses[:moves]:
        nm.move(b, T)
        nm.move(a, np.eye(4))  # back home: a no-op on the map
    nm.remove(b)
    after = nm.voxel_block()
    assert torch.equal(after.keys, before.keys)
    assert (after.latents - before.latents).abs().max() < 1e-5
    assert (after.weights - before.weights).abs().max() < 1e-5
    nm.remove(a)
    assert nm.num_voxels == 0
    assert nm.voxel_block().num_voxels == 0


def test_fused_latent_is_the_weighted_mean() -> None:
    model = _random_model()
    nm = NeuralMap(_cfg(storage_dtype="float32", latent_rank=16), model)
    p, n = _sphere(3000, seed=3)
    a = nm.encode(0, p[:1500], n[:1500], np.eye(4))
    b = nm.encode(1, p[1500:], n[1500:], np.eye(4))
    whole = nm.encode(2, p, n, np.eye(4)).original.decompress()
    nm.fuse(a)
    nm.fuse(b)
    fused = nm.voxel_block()
    assert torch.equal(fused.keys, whole.keys)
    assert torch.equal(fused.weights, whole.weights)
    assert (fused.latents - whole.latents).abs().max() < 1e-5


def test_remove_and_fuse_are_guarded() -> None:
    nm = NeuralMap(_cfg(), _random_model())
    p, n = _sphere(500)
    sub = nm.encode(3, p, n, np.eye(4))
    with pytest.raises(ValueError, match="not fused"):
        nm.remove(sub)
    nm.fuse(sub)
    with pytest.raises(ValueError, match="already fused"):
        nm.fuse(sub)
    twin = nm.encode(3, p, n, np.eye(4))
    with pytest.raises(ValueError, match="already fused"):
        nm.fuse(twin)
    with pytest.raises(ValueError, match="not fused"):
        nm.remove(twin)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        nm.encode(4, p[:, :2], n[:, :2], np.eye(4))
    with pytest.raises(ValueError, match="orthonormal"):
        nm.encode(4, p, n, np.diag([2.0, 1.0, 1.0, 1.0]))


def test_move_transforms_from_the_original_encoding() -> None:
    model = _random_model()
    nm = NeuralMap(_cfg(), model)
    p, n = _sphere(3000, seed=4)
    T0 = _pose([0.0, 0.0, 0.2], [0.1, 0.0, 0.0])
    sub = nm.encode(0, p, n, T0)
    original = sub.original
    nm.fuse(sub)
    T1 = _pose([0.1, 0.2, -0.1], [0.13, -0.04, 0.02])
    T2 = _pose([0.0, -0.3, 0.05], [0.0, 0.07, 0.1])
    nm.move(sub, T1)
    nm.move(sub, T2)
    assert sub.original is original and sub.fused
    expected = transform_block(original.decompress(), T2 @ np.linalg.inv(T0), V)
    got = nm.voxel_block()
    assert torch.equal(got.keys, expected.keys)
    assert (got.latents - expected.latents).abs().max() < 1e-5
    nm.move(sub, T0)  # back home: exactly the original
    assert not sub.is_moved
    assert (nm.voxel_block().latents - original.decompress().latents).abs().max() < 1e-5
    other = nm.encode(1, p, n, T0)
    nm.move(other, T1)  # an unfused submap is re-placed, not fused
    assert not other.fused and nm.placed(other).num_voxels > 0


def test_removing_a_block_that_was_not_fused_is_an_error() -> None:
    nm = NeuralMap(_cfg(), _random_model())
    p, n = _sphere(2000, seed=5)
    a = nm.encode(0, p, n, np.eye(4))
    nm.fuse(a)
    before = nm.voxel_block()
    far = nm.encode(1, p + 3.0, n, np.eye(4)).original.decompress()
    with pytest.raises(ValueError, match="not in the map"):
        nm._store.subtract(far)
    heavy = nm.placed(a)
    heavy.weights = heavy.weights * 2
    with pytest.raises(ValueError, match="weigh more"):
        nm._store.subtract(heavy)
    assert torch.equal(nm.voxel_block().latents, before.latents)  # nothing was changed


def test_query_sdf_reproduces_a_plane_in_metres() -> None:
    nm = NeuralMap(_cfg(), planar_prior())
    rng = np.random.default_rng(0)
    n_pts = 30000
    plane_z = 0.237
    points = np.c_[rng.uniform(-1, 1, (n_pts, 2)), np.full(n_pts, plane_z)]
    normals = np.tile([0.0, 0.0, 1.0], (n_pts, 1))
    nm.fuse(nm.encode(0, points, normals, np.eye(4)))
    queries = np.c_[
        rng.uniform(-0.8, 0.8, (500, 2)), rng.uniform(plane_z - 0.07, plane_z + 0.07, 500)
    ]
    sdf, sigma, valid = nm.query_sdf(queries)
    assert valid.all()
    assert np.abs(sdf - (queries[:, 2] - plane_z)).max() < 1e-4
    assert (sigma > 0).all()
    far = nm.query_sdf(np.array([[5.0, 5.0, 5.0]]))
    assert not far[2][0]


def test_voxel_centers_and_memory() -> None:
    nm = NeuralMap(_cfg(), _random_model())
    p, n = _sphere(2000)
    sub = nm.encode(0, p, n, np.eye(4))
    nm.fuse(sub)
    centres, weights = nm.voxel_centers()
    assert centres.shape == (nm.num_voxels, 3) and weights.shape == (nm.num_voxels,)
    assert np.allclose(
        np.mod(centres / V - 0.5, 1.0) * (1 - np.mod(centres / V - 0.5, 1.0)), 0, atol=1e-6
    )
    assert weights.sum() == pytest.approx(8 * 2000)
    assert nm.memory_bytes() >= nm.num_voxels * 16 * 3 * 4
    # the stored submap: packed key, float32 weight, rank-4 float16 latents, rank-4 int8
    # Jacobians, and per-submap bases (a few bytes per voxel)
    per_voxel = (sub.nbytes() - 2 * 16 * 8) / sub.original.num_voxels
    assert 8 + 4 + 4 * 3 * 2 + 4 * 9 <= per_voxel < 100


def test_mesh_of_box_is_closed_with_planar_prior() -> None:
    box = trimesh.creation.box(extents=[0.8, 0.6, 0.5])
    pts, face = trimesh.sample.sample_surface_even(box, 20000, seed=1)
    nm = NeuralMap(_cfg(), planar_prior())
    nm.fuse(nm.encode(0, pts, box.face_normals[face], np.eye(4)))
    mesh = nm.extract_mesh()
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(box.volume, rel=0.1)


@pytest.mark.parametrize("merge_min", [1, 10**9])
def test_changed_keys_are_merged_as_they_pile_up(monkeypatch, merge_min: int) -> None:
    """Fusing and removing the same submaps again and again (remaps) keeps the record of changed
    keys bounded by merging it; what take_dirty reports is the same either way."""
    import mapping.voxel_store as store_module

    monkeypatch.setattr(store_module, "DIRTY_MERGE_MIN", merge_min)
    nm = NeuralMap(MapConfig(min_points_per_voxel=1, device="cpu"), planar_prior())
    subs = [
        nm.encode(i, *_sphere(800, centre=(0.3 * i, 0.0, 0.0), seed=i), np.eye(4)) for i in range(3)
    ]
    for step in range(6):  # all three in, the middle one out and in, ...
        for sub in subs if step % 2 == 0 else subs[1:2]:
            if sub.submap_id in nm.fused_ids:
                nm.remove(sub)
            else:
                nm.fuse(sub)
    store = nm._store
    assert store._dirty_count == sum(k.shape[0] for k in store._dirty)
    if merge_min == 1:
        assert 0 < store._dirty_merged <= store._dirty_count
        assert store._dirty_count <= 2 * max(store._dirty_merged, store.num_voxels)
    dirty = store.take_dirty()
    every = torch.unique(torch.cat([torch.as_tensor(s.original.keys) for s in subs]))
    assert torch.equal(dirty, every) and store.take_dirty().numel() == 0
