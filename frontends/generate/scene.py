"""Scene meshes for generated sequences: a street along a path (LiDAR) and a textured room (RGB-D).

A :class:`Scene` is one triangle mesh plus per-face material attributes (LiDAR reflectance, base
colour and texture cell size) that the sensors read at the hit triangle. Every random choice is
drawn from generators seeded by ``seed``; street objects reserve their footprints, so revisiting a
place along a trajectory sees the structures of the first visit, not a second copy.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.spatial import cKDTree


@dataclass
class Scene:
    """A triangle mesh with per-face materials.

    Attributes:
        mesh: the geometry, in the world frame.
        face_reflectance: (F,) float32 LiDAR reflectance in [0, 1].
        face_albedo: (F, 3) float32 base RGB colour in [0, 1].
        face_texture_m: (F,) float32 texture cell size in metres (0 = plain colour).
    """

    mesh: trimesh.Trimesh
    face_reflectance: np.ndarray
    face_albedo: np.ndarray
    face_texture_m: np.ndarray

    def transformed(self, T_new_old: np.ndarray) -> Scene:
        """The same scene with its mesh moved by ``T_new_old`` (materials unchanged)."""
        mesh = self.mesh.copy()
        mesh.apply_transform(T_new_old)
        return Scene(mesh, self.face_reflectance, self.face_albedo, self.face_texture_m)


@dataclass
class _SceneBuilder:
    """Collects primitive meshes with their materials and concatenates them once."""

    parts: list[trimesh.Trimesh] = field(default_factory=list)
    reflectance: list[np.ndarray] = field(default_factory=list)
    albedo: list[np.ndarray] = field(default_factory=list)
    texture_m: list[np.ndarray] = field(default_factory=list)

    def add(
        self,
        mesh: trimesh.Trimesh,
        *,
        reflectance: float,
        albedo: tuple[float, float, float] | np.ndarray = (0.6, 0.6, 0.6),
        texture_m: float = 0.0,
    ) -> None:
        n = len(mesh.faces)
        self.parts.append(mesh)
        self.reflectance.append(np.full(n, reflectance, np.float32))
        self.albedo.append(np.tile(np.asarray(albedo, np.float32), (n, 1)))
        self.texture_m.append(np.full(n, texture_m, np.float32))

    def add_arrays(
        self,
        mesh: trimesh.Trimesh,
        *,
        reflectance: np.ndarray,
        albedo: np.ndarray,
        texture_m: np.ndarray | None = None,
    ) -> None:
        """Add ``mesh`` with per-face materials: (F,) reflectance, (F, 3) albedo, (F,) texture."""
        n = len(mesh.faces)
        self.parts.append(mesh)
        self.reflectance.append(np.asarray(reflectance, np.float32).reshape(n))
        self.albedo.append(np.asarray(albedo, np.float32).reshape(n, 3))
        self.texture_m.append(
            np.zeros(n, np.float32) if texture_m is None else np.asarray(texture_m, np.float32)
        )

    def build(self) -> Scene:
        mesh = trimesh.util.concatenate(self.parts)
        return Scene(
            mesh=mesh,
            face_reflectance=np.concatenate(self.reflectance),
            face_albedo=np.concatenate(self.albedo),
            face_texture_m=np.concatenate(self.texture_m),
        )


def _pose_xy_yaw(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [x, y, z]
    return T


def _box(extents: tuple[float, float, float], T: np.ndarray) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents, transform=T)


# ---------------------------------------------------------------------------------------------
# Street scene
# ---------------------------------------------------------------------------------------------


def _resample_polyline(points: np.ndarray, spacing_m: float) -> np.ndarray:
    """Points along the polyline ``points`` (N, 3), evenly spaced by arc length."""
    if len(points) == 1:
        return points.copy()
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return points[:1].copy()
    s_new = np.arange(0.0, s[-1] + 1e-9, spacing_m)
    return np.stack([np.interp(s_new, s, points[:, k]) for k in range(3)], axis=1)


class _GroundHeight:
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


def _ground_mesh(
    path_xyz: np.ndarray, height: _GroundHeight, margin_m: float, cell_m: float
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


class _Footprints:
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


class _Instances:
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


class _StreetPath:
    """The driven path, resampled every ``SPACING_M`` along its arc length, with its frame.

    An open path is extended straight by ``extension_m`` before its start and after its end so
    that the street continues behind the first and beyond the last pose.
    """

    SPACING_M = 0.5

    def __init__(self, path_xyz: np.ndarray, extension_m: float) -> None:
        dense = _resample_polyline(path_xyz, self.SPACING_M)
        closed = len(path_xyz) > 2 and np.linalg.norm(path_xyz[-1] - path_xyz[0]) < 1.0
        if len(dense) >= 2 and not closed and extension_m > 0:
            k = round(extension_m / self.SPACING_M)
            steps = self.SPACING_M * np.arange(1, k + 1)[:, None]
            head_dir = _unit_xy(dense[min(4, len(dense) - 1)] - dense[0])
            tail_dir = _unit_xy(dense[-1] - dense[max(0, len(dense) - 5)])
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


def _unit_xy(v: np.ndarray) -> np.ndarray:
    d = np.array([v[0], v[1], 0.0])
    n = np.linalg.norm(d)
    return d / n if n > 1e-9 else np.array([1.0, 0.0, 0.0])


def _blob(rng: np.random.Generator) -> trimesh.Trimesh:
    """A lumpy unit sphere (tree crowns, bushes): an icosphere with jittered vertex radii."""
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=1.0)
    vertices = np.asarray(sphere.vertices) * rng.uniform(0.8, 1.15, (len(sphere.vertices), 1))
    return trimesh.Trimesh(vertices=vertices, faces=sphere.faces, process=False)


SIDEWALK_INNER_M = 4.5
"""Distance from the path to the kerb: parked cars stand inside it, poles and trees outside."""
SIDEWALK_WIDTH_M = 2.0
KERB_HEIGHT_M = 0.15


def street_scene(
    path_xyz: np.ndarray,
    *,
    seed: int = 0,
    sensor_height_m: float = 1.73,
    margin_m: float = 45.0,
    ground_cell_m: float = 2.0,
    extension_m: float = 40.0,
    relief_m: float = 0.0,
) -> Scene:
    """A street built along ``path_xyz`` (N, 3 sensor positions in a z-up world).

    Ground follows the path at ``sensor_height_m`` below it (so the road has the path's slopes,
    crests and dips: the real elevation profile for a KITTI trajectory), with a raised sidewalk
    behind a kerb on both sides; ``relief_m > 0`` adds hills up to that height away from the road
    (see :class:`_GroundHeight`), which the buildings and bushes stand on. Building blocks 8-30 m
    long stand behind it with 2-10 m gaps, varied setbacks, depths and heights, and facades with
    pilasters, ledges, balconies and entrance canopies at irregular spacing; parked cars line the
    kerbs in irregular runs, poles and trees stand every 10-25 m, and some blocks have a low wall
    or hedge in front. An open path is extended by ``extension_m`` at both ends so the street
    also continues behind the first pose. Nothing is placed on the path itself, and a place the
    path revisits keeps the objects of its first visit (footprints are reserved), so it is not
    built twice.
    """
    rng = np.random.default_rng([seed, 11])
    path = _StreetPath(np.asarray(path_xyz, np.float64), extension_m)
    height = _GroundHeight(path.xyz, sensor_height_m, relief_m, seed)
    footprints = _Footprints(path.xyz[:, :2])
    builder = _SceneBuilder()
    builder.add(
        _ground_mesh(path.xyz, height, margin_m, ground_cell_m),
        reflectance=0.15,
        albedo=(0.3, 0.3, 0.3),
    )
    boxes = _Instances(trimesh.creation.box(extents=(1.0, 1.0, 1.0)))
    cylinders = _Instances(trimesh.creation.cylinder(radius=1.0, height=1.0, sections=10))
    spheres = _Instances(_blob(np.random.default_rng([seed, 12])))
    sides = (1.0, -1.0)

    def facing_yaw(t: np.ndarray, side: float) -> float:
        """Yaw whose local +y points away from the path (local -y faces the street)."""
        return float(np.arctan2(t[1], t[0])) + (0.0 if side > 0 else np.pi)

    def ground_z(xy: np.ndarray) -> float:
        return float(height(xy)[0])

    def add_sidewalks() -> None:
        claimed: dict[tuple[int, int], float] = {}
        segment_m = 3.0
        for side in sides:
            for s in np.arange(segment_m / 2, path.length_m, segment_m):
                p, t, n = path.at(s, side)
                center = p + n * (SIDEWALK_INNER_M + SIDEWALK_WIDTH_M / 2)
                yaw = float(np.arctan2(t[1], t[0]))
                size = (segment_m + 0.1, SIDEWALK_WIDTH_M)
                if not footprints.clear_of_path(center, yaw, size, SIDEWALK_INNER_M - 0.3):
                    continue
                cells = set(map(tuple, np.floor(footprints._samples(center, yaw, size)).tolist()))
                if any(abs(claimed.get(c, s) - s) > 6.0 for c in cells):
                    continue  # a revisit: this stretch already has its sidewalk
                claimed.update({c: s for c in cells})
                z0 = ground_z(center)
                T = _pose_xy_yaw(center[0], center[1], z0 + (KERB_HEIGHT_M - 0.3) / 2, yaw)
                boxes.add((*size, KERB_HEIGHT_M + 0.3), T, reflectance=0.25, albedo=(0.5,) * 3)

    def add_facade(T: np.ndarray, width: float, depth: float, storeys: int) -> None:
        """Pilasters, ledges, balconies and an entrance canopy on the local -y face of a box
        whose local frame ``T`` sits at ground level in the middle of its footprint."""
        front = -depth / 2
        top = 3.0 * storeys
        if rng.random() < 0.65:  # pilasters at irregular spacing
            x = -width / 2 + rng.uniform(0.2, 2.0)
            while x < width / 2 - 0.3:
                w, out = rng.uniform(0.3, 0.8), rng.uniform(0.15, 0.45)
                boxes.add((w, out, top), T @ _pose_xy_yaw(x, front - out / 2, top / 2, 0.0), 0.5)
                x += rng.uniform(2.0, 6.5)
        ledges = rng.random() < 0.5
        for k in range(1, storeys):
            z = 3.0 * k
            if ledges:
                x0, x1 = sorted(rng.uniform(-width / 2, width / 2, 2))
                if rng.random() < 0.6:
                    x0, x1 = -width / 2, width / 2
                if x1 - x0 > 1.0:
                    ledge = _pose_xy_yaw((x0 + x1) / 2, front - 0.15, z, 0.0)
                    boxes.add((x1 - x0, 0.3, 0.25), T @ ledge, 0.5)
            if rng.random() < 0.45:
                for _ in range(int(rng.integers(1, 3))):
                    bw = rng.uniform(1.5, min(3.5, width - 0.6))
                    bx = rng.uniform(-width / 2 + bw / 2 + 0.3, width / 2 - bw / 2 - 0.3)
                    bd = rng.uniform(0.8, 1.2)
                    slab = _pose_xy_yaw(bx, front - bd / 2, z, 0.0)
                    rail = _pose_xy_yaw(bx, front - bd + 0.04, z + 0.55, 0.0)
                    boxes.add((bw, bd, 0.15), T @ slab, 0.45)
                    boxes.add((bw, 0.08, 1.0), T @ rail, 0.45)
        if rng.random() < 0.7:  # entrance canopy with a step below it
            cw, cd = rng.uniform(1.5, 3.5), rng.uniform(0.8, 1.2)
            cx = rng.uniform(-width / 2 + cw / 2 + 0.2, width / 2 - cw / 2 - 0.2)
            boxes.add((cw, cd, 0.2), T @ _pose_xy_yaw(cx, front - cd / 2, 2.8, 0.0), 0.45)
            boxes.add((cw, 0.6, 0.5), T @ _pose_xy_yaw(cx, front - 0.3, 0.1, 0.0), 0.3)

    def place_building(s: float, side: float, width: float, row: int) -> bool:
        p, t, n = path.at(s, side)
        setback = rng.uniform(6.5, 12.0) if row == 0 else rng.uniform(24.0, 34.0)
        depth = rng.uniform(8.0, 16.0)
        storeys = int(rng.integers(2, 8))
        center = p + n * (setback + depth / 2)
        yaw = facing_yaw(t, side)
        # Reserve the protrusions in front too (up to 1.2 m).
        if not footprints.try_place(center, yaw, (width + 0.3, depth + 2.6), clearance_m=5.1):
            return False
        z0 = ground_z(center)
        h = 3.0 * storeys + rng.uniform(0.5, 1.5)
        T = _pose_xy_yaw(center[0], center[1], z0, yaw)
        shade = rng.uniform(0.35, 0.85)
        below = 1.0 + relief_m  # on a hillside the footprint's corners lie lower than its centre
        boxes.add(
            (width, depth, h + below),
            T @ _pose_xy_yaw(0.0, 0.0, (h - below) / 2, 0.0),
            reflectance=rng.uniform(0.2, 0.6),
            albedo=(shade,) * 3,
        )
        add_facade(T, width, depth, storeys)
        if rng.random() < 0.3:  # low wall or hedge in front, with openings
            x = -width / 2
            while x < width / 2 - 1.0:
                length = min(rng.uniform(2.0, 8.0), width / 2 - x)
                wall_h, thick = rng.uniform(0.5, 1.3), rng.uniform(0.2, 0.7)
                wall = _pose_xy_yaw(x + length / 2, -depth / 2 - 1.6, wall_h / 2 - 0.1, 0.0)
                boxes.add((length, thick, wall_h + 0.1), T @ wall, 0.35, (0.3, 0.45, 0.3))
                x += length + rng.uniform(1.0, 4.0)
        return True

    def add_buildings(row: int) -> None:
        """Row 0 lines the street; row 1 stands behind it, seen through the gaps."""
        for side in sides:
            s = rng.uniform(0.0, 6.0)
            while s < path.length_m:
                width = rng.uniform(8.0, 30.0)
                while width >= 6.0 and not place_building(s + width / 2, side, width, row):
                    width *= 0.6
                s += (width if width >= 6.0 else 2.0) + rng.uniform(2.0, 10.0)

    def add_bushes() -> None:
        """Clumps of bushes in front gardens and in the gaps between buildings."""
        for side in sides:
            s = rng.uniform(0.0, 8.0)
            while s < path.length_m:
                p, t, n = path.at(s, side)
                base = p + n * rng.uniform(6.8, 9.0)
                for _ in range(int(rng.integers(1, 4))):
                    r = rng.uniform(0.4, 1.0)
                    c = base + t * rng.uniform(-1.5, 1.5) + n * rng.uniform(0.0, 1.0)
                    if footprints.try_place(c, 0.0, (1.6 * r, 1.6 * r), clearance_m=5.5):
                        bush = _pose_xy_yaw(c[0], c[1], ground_z(c) + 0.5 * r, rng.uniform(0, 6.3))
                        spheres.add((r * rng.uniform(1.0, 1.8), r, r), bush, 0.3, (0.2, 0.45, 0.2))
                s += rng.uniform(3.0, 12.0)

    def add_cars() -> None:
        for side in sides:
            s = rng.uniform(0.0, 10.0)
            while s < path.length_m:
                if rng.random() < 0.2:  # an empty stretch of kerb
                    s += rng.uniform(4.0, 15.0)
                    continue
                length, width = rng.uniform(3.8, 4.9), rng.uniform(1.65, 1.9)
                p, t, n = path.at(s + length / 2, side)
                c = p + n * rng.uniform(2.95, SIDEWALK_INNER_M - width / 2 - 0.05)
                yaw = float(np.arctan2(t[1], t[0])) + rng.normal(0.0, 0.03)
                if footprints.try_place(c, yaw, (length + 0.2, width + 0.1), clearance_m=2.0):
                    z0 = ground_z(c)
                    paint = rng.uniform(0.1, 0.9, 3)
                    body_h, cabin_h = rng.uniform(0.8, 1.0), rng.uniform(0.45, 0.65)
                    cabin_l = rng.uniform(0.45, 0.6) * length
                    body = _pose_xy_yaw(c[0], c[1], z0 + 0.25 + body_h / 2, yaw)
                    cabin = body @ _pose_xy_yaw(
                        rng.uniform(-0.3, 0.1), 0.0, (body_h + cabin_h) / 2, 0.0
                    )
                    boxes.add((length, width, body_h), body, 0.8, paint)
                    boxes.add((cabin_l, width - 0.15, cabin_h), cabin, 0.3, paint)
                s += length + rng.uniform(0.6, 3.0)

    def add_poles_and_trees() -> None:
        for side in sides:
            s = rng.uniform(0.0, 15.0)
            while s < path.length_m:
                p, _, n = path.at(s, side)
                if rng.random() < 0.45:
                    c = p + n * rng.uniform(4.8, 5.3)
                    if footprints.try_place(c, 0.0, (0.4, 0.4), clearance_m=4.0):
                        pole_h = rng.uniform(5.0, 8.5)
                        z0 = ground_z(c)
                        cyl = _pose_xy_yaw(c[0], c[1], z0 + pole_h / 2 - 0.2, 0.0)
                        cylinders.add((0.12, 0.12, pole_h), cyl, 0.7)
                        if rng.random() < 0.5:  # lamp arm over the sidewalk
                            yaw = float(np.arctan2(-n[1], -n[0]))
                            arm = _pose_xy_yaw(c[0], c[1], z0 + pole_h - 0.4, yaw)
                            boxes.add((1.2, 0.15, 0.15), arm @ _pose_xy_yaw(0.5, 0, 0, 0), 0.7)
                else:
                    crown_r = rng.uniform(1.2, 2.2)
                    c = p + n * rng.uniform(5.2, 6.2)
                    crown_ok = footprints.clear_of_path(c, 0.0, (2 * crown_r,) * 2, 2.6)
                    if crown_ok and footprints.try_place(c, 0.0, (0.6, 0.6), clearance_m=4.0):
                        z0 = ground_z(c)
                        trunk_h = rng.uniform(2.5, 3.5)
                        trunk = _pose_xy_yaw(c[0], c[1], z0 + trunk_h / 2 - 0.15, 0.0)
                        cylinders.add((0.18, 0.18, trunk_h + 0.3), trunk, 0.35, (0.4, 0.3, 0.2))
                        squash = rng.uniform(0.75, 1.25)
                        crown = _pose_xy_yaw(c[0], c[1], z0 + trunk_h + crown_r * 0.8, 0.0)
                        crown = crown @ _pose_xy_yaw(0, 0, 0, rng.uniform(0, np.pi))
                        spheres.add(
                            (crown_r, crown_r * rng.uniform(0.8, 1.0), crown_r * squash),
                            crown,
                            0.25,
                            (0.2, 0.5, 0.2),
                        )
                s += rng.uniform(10.0, 25.0) / 2  # a pole or a tree about every 10-25 m

    # The street layout first (kerbs, cars, poles, trees), then the buildings behind them.
    add_sidewalks()
    add_cars()
    add_poles_and_trees()
    add_buildings(row=0)
    add_bushes()
    add_buildings(row=1)
    for instances in (boxes, cylinders, spheres):
        instances.add_to(builder)
    return builder.build()


# ---------------------------------------------------------------------------------------------
# Indoor room
# ---------------------------------------------------------------------------------------------

ROOM_SIZE_M = (6.0, 5.0, 3.0)


def room_scene(*, seed: int = 0) -> Scene:
    """A 6 x 5 x 3 m room centred on the origin (floor at z = 0), textured for ORB features.

    Walls, floor and ceiling, posters, a cabinet, a shelf, a sofa, a desk with legs, a round side
    table with a sphere, a bin and a pillar. Everything stays more than ~1.3 m away from the
    vertical axis through the room centre except a small round table, so a camera circling at
    radius <= 1 m above 1.2 m height never enters geometry.
    """
    rng = np.random.default_rng([seed, 7])
    sx, sy, sz = ROOM_SIZE_M
    t = 0.1
    b = _SceneBuilder()

    def colour() -> np.ndarray:
        return rng.uniform(0.25, 0.95, 3)

    b.add(
        _box((sx, sy, t), _pose_xy_yaw(0, 0, -t / 2, 0)),
        reflectance=0.3,
        albedo=colour(),
        texture_m=0.3,
    )
    b.add(
        _box((sx, sy, t), _pose_xy_yaw(0, 0, sz + t / 2, 0)),
        reflectance=0.3,
        albedo=colour(),
        texture_m=0.6,
    )
    b.add(
        _box((sx + 2 * t, t, sz), _pose_xy_yaw(0, sy / 2 + t / 2, sz / 2, 0)),
        reflectance=0.3,
        albedo=colour(),
        texture_m=0.25,
    )
    b.add(
        _box((sx + 2 * t, t, sz), _pose_xy_yaw(0, -sy / 2 - t / 2, sz / 2, 0)),
        reflectance=0.3,
        albedo=colour(),
        texture_m=0.25,
    )
    b.add(
        _box((t, sy, sz), _pose_xy_yaw(sx / 2 + t / 2, 0, sz / 2, 0)),
        reflectance=0.3,
        albedo=colour(),
        texture_m=0.25,
    )
    b.add(
        _box((t, sy, sz), _pose_xy_yaw(-sx / 2 - t / 2, 0, sz / 2, 0)),
        reflectance=0.3,
        albedo=colour(),
        texture_m=0.25,
    )

    # Posters: thin slabs 1 cm off the walls with a fine, high-contrast texture.
    walls = [
        ((0, sy / 2, 0), np.pi / 2, sx),
        ((0, -sy / 2, 0), -np.pi / 2, sx),
        ((sx / 2, 0, 0), 0.0, sy),
        ((-sx / 2, 0, 0), np.pi, sy),
    ]
    for (wx, wy, _), yaw, length in walls:
        for _ in range(3):
            w, h = rng.uniform(0.5, 1.2), rng.uniform(0.4, 0.9)
            along = rng.uniform(-length / 2 + w, length / 2 - w)
            zc = rng.uniform(1.1, 2.3)
            inward = -np.array([np.cos(yaw), np.sin(yaw)])
            along_dir = np.array([-np.sin(yaw), np.cos(yaw)])
            c = np.array([wx, wy]) + inward * 0.01 + along_dir * along
            b.add(
                _box((0.01, w, h), _pose_xy_yaw(c[0], c[1], zc, yaw)),
                reflectance=0.5,
                albedo=colour(),
                texture_m=rng.uniform(0.04, 0.1),
            )

    # Cabinet, shelf and sofa against the walls.
    b.add(
        _box((1.2, 0.5, 1.8), _pose_xy_yaw(-1.6, sy / 2 - 0.25, 0.9, 0)),
        reflectance=0.4,
        albedo=colour(),
        texture_m=0.15,
    )
    b.add(
        _box((0.4, 1.6, 1.2), _pose_xy_yaw(sx / 2 - 0.2, -1.0, 0.6, 0)),
        reflectance=0.4,
        albedo=colour(),
        texture_m=0.12,
    )
    for d in range(3):
        b.add(
            _box((0.42, 1.62, 0.03), _pose_xy_yaw(sx / 2 - 0.2, -1.0, 0.3 + 0.35 * d, 0)),
            reflectance=0.5,
            albedo=colour(),
            texture_m=0.05,
        )
    b.add(
        _box((2.0, 0.9, 0.45), _pose_xy_yaw(0.6, -sy / 2 + 0.45, 0.225, 0)),
        reflectance=0.3,
        albedo=colour(),
        texture_m=0.1,
    )
    b.add(
        _box((2.0, 0.25, 0.85), _pose_xy_yaw(0.6, -sy / 2 + 0.125, 0.425, 0)),
        reflectance=0.3,
        albedo=colour(),
        texture_m=0.1,
    )

    # Desk with four legs.
    dx, dy = -sx / 2 + 0.8, -1.2
    b.add(
        _box((1.4, 0.8, 0.04), _pose_xy_yaw(dx, dy, 0.74, np.pi / 2)),
        reflectance=0.4,
        albedo=colour(),
        texture_m=0.08,
    )
    for ox in (-0.62, 0.62):
        for oy in (-0.32, 0.32):
            leg = _box((0.05, 0.05, 0.72), _pose_xy_yaw(dx + oy, dy + ox, 0.36, 0))
            b.add(leg, reflectance=0.4, albedo=(0.2, 0.2, 0.2))
    box_on_desk = _box((0.3, 0.25, 0.2), _pose_xy_yaw(dx, dy + 0.2, 0.86, 0.3))
    b.add(box_on_desk, reflectance=0.4, albedo=colour(), texture_m=0.05)

    # Round side table at the centre with a sphere on it, a bin, a pillar, a big ball.
    table = trimesh.creation.cylinder(radius=0.3, height=0.6, sections=32)
    table.apply_translation([0, 0, 0.3])
    b.add(table, reflectance=0.4, albedo=colour(), texture_m=0.07)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.15)
    ball.apply_translation([0.05, 0.0, 0.75])
    b.add(ball, reflectance=0.4, albedo=colour(), texture_m=0.04)
    bin_ = trimesh.creation.cylinder(radius=0.2, height=0.5, sections=24)
    bin_.apply_translation([1.8, 1.6, 0.25])
    b.add(bin_, reflectance=0.4, albedo=colour(), texture_m=0.06)
    pillar = trimesh.creation.cylinder(radius=0.18, height=sz, sections=24)
    pillar.apply_translation([2.0, -0.2, sz / 2])
    b.add(pillar, reflectance=0.4, albedo=colour(), texture_m=0.1)
    big_ball = trimesh.creation.icosphere(subdivisions=3, radius=0.35)
    big_ball.apply_translation([-2.2, 1.4, 0.35])
    b.add(big_ball, reflectance=0.4, albedo=colour(), texture_m=0.08)
    return b.build()
