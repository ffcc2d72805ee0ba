"""Scene meshes for generated sequences: the :class:`Scene` record, its builder and the textured
room (RGB-D); the LiDAR street is in :mod:`frontends.generate.street`.

A :class:`Scene` is one triangle mesh plus per-face material attributes (LiDAR reflectance, base
colour and texture cell size) that the sensors read at the hit triangle. Every random choice is
drawn from generators seeded by ``seed``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh


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

    def box(extents, x: float, y: float, z: float, yaw: float, reflectance: float, texture_m):
        """A box with its own random colour (drawn in the order the boxes are added)."""
        mesh = _box(extents, _pose_xy_yaw(x, y, z, yaw))
        b.add(mesh, reflectance=reflectance, albedo=colour(), texture_m=texture_m)

    # Floor, ceiling and the four walls: (extents, x, y, z, texture cell).
    for extents, x, y, z, texture_m in (
        ((sx, sy, t), 0, 0, -t / 2, 0.3),
        ((sx, sy, t), 0, 0, sz + t / 2, 0.6),
        ((sx + 2 * t, t, sz), 0, sy / 2 + t / 2, sz / 2, 0.25),
        ((sx + 2 * t, t, sz), 0, -sy / 2 - t / 2, sz / 2, 0.25),
        ((t, sy, sz), sx / 2 + t / 2, 0, sz / 2, 0.25),
        ((t, sy, sz), -sx / 2 - t / 2, 0, sz / 2, 0.25),
    ):
        box(extents, x, y, z, 0, 0.3, texture_m)

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

    # Cabinet, shelf (three boards), sofa (seat and back) and the desk's top.
    dx, dy = -sx / 2 + 0.8, -1.2
    box((1.2, 0.5, 1.8), -1.6, sy / 2 - 0.25, 0.9, 0, 0.4, 0.15)
    box((0.4, 1.6, 1.2), sx / 2 - 0.2, -1.0, 0.6, 0, 0.4, 0.12)
    for d in range(3):
        box((0.42, 1.62, 0.03), sx / 2 - 0.2, -1.0, 0.3 + 0.35 * d, 0, 0.5, 0.05)
    box((2.0, 0.9, 0.45), 0.6, -sy / 2 + 0.45, 0.225, 0, 0.3, 0.1)
    box((2.0, 0.25, 0.85), 0.6, -sy / 2 + 0.125, 0.425, 0, 0.3, 0.1)
    box((1.4, 0.8, 0.04), dx, dy, 0.74, np.pi / 2, 0.4, 0.08)

    # The desk's four legs and a box on it.
    for ox in (-0.62, 0.62):
        for oy in (-0.32, 0.32):
            leg = _box((0.05, 0.05, 0.72), _pose_xy_yaw(dx + oy, dy + ox, 0.36, 0))
            b.add(leg, reflectance=0.4, albedo=(0.2, 0.2, 0.2))
    box((0.3, 0.25, 0.2), dx, dy + 0.2, 0.86, 0.3, 0.4, 0.05)

    # Round side table at the centre with a sphere on it, a bin, a pillar, a big ball.
    cylinder, sphere = trimesh.creation.cylinder, trimesh.creation.icosphere
    for mesh, centre, texture_m in (
        (cylinder(radius=0.3, height=0.6, sections=32), [0, 0, 0.3], 0.07),
        (sphere(subdivisions=3, radius=0.15), [0.05, 0.0, 0.75], 0.04),
        (cylinder(radius=0.2, height=0.5, sections=24), [1.8, 1.6, 0.25], 0.06),
        (cylinder(radius=0.18, height=sz, sections=24), [2.0, -0.2, sz / 2], 0.1),
        (sphere(subdivisions=3, radius=0.35), [-2.2, 1.4, 0.35], 0.08),
    ):
        mesh.apply_translation(centre)
        b.add(mesh, reflectance=0.4, albedo=colour(), texture_m=texture_m)
    return b.build()
