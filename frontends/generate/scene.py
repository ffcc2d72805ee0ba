"""Scene meshes for generated sequences: a street along a path (LiDAR) and a textured room (RGB-D).

A :class:`Scene` is one triangle mesh plus per-face material attributes (LiDAR reflectance, base
colour and texture cell size) that the sensors read at the hit triangle. Every random choice is
drawn from generators seeded by ``seed`` and, for street objects, by the world cell they stand in,
so that revisiting a place along a trajectory sees the same structures.
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
    """Ground height as the inverse-distance-weighted path height minus the sensor height."""

    def __init__(self, path_xyz: np.ndarray, sensor_height_m: float) -> None:
        self._tree = cKDTree(path_xyz[:, :2])
        self._z = path_xyz[:, 2] - sensor_height_m
        self._k = min(8, len(path_xyz))

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        xy = np.atleast_2d(xy)
        dist, idx = self._tree.query(xy, k=self._k)
        if self._k == 1:
            return self._z[idx]
        w = 1.0 / np.maximum(dist, 0.5) ** 2
        return (w * self._z[idx]).sum(axis=1) / w.sum(axis=1)


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

    def try_place(
        self, center_xy: np.ndarray, yaw: float, size_xy: tuple[float, float], clearance_m: float
    ) -> bool:
        """Reserve the rectangle if it is ``clearance_m`` away from the path and free."""
        hx, hy = size_xy[0] / 2, size_xy[1] / 2
        u = np.linspace(-hx, hx, max(2, int(np.ceil(2 * hx / 0.5)) + 1))
        v = np.linspace(-hy, hy, max(2, int(np.ceil(2 * hy / 0.5)) + 1))
        gu, gv = np.meshgrid(u, v)
        c, s = np.cos(yaw), np.sin(yaw)
        pts = np.stack(
            [
                center_xy[0] + c * gu.ravel() - s * gv.ravel(),
                center_xy[1] + s * gu.ravel() + c * gv.ravel(),
            ],
            axis=1,
        )
        dist, _ = self._path.query(pts)
        if dist.min() < clearance_m:
            return False
        cells = set(map(tuple, np.floor(pts).astype(np.int64).tolist()))
        if cells & self._occupied:
            return False
        self._occupied |= cells
        return True


def _cell_rng(
    seed: int, kind: int, xy: np.ndarray, cell_m: float
) -> tuple[tuple, np.random.Generator]:
    key = (kind, *np.floor(xy / cell_m).astype(np.int64).tolist())
    entropy = [seed, kind, int(key[1]) + 2**31, int(key[2]) + 2**31]
    return key, np.random.default_rng(entropy)


def street_scene(
    path_xyz: np.ndarray,
    *,
    seed: int = 0,
    sensor_height_m: float = 1.73,
    margin_m: float = 45.0,
    ground_cell_m: float = 2.0,
) -> Scene:
    """A street built along ``path_xyz`` (N, 3 sensor positions in a z-up world).

    Ground follows the path at ``sensor_height_m`` below it; building blocks with balconies or
    ledges line both sides with varied setbacks, sizes and heights; poles, parked cars and trees
    stand between road and facades. Nothing is placed on the path itself. Objects are keyed by
    the world cell they stand in, so a revisited place gets the same objects, not a second copy.
    """
    path_xyz = np.asarray(path_xyz, np.float64)
    dense = _resample_polyline(path_xyz, 0.5)
    height = _GroundHeight(dense, sensor_height_m)
    footprints = _Footprints(dense[:, :2])
    builder = _SceneBuilder()
    builder.add(
        _ground_mesh(dense, height, margin_m, ground_cell_m),
        reflectance=0.15,
        albedo=(0.3, 0.3, 0.3),
    )

    tangents = np.gradient(dense[:, :2], axis=0)
    norms = np.linalg.norm(tangents, axis=1, keepdims=True)
    tangents = np.where(norms > 1e-9, tangents / np.maximum(norms, 1e-12), [1.0, 0.0])
    lefts = np.stack([-tangents[:, 1], tangents[:, 0]], axis=1)
    used: set[tuple] = set()

    def place_candidates(every: int, kind: int, cell_m: float, lateral: float, make) -> None:
        for i in range(0, len(dense), every):
            for side in (1.0, -1.0):
                p, t, n = dense[i, :2], tangents[i], lefts[i] * side
                key, rng = _cell_rng(seed, kind, p + n * lateral, cell_m)
                if key in used:
                    continue
                if make(p, t, n, rng):
                    used.add(key)

    def make_building(p, t, n, rng) -> bool:
        setback = rng.uniform(6.5, 11.0)
        width, depth = rng.uniform(7.0, 16.0), rng.uniform(6.0, 14.0)
        storeys = int(rng.integers(2, 7))
        h = storeys * 3.0 + rng.uniform(0.5, 1.5)
        center = p + n * (setback + depth / 2)
        yaw = float(np.arctan2(t[1], t[0]))
        if not footprints.try_place(center, yaw, (width + 0.5, depth + 0.5), clearance_m=5.5):
            return False
        z0 = float(height(center)[0]) - 1.0
        T = _pose_xy_yaw(center[0], center[1], z0 + (h + 1.0) / 2, yaw)
        shade = rng.uniform(0.35, 0.85)
        builder.add(
            _box((width, depth, h + 1.0), T), reflectance=rng.uniform(0.2, 0.6), albedo=(shade,) * 3
        )
        # Front face faces the path: in the box frame that is -y when n is +y (left of tangent).
        front_sign = -1.0 if np.dot(n, [-np.sin(yaw), np.cos(yaw)]) > 0 else 1.0
        base_local = 1.0 - (h + 1.0) / 2  # ground level in the box frame
        if rng.random() < 0.5:  # balconies: a slab and a railing in front of some storeys
            for k in range(1, storeys):
                for _ in range(int(rng.integers(1, 3))):
                    bw = rng.uniform(1.8, 3.2)
                    bx = rng.uniform(-width / 2 + bw / 2 + 0.3, width / 2 - bw / 2 - 0.3)
                    floor_z = base_local + 3.0 * k
                    slab = _pose_xy_yaw(bx, front_sign * (depth / 2 + 0.5), floor_z, 0.0)
                    rail = _pose_xy_yaw(bx, front_sign * (depth / 2 + 0.96), floor_z + 0.55, 0.0)
                    builder.add(_box((bw, 1.0, 0.15), T @ slab), reflectance=0.45)
                    builder.add(_box((bw, 0.08, 1.0), T @ rail), reflectance=0.45)
        else:  # ledges along the whole facade at every storey
            for k in range(1, storeys):
                ledge = _pose_xy_yaw(
                    0.0, front_sign * (depth / 2 + 0.15), base_local + 3.0 * k, 0.0
                )
                builder.add(_box((width, 0.3, 0.25), T @ ledge), reflectance=0.5)
        return True

    def make_pole(p, t, n, rng) -> bool:
        lateral = rng.uniform(3.8, 4.8)
        c = p + n * lateral
        if not footprints.try_place(c, 0.0, (0.4, 0.4), clearance_m=3.3):
            return False
        z0 = float(height(c)[0])
        pole_h = rng.uniform(5.0, 8.0)
        pole = trimesh.creation.cylinder(radius=0.12, height=pole_h, sections=12)
        pole.apply_translation([c[0], c[1], z0 + pole_h / 2 - 0.2])
        builder.add(pole, reflectance=0.7)
        return True

    def make_car(p, t, n, rng) -> bool:
        if rng.random() < 0.35:
            return False
        lateral = rng.uniform(3.0, 3.6)
        c = p + n * lateral
        yaw = float(np.arctan2(t[1], t[0]))
        if not footprints.try_place(c, yaw, (4.4, 1.9), clearance_m=2.0):
            return False
        z0 = float(height(c)[0])
        paint = rng.uniform(0.1, 0.9, 3)
        builder.add(
            _box((4.3, 1.8, 0.9), _pose_xy_yaw(c[0], c[1], z0 + 0.25 + 0.45, yaw)),
            reflectance=0.8,
            albedo=paint,
        )
        builder.add(
            _box((2.2, 1.6, 0.55), _pose_xy_yaw(c[0], c[1], z0 + 1.15 + 0.275, yaw)),
            reflectance=0.3,
            albedo=paint,
        )
        return True

    def make_tree(p, t, n, rng) -> bool:
        if rng.random() < 0.4:
            return False
        lateral = rng.uniform(5.0, 6.0)
        c = p + n * lateral
        crown_r = rng.uniform(1.2, 2.0)
        if not footprints.try_place(c, 0.0, (2 * crown_r, 2 * crown_r), clearance_m=2.5):
            return False
        z0 = float(height(c)[0])
        trunk_h = rng.uniform(2.5, 3.5)
        trunk = trimesh.creation.cylinder(radius=0.18, height=trunk_h + 0.3, sections=10)
        trunk.apply_translation([c[0], c[1], z0 + trunk_h / 2 - 0.15])
        crown = trimesh.creation.icosphere(subdivisions=2, radius=crown_r)
        crown.apply_translation([c[0], c[1], z0 + trunk_h + crown_r * 0.8])
        builder.add(trunk, reflectance=0.35, albedo=(0.4, 0.3, 0.2))
        builder.add(crown, reflectance=0.25, albedo=(0.2, 0.5, 0.2))
        return True

    # Small objects first (they stand closer to the road), then the facades behind them.
    place_candidates(every=40, kind=1, cell_m=10.0, lateral=4.3, make=make_pole)
    place_candidates(every=14, kind=2, cell_m=5.0, lateral=3.3, make=make_car)
    place_candidates(every=24, kind=3, cell_m=6.0, lateral=5.5, make=make_tree)
    place_candidates(every=8, kind=4, cell_m=6.0, lateral=12.0, make=make_building)
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
