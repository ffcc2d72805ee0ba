"""The procedural patch generator: exact SDF of its primitives, sensor-like observations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from mapping.training.patches import PatchConfig, generate_patches, generate_patches_with_scenes
from mapping.training.scenes import BOX, CYLINDER, PATCH_KINDS, WEDGE, primitive_scene

SMALL = PatchConfig(n_queries=512, shell_candidates=2048, surface_pool=256)


def _rotation(seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _mesh_sdf(mesh: trimesh.Trimesh, pts: np.ndarray) -> np.ndarray:
    """Signed distance to a closed mesh, positive outside (brute force over all triangles;
    trimesh.proximity would need the optional rtree package)."""
    n, t = len(pts), len(mesh.triangles)
    closest = trimesh.triangles.closest_point(
        np.repeat(mesh.triangles[None], n, axis=0).reshape(-1, 3, 3), np.repeat(pts, t, axis=0)
    )
    dist = np.linalg.norm(closest - np.repeat(pts, t, axis=0), axis=1).reshape(n, t).min(1)
    return np.where(mesh.contains(pts), -dist, dist)


def _compare_with_mesh(scene, mesh: trimesh.Trimesh, pts: np.ndarray, tol: float) -> None:
    ours = scene.sdf(torch.as_tensor(pts, dtype=torch.float32)[None])[0].numpy()
    np.testing.assert_allclose(ours, _mesh_sdf(mesh, pts), atol=tol)


def _query_points(n: int = 200, scale: float = 1.5, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-scale, scale, size=(n, 3))


def test_box_sdf_is_exact_inside_and_outside():
    R, t = _rotation(1), np.array([0.2, -0.1, 0.3])
    half = np.array([0.6, 0.3, 0.45])
    scene = primitive_scene(BOX, [*half, 0.0], R, t)
    mesh = trimesh.creation.box(extents=2 * half, transform=_pose(R, t))
    _compare_with_mesh(scene, mesh, _query_points(), 1e-4)


def test_complemented_box_is_the_negated_distance():
    R, t = _rotation(2), np.zeros(3)
    half = np.array([0.8, 0.7, 0.9])
    scene = primitive_scene(BOX, [*half, 0.0], R, t, complement=True)
    mesh = trimesh.creation.box(extents=2 * half, transform=_pose(R, t))
    pts = _query_points(seed=1)
    ours = scene.sdf(torch.as_tensor(pts, dtype=torch.float32)[None])[0].numpy()
    np.testing.assert_allclose(ours, -_mesh_sdf(mesh, pts), atol=1e-4)


def test_sphere_sdf_matches_tessellated_sphere():
    radius, t = 0.7, np.array([0.1, 0.2, -0.1])
    scene = primitive_scene(BOX, [0.0, 0.0, 0.0, radius], None, t)
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    mesh.apply_translation(t)
    # chord error of the tessellation is below ~1e-3 vu at this radius
    _compare_with_mesh(scene, mesh, _query_points(seed=2), 2e-3)


def test_capped_cylinder_sdf_matches_tessellated_cylinder():
    R, t = _rotation(3), np.array([-0.2, 0.1, 0.0])
    radius, half_height = 0.5, 0.6
    scene = primitive_scene(CYLINDER, [radius, half_height], R, t)
    mesh = trimesh.creation.cylinder(
        radius=radius, height=2 * half_height, sections=128, transform=_pose(R, t)
    )
    _compare_with_mesh(scene, mesh, _query_points(seed=3), 2e-3)


@pytest.mark.parametrize("alpha_deg", [50.0, 120.0, 180.0])
def test_wedge_sdf_matches_a_long_prism(alpha_deg: float):
    alpha = math.radians(alpha_deg)
    length = 40.0
    R = _rotation(4)
    scene = primitive_scene(WEDGE, [alpha], R, np.zeros(3))
    # the wedge's (x, z) cross-section, long rays from the apex, extruded along y
    e1 = length * np.array([math.sin(alpha / 2), -math.cos(alpha / 2)])
    e2 = length * np.array([-math.sin(alpha / 2), -math.cos(alpha / 2)])
    if alpha_deg < 180:
        section, faces = np.array([[0.0, 0.0], e1, e2]), np.array([[0, 1, 2]])
    else:  # a half-plane: a wide rectangle below the apex line
        down = np.array([0.0, -length])
        section = np.array([e1, e2, e2 + down, e1 + down])
        faces = np.array([[0, 1, 2], [0, 2, 3]])
    prism = trimesh.creation.extrude_triangulation(section, faces, height=2 * length)
    if prism.volume < 0:
        prism.invert()
    # built in (x, y) and extruded along z; map (x, y, z) -> (x, z - L, y)
    to_wedge = np.array([[1, 0, 0, 0], [0, 0, 1, -length], [0, 1, 0, 0], [0, 0, 0, 1.0]])
    prism.apply_transform(_pose(R, np.zeros(3)) @ to_wedge)
    _compare_with_mesh(scene, prism, _query_points(seed=5), 1e-3)


def test_union_is_exact_where_flagged_and_a_bound_elsewhere():
    """Concave edge as the union of two half-spaces z < 0 and x < 0 (known closed form)."""
    scene = primitive_scene(BOX, [100.0, 100.0, 100.0, 0.0], None, np.array([0, 0, -100.0]))
    other = primitive_scene(BOX, [100.0, 100.0, 100.0, 0.0], None, np.array([-100.0, 0, 0]))
    for name in ("kind", "params", "sign", "active", "R", "t"):
        merged = getattr(scene, name).clone()
        merged[0, 1] = getattr(other, name)[0, 0]
        setattr(scene, name, merged)
    pts = torch.as_tensor(_query_points(2000, 1.0, seed=6), dtype=torch.float32)
    d, _, exact = scene.sdf_exact(pts[None])
    x, z = pts[:, 0].numpy(), pts[:, 2].numpy()
    # inside the solid: the distance to the free quadrant {x > 0, z > 0}
    inside = np.where(x > 0, -z, np.where(z > 0, -x, np.hypot(x, z)))
    truth = np.where((x > 0) & (z > 0), np.minimum(x, z), -inside)
    d, exact = d[0].numpy(), exact[0].numpy()
    assert exact.mean() > 0.3 and (~exact).sum() > 50
    np.testing.assert_allclose(d[exact], truth[exact], atol=1e-5)
    assert np.all(truth[~exact] <= d[~exact] + 1e-4)  # an upper bound where not flagged exact


def test_patches_have_the_documented_shapes_and_units():
    batch = generate_patches(8, seed=3, cfg=SMALL)
    assert batch.points.shape == (8, SMALL.n_points, 3)
    assert batch.normals.shape == (8, SMALL.n_points, 3)
    assert batch.queries.shape == (8, SMALL.n_queries, 3)
    assert batch.sdf.shape == batch.sdf_mask.shape == (8, SMALL.n_queries)
    assert torch.allclose(batch.normals.norm(dim=-1), torch.ones(8, SMALL.n_points), atol=1e-5)
    assert batch.queries.abs().max() <= 1.0
    assert batch.points.abs().max() < 1.3  # the 2V cube plus sensor noise


def test_patches_are_deterministic_by_seed():
    a = generate_patches(4, seed=11, cfg=SMALL)
    b = generate_patches(4, seed=11, cfg=SMALL)
    c = generate_patches(4, seed=12, cfg=SMALL)
    for name in ("points", "normals", "queries", "sdf", "sdf_mask", "sensors"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert not torch.equal(a.points, c.points)


def test_observations_face_sensors_in_free_space():
    batch, scenes = generate_patches_with_scenes(16, seed=5, cfg=SMALL)
    # sensors are in free space (positive SDF), and every normal faces one of them
    sensor_sdf = scenes.sdf(batch.sensors)
    assert torch.all(sensor_sdf[batch.sensor_mask] > 0)
    to_sensor = batch.sensors.unsqueeze(1) - batch.points.unsqueeze(2)
    facing = (batch.normals.unsqueeze(2) * to_sensor).sum(-1) > 0
    facing = (facing & batch.sensor_mask.unsqueeze(1)).any(-1)
    assert facing[batch.point_mask].all()
    # points lie on the surface up to the sensor noise (per-patch sigma <= 0.05 vu)
    on_surface = scenes.sdf(batch.points).abs()
    assert on_surface[batch.point_mask].mean() < 0.03
    # noisy normals stay within the tilt bound of the true surface normal (up to sign)
    _, true_normal, _ = scenes.sdf_exact(batch.points)
    cos = (true_normal * batch.normals).sum(-1).abs()
    clean = batch.point_mask & (on_surface < 0.01)
    assert torch.quantile(cos[clean], 0.1) > math.cos(math.radians(45.0))


def test_sdf_samples_are_balanced_and_consistent_with_the_scene():
    batch, scenes = generate_patches_with_scenes(16, seed=8, cfg=SMALL)
    valid = batch.sdf_mask.all(-1)
    assert valid.float().mean() > 0.8
    positive = (batch.sdf > 0).float().mean(-1)[valid]
    assert torch.allclose(positive, torch.full_like(positive, 0.5), atol=1e-6) or (
        (positive - 0.5).abs().median() < 1e-6
    )
    d, _, exact = scenes.sdf_exact(batch.queries)
    assert torch.allclose(d, batch.sdf)
    clamp = SMALL.sdf_clamp_vu
    assert torch.all((exact | (batch.sdf <= -clamp))[batch.sdf_mask])
    # concentrated near the surface: most supervised samples within 0.2 vu
    assert ((batch.sdf.abs() < 0.2) & batch.sdf_mask).float().sum() > 0.5 * batch.sdf_mask.sum()


def test_one_sided_thin_wall_leaves_the_far_side_unsupervised():
    cfg = SMALL.model_copy(update={"kind_weights": {"thin_wall": 1.0}})
    batch, scenes = generate_patches_with_scenes(24, seed=2, cfg=cfg)
    one_sided = batch.sensor_mask.sum(-1) == 1
    assert one_sided.any()
    # a supervised free-space sample is on the same side of the wall as the sensor
    wall_normal = scenes.R[:, 0, :, 2]  # local z of the slab
    wall_centre = scenes.t[:, 0]
    side = lambda p: torch.sign(((p - wall_centre[:, None]) * wall_normal[:, None]).sum(-1))  # noqa: E731
    sensor_side = side(batch.sensors[:, :1])  # (B, 1)
    sample_side = side(batch.queries)
    positive = batch.sdf_mask & (batch.sdf > 0) & one_sided[:, None]
    assert positive.any()
    assert torch.all(sample_side[positive] == sensor_side.expand_as(sample_side)[positive])


@pytest.mark.parametrize("kind", PATCH_KINDS)
def test_every_kind_generates_observed_points(kind: str):
    cfg = SMALL.model_copy(update={"kind_weights": {kind: 1.0}})
    batch = generate_patches(6, seed=1, cfg=cfg)
    assert torch.all(batch.kind == PATCH_KINDS.index(kind))
    assert batch.point_mask.float().mean() > 0.8
    assert batch.sdf_mask.float().mean() > 0.8


def test_unknown_kind_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown patch kinds"):
        generate_patches(2, 0, PatchConfig(kind_weights={"torus": 1.0}))
