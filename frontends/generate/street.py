"""The generated LiDAR street: ground following the path, kerbs, cars, poles, trees and buildings
with detailed facades, in one of three layouts (:data:`StreetStyle`).

Every random choice is drawn from generators seeded by ``seed``; street objects reserve their
footprints, so revisiting a place along a trajectory sees the structures of the first visit, not a
second copy.
"""

from __future__ import annotations

from typing import Literal, get_args

import numpy as np
import trimesh

from frontends.generate.scene import Scene, _pose_xy_yaw, _SceneBuilder
from frontends.generate.street_parts import (
    KERB_HEIGHT_M,
    SIDEWALK_INNER_M,
    SIDEWALK_WIDTH_M,
    Footprints,
    GroundHeight,
    Instances,
    StreetPath,
    blob,
    ground_mesh,
)

StreetStyle = Literal["standard", "sparse", "periodic"]
"""Layouts of the generated street: ``standard`` (irregular buildings, cars, poles and trees),
``sparse`` (long blank walls far apart, a rare building, few cars), ``periodic`` (one identical
building and tree repeating every :data:`PERIOD_M`)."""
STREET_STYLES: tuple[str, ...] = get_args(StreetStyle)
PERIOD_M = 16.0
"""Period of the ``periodic`` street along the path (a 12 m building and a 4 m gap)."""


def street_scene(
    path_xyz: np.ndarray,
    *,
    seed: int = 0,
    sensor_height_m: float = 1.73,
    margin_m: float = 45.0,
    ground_cell_m: float = 2.0,
    extension_m: float = 40.0,
    relief_m: float = 0.0,
    style: StreetStyle = "standard",
) -> Scene:
    """A street built along ``path_xyz`` (N, 3 sensor positions in a z-up world).

    Ground follows the path at ``sensor_height_m`` below it (so the road has the path's slopes,
    crests and dips: the real elevation profile for a KITTI trajectory), with a raised sidewalk
    behind a kerb on both sides; ``relief_m > 0`` adds hills up to that height away from the road
    (see :class:`GroundHeight`), which the buildings and bushes stand on. Building blocks 8-30 m
    long stand behind it with 2-10 m gaps, varied setbacks, depths and heights, and facades with
    pilasters, ledges, balconies and entrance canopies at irregular spacing; parked cars line the
    kerbs in irregular runs, poles and trees stand every 10-25 m, and some blocks have a low wall
    or hedge in front. An open path is extended by ``extension_m`` at both ends so the street
    also continues behind the first pose. Nothing is placed on the path itself, and a place the
    path revisits keeps the objects of its first visit (footprints are reserved), so it is not
    built twice.

    ``style`` varies the layout for robustness checks (see :data:`StreetStyle`): ``standard`` is
    the street above; ``sparse`` keeps the kerbs but has long blank walls with a rare building
    between them, few cars and poles, and no second row; ``periodic`` repeats one identical
    building (facade included) and one tree every :data:`PERIOD_M` along both sides, with no
    cars, the aliasing of a regular avenue.
    """
    if style not in STREET_STYLES:
        raise ValueError(f"unknown street style '{style}'; choose one of {STREET_STYLES}")
    rng = np.random.default_rng([seed, 11])
    path = StreetPath(np.asarray(path_xyz, np.float64), extension_m)
    height = GroundHeight(path.xyz, sensor_height_m, relief_m, seed)
    footprints = Footprints(path.xyz[:, :2])
    builder = _SceneBuilder()
    builder.add(
        ground_mesh(path.xyz, height, margin_m, ground_cell_m),
        reflectance=0.15,
        albedo=(0.3, 0.3, 0.3),
    )
    boxes = Instances(trimesh.creation.box(extents=(1.0, 1.0, 1.0)))
    cylinders = Instances(trimesh.creation.cylinder(radius=1.0, height=1.0, sections=10))
    spheres = Instances(blob(np.random.default_rng([seed, 12])))
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

    def add_facade(
        T: np.ndarray, width: float, depth: float, storeys: int, rng: np.random.Generator = rng
    ) -> None:
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

    def add_cars(empty_stretch: float = 0.2) -> None:
        for side in sides:
            s = rng.uniform(0.0, 10.0)
            while s < path.length_m:
                if rng.random() < empty_stretch:  # an empty stretch of kerb
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

    def add_blank_walls() -> None:
        """Sparse style: long blank walls (30-80 m) 10-20 m off the path, 30-80 m apart, and
        now and then a plain building with a facade in a gap."""
        for side in sides:
            s = rng.uniform(0.0, 30.0)
            while s < path.length_m:
                length = rng.uniform(30.0, 80.0)
                setback = rng.uniform(10.0, 20.0)
                for k in np.arange(0.0, length, 10.0):  # 10 m pieces follow the curves
                    p, t, n = path.at(s + k + 5.0, side)
                    c = p + n * (setback + 0.5)
                    yaw = facing_yaw(t, side)
                    if footprints.try_place(c, yaw, (10.2, 1.0), clearance_m=5.1):
                        wall = _pose_xy_yaw(c[0], c[1], ground_z(c) + 2.0, yaw)
                        boxes.add((10.2, 1.0, 5.0 + relief_m), wall, 0.4, (0.6,) * 3)
                s += length + rng.uniform(30.0, 80.0)
                if rng.random() < 0.3:
                    place_building(s - 15.0, side, rng.uniform(8.0, 14.0), row=0)

    def add_periodic() -> None:
        """Periodic style: the same building, facade and tree every ``PERIOD_M`` per side."""
        for side in sides:
            for s in np.arange(PERIOD_M / 2, path.length_m, PERIOD_M):
                p, t, n = path.at(s, side)
                yaw = facing_yaw(t, side)
                width, depth, storeys = PERIOD_M - 4.0, 12.0, 4
                center = p + n * (8.0 + depth / 2)
                if footprints.try_place(center, yaw, (width + 0.3, depth + 2.6), clearance_m=5.1):
                    z0 = ground_z(center)
                    T = _pose_xy_yaw(center[0], center[1], z0, yaw)
                    body = _pose_xy_yaw(0.0, 0.0, (12.5 - 1.0 - relief_m) / 2, 0.0)
                    boxes.add((width, depth, 13.5 + relief_m), T @ body, 0.4, (0.6,) * 3)
                    add_facade(T, width, depth, storeys, np.random.default_rng([seed, 14]))
                tree_xy = path.at(s + PERIOD_M / 2, side)
                c = tree_xy[0] + tree_xy[2] * 5.7
                if footprints.try_place(c, 0.0, (0.6, 0.6), clearance_m=4.0):
                    z0 = ground_z(c)
                    trunk = _pose_xy_yaw(c[0], c[1], z0 + 1.35, 0.0)
                    cylinders.add((0.18, 0.18, 3.3), trunk, 0.35, (0.4, 0.3, 0.2))
                    crown = _pose_xy_yaw(c[0], c[1], z0 + 4.4, 0.0)
                    spheres.add((1.6, 1.6, 1.6), crown, 0.25, (0.2, 0.5, 0.2))

    # The street layout first (kerbs, cars, poles, trees), then the buildings behind them.
    add_sidewalks()
    if style == "standard":
        add_cars()
        add_poles_and_trees()
        add_buildings(row=0)
        add_bushes()
        add_buildings(row=1)
    elif style == "sparse":
        add_cars(empty_stretch=0.8)
        add_blank_walls()
    else:
        add_periodic()
    for instances in (boxes, cylinders, spheres):
        instances.add_to(builder)
    return builder.build()
