"""PCA normals of LiDAR point clouds and the 3x3 eigen solver behind them."""

from __future__ import annotations

import numpy as np

from common.normals import estimate_normals, smallest_eigenvectors


def _random_covariances(rng: np.random.Generator, n: int) -> np.ndarray:
    spread = rng.uniform(0.01, 2.0, size=(n, 1, 3))
    samples = rng.normal(size=(n, 12, 3)) * spread
    rotation = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0]
    samples = samples @ rotation.transpose(0, 2, 1)
    return np.einsum("nki,nkj->nij", samples, samples)


def test_smallest_eigenvectors_match_lapack() -> None:
    cov = _random_covariances(np.random.default_rng(0), 5000)
    vectors = smallest_eigenvectors(cov)
    reference = np.linalg.eigh(cov)[1][:, :, 0]
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.abs(np.einsum("ni,ni->n", vectors, reference)), 1.0, atol=1e-9)


def test_smallest_eigenvectors_of_degenerate_matrices_are_eigenvectors() -> None:
    line = np.outer([1.0, 2.0, 2.0], [1.0, 2.0, 2.0])  # rank 1: two zero eigenvalues
    plane = np.diag([4.0, 4.0, 0.0])  # a flat patch, repeated largest eigenvalue
    blob = np.eye(3) * 2.0  # isotropic
    cov = np.stack([line, plane, blob, np.zeros((3, 3))])
    vectors = smallest_eigenvectors(cov)
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), 1.0, atol=1e-12)
    smallest = np.linalg.eigvalsh(cov)[:, 0]
    residual = np.einsum("nij,nj->ni", cov, vectors) - smallest[:, None] * vectors
    np.testing.assert_allclose(residual, 0.0, atol=1e-9)
    np.testing.assert_allclose(np.abs(vectors[1]), [0.0, 0.0, 1.0], atol=1e-12)


def test_normals_of_a_noisy_plane_point_to_the_sensor() -> None:
    rng = np.random.default_rng(1)
    xy = rng.uniform(-5.0, 5.0, size=(3000, 2))
    points = np.c_[xy, 0.3 * xy[:, 0] + rng.normal(scale=0.005, size=len(xy))]
    truth = np.array([-0.3, 0.0, 1.0]) / np.hypot(0.3, 1.0)  # sensor above the plane
    normals, valid = estimate_normals(points, np.array([0.0, 0.0, 10.0]), max_radius_m=1.0)
    assert valid.mean() > 0.99
    assert np.einsum("ni,i->n", normals[valid], truth).min() > 0.98
    assert not normals[~valid].any()
