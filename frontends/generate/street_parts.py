"""Building blocks of the generated street (:mod:`frontends.generate.street`): the resampled
path with its frame, the ground height and mesh, footprint reservation and instanced primitives."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from frontends.generate.scene import _SceneBuilder


def resample_polyline(points: np.ndarray, spacing_m: float) -> np.ndarray:
    """Points along the polyline ``points`` (N, 3), evenly spaced by arc length."""
    if len(points) == 1:
        return points.copy()
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return points[:1].copy()
    s_new = np.arange(0.0, s[-1] + 1e-9, spacing_m)
    return np.stack([np.interp(s_new, s, points[:, k]) for k in range(3)], axis=1)


class GroundHeight:
    """Ground height: the inverse-distance-weighted path height minus the sensor height.

    With ``relief_m > 0`` smooth hills and hollows (a few random plane waves of 40-160 m
    wavelength, at most ``relief_m`` high) rise away from the road: zero within
    ``ROAD_FLAT_M`` of the path, full beyond ``ROAD_FLAT_M + RELIEF_RAMP_M``, so the road and its
    kerbs keep the path's height and slope while the surroundings stop being a continuation of
    the road's plane.
    """

    ROAD_FLAT_M = 7.0
    RELIEF_RAMP_M = 18.0

    def __init__(
        self, path_xyz: np.ndarray, sensor_height_m: float, relief_m: float = 0.0, seed: int = 0
    ) -> None:
        self._tree = cKDTree(path_xyz[:, :2])
        self._z = path_xyz[:, 2] - sensor_height_m
        self._k = min(8, len(path_xyz))
        self._relief_m = relief_m
        rng = np.random.default_rng([seed, 13])
        waves = 5
        angle = rng.uniform(0.0, 2 * np.pi, waves)
        wavelength = rng.uniform(40.0, 160.0, waves)
        self._k_xy = np.stack([np.cos(angle), np.sin(angle)], 1) * (2 * np.pi / wavelength)[:, None]
        self._phase = rng.uniform(0.0, 2 * np.pi, waves)
        self._amplitude = rng.uniform(0.5, 1.0, waves)

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        xy = np.atleast_2d(xy)
        dist, idx = self._tree.query(xy, k=self._k)
        if self._k == 1:
            z = self._z[idx]
            nearest = dist
        else:
            w = 1.0 / np.maximum(dist, 0.5) ** 2
            z = (w * self._z[idx]).sum(axis=1) / w.sum(axis=1)
            nearest = dist[:, 0]
        if self._relief_m > 0:
            u = np.clip((nearest - self.ROAD_FLAT_M) / self.RELIEF_RAMP_M, 0.0, 1.0)
            ramp = u * u * (3 - 2 * u)
            waves = np.sin(xy @ self._k_xy.T + self._phase) @ self._amplitude
            z = z + self._relief_m * ramp * waves / self._amplitude.sum()
        return z


def ground_mesh(
    path_xyz: np.ndarray, height: GroundHeight, margin_m: float, cell_m: float
) -> trimesh.Trimesh:
    lo = path_xyz[:, :2].min(axis=0) - margin_m
    hi = path_xyz[:, :2].max(axis=0) + margin_m
    xs = np.arange(lo[0], hi[0] + cell_m, cell_m)
    ys = np.arange(lo[1], hi[1] + cell_m, cell_m)
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    xy = np.stack([gx.ravel(), gy.ravel()], axis=1)
    vertices = np.column_stack([xy, height(xy)])
    nx, ny = len(xs), len(ys)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])  # normals +z
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)


class Footprints:
    """Keeps placed objects apart from each other and from the trajectory."""

    def __init__(self, dense_path_xy: np.ndarray) -> None:
        self._path = cKDTree(dense_path_xy)
        self._occupied: set[tuple[int, int]] = set()

    @staticmethod
    def _samples(center_xy: np.ndarray, yaw: float, size_xy: tuple[float, float]) -> np.ndarray:
        hx, hy = size_xy[0] / 2, size_xy[1] / 2
        u = np.linspace(-hx, hx, max(2, int(np.ceil(2 * hx / 0.5)) + 1))
        v = np.linspace(-hy, hy, max(2, int(np.ceil(2 * hy / 0.5)) + 1))
        gu, gv = np.meshgrid(u, v)
        c, s = np.cos(yaw), np.sin(yaw)
        return np.stack(
            [
                center_xy[0] + c * gu.ravel() - s * gv.ravel(),
                center_xy[1] + s * gu.ravel() + c * gv.ravel(),
            ],
            axis=1,
        )

    def clear_of_path(
        self, center_xy: np.ndarray, yaw: float, size_xy: tuple[float, float], clearance_m: float
    ) -> bool:
        """Whether the rectangle stays ``clearance_m`` away from the path (reserves nothing)."""
        dist, _ = self._path.query(self._samples(center_xy, yaw, size_xy))
        return bool(dist.min() >= clearance_m)

    def try_place(
        self, center_xy: np.ndarray, yaw: float, size_xy: tuple[float, float], clearance_m: float
    ) -> bool:
        """Reserve the rectangle if it is ``clearance_m`` away from the path and free."""
        pts = self._samples(center_xy, yaw, size_xy)
        cells = set(map(tuple, np.floor(pts).astype(np.int64).tolist()))
        if cells & self._occupied:
            return False
        dist, _ = self._path.query(pts)
        if dist.min() < clearance_m:
            return False
        self._occupied |= cells
        return True


class Instances:
    """Many scaled/posed copies of one template mesh, concatenated into one mesh at once.

    Far faster than building and concatenating one trimesh per object.
    """

    def __init__(self, template: trimesh.Trimesh) -> None:
        self._vertices = np.asarray(template.vertices, np.float64)
        self._faces = np.asarray(template.faces, np.int64)
        self._T: list[np.ndarray] = []
        self._reflectance: list[float] = []
        self._albedo: list[np.ndarray] = []

    def add(
        self,
        scale: tuple[float, float, float],
        T: np.ndarray,
        reflectance: float,
        albedo: tuple[float, float, float] | np.ndarray = (0.6, 0.6, 0.6),
    ) -> None:
        """One copy scaled by ``scale`` along the template axes, then moved by ``T``."""
        self._T.append(T @ np.diag([*scale, 1.0]))
        self._reflectance.append(reflectance)
        self._albedo.append(np.asarray(albedo, np.float32))

    def add_to(self, builder: _SceneBuilder) -> None:
        if not self._T:
            return
        T = np.stack(self._T)
        vertices = np.einsum("nij,vj->nvi", T[:, :3, :3], self._vertices) + T[:, None, :3, 3]
        offsets = np.arange(len(T))[:, None, None] * len(self._vertices)
        faces = (self._faces[None] + offsets).reshape(-1, 3)
        mesh = trimesh.Trimesh(vertices=vertices.reshape(-1, 3), faces=faces, process=False)
        per_face = len(self._faces)
        builder.add_arrays(
            mesh,
            reflectance=np.repeat(np.asarray(self._reflectance, np.float32), per_face),
            albedo=np.repeat(np.stack(self._albedo), per_face, axis=0),
        )


class StreetPath:
    """The driven path, resampled every ``SPACING_M`` along its arc length, with its frame.

    An open path is extended straight by ``extension_m`` before its start and after its end so
    that the street continues behind the first and beyond the last pose.
    """

    SPACING_M = 0.5

    def __init__(self, path_xyz: np.ndarray, extension_m: float) -> None:
        dense = resample_polyline(path_xyz, self.SPACING_M)
        closed = len(path_xyz) > 2 and np.linalg.norm(path_xyz[-1] - path_xyz[0]) < 1.0
        if len(dense) >= 2 and not closed and extension_m > 0:
            k = round(extension_m / self.SPACING_M)
            steps = self.SPACING_M * np.arange(1, k + 1)[:, None]
            head_dir = unit_xy(dense[min(4, len(dense) - 1)] - dense[0])
            tail_dir = unit_xy(dense[-1] - dense[max(0, len(dense) - 5)])
            head = dense[0] - steps[::-1] * head_dir
            tail = dense[-1] + steps * tail_dir
            dense = np.vstack([head, dense, tail])
        self.xyz = dense
        tangents = np.gradient(dense[:, :2], axis=0) if len(dense) > 1 else np.ones((1, 2))
        norms = np.linalg.norm(tangents, axis=1, keepdims=True)
        self.tangents = np.where(norms > 1e-9, tangents / np.maximum(norms, 1e-12), [1.0, 0.0])
        self.lefts = np.stack([-self.tangents[:, 1], self.tangents[:, 0]], axis=1)
        self.length_m = self.SPACING_M * (len(dense) - 1)

    def at(self, s: float, side: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Point, unit tangent and unit normal towards ``side`` (+1 left, -1 right) at ``s``."""
        i = int(np.clip(round(s / self.SPACING_M), 0, len(self.xyz) - 1))
        return self.xyz[i, :2], self.tangents[i], self.lefts[i] * side


def unit_xy(v: np.ndarray) -> np.ndarray:
    d = np.array([v[0], v[1], 0.0])
    n = np.linalg.norm(d)
    return d / n if n > 1e-9 else np.array([1.0, 0.0, 0.0])


def blob(rng: np.random.Generator) -> trimesh.Trimesh:
    """A lumpy unit sphere (tree crowns, bushes): an icosphere with jittered vertex radii."""
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=1.0)
    vertices = np.asarray(sphere.vertices) * rng.uniform(0.8, 1.15, (len(sphere.vertices), 1))
    return trimesh.Trimesh(vertices=vertices, faces=sphere.faces, process=False)


SIDEWALK_INNER_M = 4.5
"""Distance from the path to the kerb: parked cars stand inside it, poles and trees outside."""
SIDEWALK_WIDTH_M = 2.0
KERB_HEIGHT_M = 0.15
