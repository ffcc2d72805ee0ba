"""Procedural scenes with exact signed distance for the prior's training patches.

Geometry. A patch is a union (``min``) of up to :data:`MAX_PRIMITIVES` primitives whose own SDF is
exact: rounded boxes (planes, 90-degree convex edges and corners, boxes, thin walls, spheres),
capped cylinders, and wedges (two-plane edges of any opening angle). Every primitive can be
complemented (``-sdf``), which turns it into the matching concave shape (room corners, concave
edges, pipe interiors, domes) and stays exact. Scene kinds (:data:`PATCH_KINDS`) combine them:
planes, edges, box corners, boxes, thin walls (one or both sides observed), steps, cylinders and
spheres with radii from 0.2 to 20 vu, and random unions.

Exactness of unions. ``min`` of exact SDFs is exact outside the union but only an upper bound inside
it (the true value is more negative). For a point ``x`` inside, the bound comes from primitive
``j``; its nearest surface point ``p = x - d_j grad d_j`` lies on the union's boundary exactly when
``p`` is not inside another primitive, and then the bound is attained (the true distance to the
free space is at least ``|d_j|`` and ``p`` realises it). Samples that fail this test are only
kept when the bound is already below ``-sdf_clamp_vu`` (the clamped target is then exact);
the rest are dropped.

All scene parameters are drawn with numpy from a seeded generator; :class:`Scenes` evaluates the
SDF in torch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

MAX_PRIMITIVES = 3
MAX_SENSORS = 2
_BIG = 100.0  # half-extent in vu of "infinite" boxes (planes, walls); exact and float32-safe
_INACTIVE = 1.0e3

BOX, CYLINDER, WEDGE = 0, 1, 2

PATCH_KINDS: tuple[str, ...] = (
    "plane",
    "edge",
    "box_corner",
    "box",
    "thin_wall",
    "step",
    "cylinder",
    "sphere",
    "union",
)


_DEFAULT_KIND_WEIGHTS = {
    "plane": 0.08,
    "edge": 0.12,
    "box_corner": 0.1,
    "box": 0.12,
    "thin_wall": 0.12,
    "step": 0.1,
    "cylinder": 0.12,
    "sphere": 0.1,
    "union": 0.14,
}


# ---------------------------------------------------------------------------------------------
# Scenes: batched primitives with exact SDF
# ---------------------------------------------------------------------------------------------


def safe_norm(x: torch.Tensor) -> torch.Tensor:
    return torch.sqrt((x * x).sum(-1).clamp_min(1e-12))


def _box_sdf(x: torch.Tensor, half: torch.Tensor, rounding: torch.Tensor) -> torch.Tensor:
    q = x.abs() - half
    inner = q.amax(-1)  # written with where() so the gradient is defined on the surface itself
    return torch.where(inner > 0, safe_norm(q.clamp_min(0.0)), inner) - rounding


def _cylinder_sdf(x: torch.Tensor, radius: torch.Tensor, half_height: torch.Tensor) -> torch.Tensor:
    """Capped cylinder along local z (exact)."""
    dr = safe_norm(x[..., :2]) - radius
    dz = x[..., 2].abs() - half_height
    d = torch.stack([dr, dz], dim=-1)
    inner = d.amax(-1)
    return torch.where(inner > 0, safe_norm(d.clamp_min(0.0)), inner)


def _wedge_sdf(x: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Solid wedge of opening angle ``alpha <= pi`` around local -z, extruded along local y."""
    s, c = torch.sin(alpha / 2), torch.cos(alpha / 2)
    px, pz = x[..., 0], x[..., 2]
    side = [px * c + pz * s, -px * c + pz * s]  # signed distances to the two face planes
    along = [px * s - pz * c, -px * s - pz * c]  # positions along the two boundary rays
    apex = torch.sqrt((px * px + pz * pz).clamp_min(1e-12))
    ray = [torch.where(a >= 0, f.abs(), apex) for f, a in zip(side, along, strict=True)]
    inside = (side[0] <= 0) & (side[1] <= 0)
    return torch.where(inside, torch.maximum(side[0], side[1]), torch.minimum(ray[0], ray[1]))


@dataclass
class Scenes:
    """A batch of B scenes, each a union of up to K primitives (torch tensors).

    Attributes:
        kind: (B, K) primitive type (BOX, CYLINDER, WEDGE).
        params: (B, K, 4) box: half-extents and rounding; cylinder: radius, half-height; wedge:
            opening angle (radians).
        sign: (B, K) +1 for the solid primitive, -1 for its complement.
        active: (B, K) whether the slot is used.
        R: (B, K, 3, 3) rotation taking primitive-local directions to patch coordinates.
        t: (B, K, 3) primitive origin in patch coordinates (vu).
    """

    kind: torch.Tensor
    params: torch.Tensor
    sign: torch.Tensor
    active: torch.Tensor
    R: torch.Tensor
    t: torch.Tensor

    def slot_sdf_flat(self, x: torch.Tensor, patch: torch.Tensor) -> torch.Tensor:
        """SDF of every primitive at points ``x (P, 3)`` of patches ``patch (P,)``: ``(P, K)``.

        Only active (point, primitive) pairs are evaluated, each with its own formula; inactive
        slots give a large value.
        """
        out = torch.full((x.shape[0], self.kind.shape[1]), _INACTIVE, dtype=x.dtype)
        pi, si = self.active[patch].nonzero(as_tuple=True)
        b = patch[pi]
        R, prm, kind = self.R[b, si], self.params[b, si], self.kind[b, si]
        local = ((x[pi] - self.t[b, si]).unsqueeze(-2) @ R).squeeze(-2)
        d = torch.zeros(len(pi), dtype=x.dtype)
        for code in (BOX, CYLINDER, WEDGE):
            m = (kind == code).nonzero(as_tuple=True)[0]
            if len(m) == 0:
                continue
            lm, pm = local[m], prm[m]
            if code == BOX:
                dm = _box_sdf(lm, pm[:, :3], pm[:, 3])
            elif code == CYLINDER:
                dm = _cylinder_sdf(lm, pm[:, 0], pm[:, 1])
            else:
                dm = _wedge_sdf(lm, pm[:, 0])
            d = d.index_put((m,), dm)
        d = d * self.sign[b, si]
        return out.index_put((pi, si), d)

    def sdf_flat(self, x: torch.Tensor, patch: torch.Tensor) -> torch.Tensor:
        """Union SDF at ``x (P, 3)`` of patches ``patch (P,)``; exact outside, a bound inside."""
        return self.slot_sdf_flat(x, patch).amin(-1)

    def slot_sdf(self, x: torch.Tensor) -> torch.Tensor:
        """SDF of every primitive: ``x (B, M, 3) -> (B, M, K)``."""
        b, m, _ = x.shape
        patch = torch.arange(b).repeat_interleave(m)
        return self.slot_sdf_flat(x.reshape(-1, 3), patch).reshape(b, m, -1)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """SDF of the union ``(B, M)``; exact outside, an upper bound inside (see module doc)."""
        return self.slot_sdf(x).amin(-1)

    def sdf_exact_flat(
        self, x: torch.Tensor, patch: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Union SDF, unit gradient and where the value is exact (not only a bound); flat points."""
        with torch.enable_grad():
            xg = x.detach().requires_grad_(True)
            slots = self.slot_sdf_flat(xg, patch)
            d = slots.amin(-1)
            (g,) = torch.autograd.grad(d.sum(), xg)
        d, slots = d.detach(), slots.detach()
        g = g / safe_norm(g).unsqueeze(-1)
        exact = d >= 0
        inside = (~exact).nonzero(as_tuple=True)[0]
        if len(inside):
            owner = slots[inside].argmin(-1, keepdim=True)
            nearest = x[inside] - d[inside].unsqueeze(-1) * g[inside]
            others = self.slot_sdf_flat(nearest, patch[inside]).scatter(-1, owner, _INACTIVE)
            exact = exact.index_put((inside,), others.amin(-1) >= -1e-4)
        return d, g, exact

    def sdf_exact(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Batched :meth:`sdf_exact_flat`: ``x (B, M, 3)`` -> SDF, unit gradient, exact mask."""
        b, m, _ = x.shape
        patch = torch.arange(b).repeat_interleave(m)
        d, g, exact = self.sdf_exact_flat(x.reshape(-1, 3), patch)
        return d.reshape(b, m), g.reshape(b, m, 3), exact.reshape(b, m)

    def march(
        self, origin: torch.Tensor, direction: torch.Tensor, max_t: torch.Tensor, steps: int
    ) -> torch.Tensor:
        """Sphere tracing from ``origin (B, M, 3)`` along unit ``direction`` up to ``max_t (B, M)``.

        Returns the hit distance, or +inf where nothing is hit before ``max_t``. Rays that escape
        or hit are dropped from later steps.
        """
        b, m, _ = origin.shape
        o, v = origin.reshape(-1, 3), direction.reshape(-1, 3)
        limit = max_t.reshape(-1)
        patch = torch.arange(b).repeat_interleave(m)
        t = torch.zeros_like(limit)
        result = torch.full_like(limit, math.inf)
        live = torch.arange(len(limit))
        for _ in range(steps):
            if len(live) == 0:
                break
            tl = t[live]
            d = self.sdf_flat(o[live] + tl.unsqueeze(-1) * v[live], patch[live])
            hit = d < 1e-3
            result[live[hit]] = tl[hit]
            tl = tl + d.clamp_min(2e-3)
            t[live] = tl
            live = live[~hit & (tl < limit[live])]
        return result.reshape(b, m)


def torch_scenes(arrays: dict[str, np.ndarray]) -> Scenes:
    return Scenes(
        kind=torch.from_numpy(arrays["kind"]).long(),
        params=torch.from_numpy(arrays["params"]).float(),
        sign=torch.from_numpy(arrays["sign"]).float(),
        active=torch.from_numpy(arrays["active"]).bool(),
        R=torch.from_numpy(arrays["R"]).float(),
        t=torch.from_numpy(arrays["t"]).float(),
    )


def primitive_scene(
    kind: int,
    params: list[float],
    R: np.ndarray | None = None,
    t: np.ndarray | None = None,
    complement: bool = False,
) -> Scenes:
    """A batch of one scene holding one primitive (for tests and inspection)."""
    arrays = _empty_arrays(1)
    arrays["kind"][0, 0] = kind
    arrays["params"][0, 0, : len(params)] = params
    arrays["sign"][0, 0] = -1.0 if complement else 1.0
    arrays["active"][0, 0] = True
    arrays["R"][0, 0] = np.eye(3) if R is None else R
    arrays["t"][0, 0] = 0.0 if t is None else t
    return torch_scenes(arrays)


# ---------------------------------------------------------------------------------------------
# Scene builder (numpy, one patch at a time; cheap)
# ---------------------------------------------------------------------------------------------


def _empty_arrays(batch: int) -> dict[str, np.ndarray]:
    return {
        "kind": np.zeros((batch, MAX_PRIMITIVES), np.int64),
        "params": np.zeros((batch, MAX_PRIMITIVES, 4), np.float32),
        "sign": np.ones((batch, MAX_PRIMITIVES), np.float32),
        "active": np.zeros((batch, MAX_PRIMITIVES), bool),
        "R": np.tile(np.eye(3, dtype=np.float32), (batch, MAX_PRIMITIVES, 1, 1)),
        "t": np.zeros((batch, MAX_PRIMITIVES, 3), np.float32),
        "anchors": np.zeros((batch, MAX_SENSORS, 3), np.float32),
        "n_sensors": np.ones(batch, np.int64),
    }


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _log_uniform(rng: np.random.Generator, low: float, high: float) -> float:
    return float(np.exp(rng.uniform(np.log(low), np.log(high))))


@dataclass
class _Prim:
    kind: int
    params: tuple[float, ...]
    R: np.ndarray  # local -> canonical
    t: np.ndarray
    sign: float = 1.0


def _box_surface_point(rng: np.random.Generator, half: np.ndarray, rounding: float) -> np.ndarray:
    """A point on a (rounded) box surface: a vertex, an edge point or a face point."""
    s = rng.choice([-1.0, 1.0], size=3)
    p = s * half
    free = rng.permutation(3)[: rng.integers(0, 3)]  # 0 free axes: vertex, 1: edge, 2: face
    p[free] = rng.uniform(-1, 1, size=len(free)) * half[free]
    normal = s.copy()
    normal[free] = 0.0
    return p + rounding * normal / np.linalg.norm(normal)


def _prim_box(rng: np.random.Generator, complement: bool) -> tuple[_Prim, np.ndarray]:
    low = 0.5 if complement else 0.05
    half = np.array([_log_uniform(rng, low, 4.0) for _ in range(3)])
    rounding = rng.uniform(0, 0.5) * half.min() if rng.random() < 0.3 else 0.0
    anchor = _box_surface_point(rng, half, rounding)
    sign = -1.0 if complement else 1.0
    return _Prim(BOX, (*half, rounding), np.eye(3), np.zeros(3), sign), anchor


def _prim_sphere(rng: np.random.Generator, complement: bool) -> tuple[_Prim, np.ndarray]:
    radius = _log_uniform(rng, 1.0 if complement else 0.2, 20.0)
    direction = rng.normal(size=3)
    anchor = radius * direction / np.linalg.norm(direction)
    sign = -1.0 if complement else 1.0
    return _Prim(BOX, (0, 0, 0, radius), np.eye(3), np.zeros(3), sign), anchor


def _prim_cylinder(rng: np.random.Generator, complement: bool) -> tuple[_Prim, np.ndarray]:
    radius = _log_uniform(rng, 1.0 if complement else 0.2, 20.0)
    half_height = _BIG if (complement or rng.random() < 0.6) else _log_uniform(rng, 0.2, 5.0)
    theta = rng.uniform(0, 2 * np.pi)
    ring = np.array([np.cos(theta), np.sin(theta), 0.0])
    where = rng.random() if half_height < _BIG else 0.0
    if where < 0.6:  # side
        anchor = radius * ring + np.array([0, 0, rng.uniform(-1, 1) * min(half_height, 5.0)])
    elif where < 0.8:  # rim
        anchor = radius * ring + np.array([0, 0, rng.choice([-1, 1]) * half_height])
    else:  # cap
        anchor = np.sqrt(rng.random()) * radius * ring + np.array(
            [0, 0, rng.choice([-1, 1]) * half_height]
        )
    sign = -1.0 if complement else 1.0
    return _Prim(CYLINDER, (radius, half_height), np.eye(3), np.zeros(3), sign), anchor


def _prim_wedge(rng: np.random.Generator, complement: bool) -> tuple[_Prim, np.ndarray]:
    alpha = np.deg2rad(rng.uniform(40.0, 170.0))
    anchor = np.zeros(3)
    if rng.random() < 0.5:  # a point on one face instead of the edge itself
        s = rng.choice([-1.0, 1.0])
        anchor = rng.uniform(0, 1.0) * np.array([s * np.sin(alpha / 2), 0.0, -np.cos(alpha / 2)])
    return _Prim(WEDGE, (alpha,), np.eye(3), np.zeros(3), -1.0 if complement else 1.0), anchor


def _plane() -> _Prim:
    """Solid half-space z < 0."""
    return _Prim(BOX, (_BIG, _BIG, _BIG, 0.0), np.eye(3), np.array([0.0, 0.0, -_BIG]))


def _build_kind(rng: np.random.Generator, kind: str) -> tuple[list[_Prim], list[np.ndarray]]:
    """Primitives in a canonical frame and 1-2 sensor anchor points on their surface."""
    if kind == "plane":
        return [_plane()], [np.zeros(3)]
    if kind == "edge":
        prim, anchor = _prim_wedge(rng, complement=rng.random() < 0.45)
        return [prim], [anchor]
    if kind == "box_corner":
        complement = rng.random() < 0.5
        edge_only = rng.random() < 0.3
        half = np.array([_BIG, _BIG, _BIG])
        centre = -half.copy()
        if edge_only:
            centre[2] = 0.0
        prim = _Prim(BOX, (*half, 0.0), np.eye(3), centre, -1.0 if complement else 1.0)
        return [prim], [np.zeros(3)]
    if kind == "box":
        prim, anchor = _prim_box(rng, complement=rng.random() < 0.25)
        return [prim], [anchor]
    if kind == "thin_wall":
        thickness = _log_uniform(rng, 0.03, 0.6)
        centre = np.zeros(3)
        if rng.random() < 0.4:  # the wall ends inside the patch
            centre[0] = -_BIG
        prim = _Prim(BOX, (_BIG, _BIG, thickness / 2, 0.0), np.eye(3), centre)
        x = rng.uniform(-0.5, 0.0) if centre[0] < 0 else 0.0
        front = np.array([x, 0.0, thickness / 2])
        anchors = [front]
        if rng.random() < 0.5:
            anchors.append(np.array([x, 0.0, -thickness / 2]))
        return [prim], anchors
    if kind == "step":
        height = _log_uniform(rng, 0.1, 3.0)
        block = _Prim(
            BOX,
            (_BIG, _BIG, (height + 1.0) / 2, 0.0),
            np.eye(3),
            np.array([-_BIG, 0.0, (height - 1.0) / 2]),
        )
        anchor = np.array([0.0, 0.0, height if rng.random() < 0.5 else 0.0])
        anchor[0] += rng.uniform(-0.3, 0.3)
        return [_plane(), block], [anchor]
    if kind == "cylinder":
        prim, anchor = _prim_cylinder(rng, complement=rng.random() < 0.2)
        return [prim], [anchor]
    if kind == "sphere":
        prim, anchor = _prim_sphere(rng, complement=rng.random() < 0.2)
        return [prim], [anchor]
    if kind == "union":
        makers = [_prim_box, _prim_sphere, _prim_cylinder, _prim_wedge]
        prims, anchors = [], []
        for _ in range(rng.integers(2, MAX_PRIMITIVES + 1)):
            prim, anchor = makers[rng.integers(len(makers))](rng, False)
            # each primitive gets its own pose so that its anchor lands somewhere in the cube
            R = _random_rotation(rng)
            target = rng.uniform(-0.6, 0.6, size=3)
            prims.append(_Prim(prim.kind, prim.params, R, target - R @ anchor, prim.sign))
            anchors.append(target)
        return prims, anchors[:1]
    raise ValueError(f"unknown patch kind '{kind}' (one of {', '.join(PATCH_KINDS)})")


def build_scenes(
    rng: np.random.Generator, batch: int, kind_weights: dict[str, float] | None = None
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Random scene parameters for ``batch`` patches, and the index of each patch's kind."""
    weights = _DEFAULT_KIND_WEIGHTS if kind_weights is None else kind_weights
    unknown = set(kind_weights or {}) - set(PATCH_KINDS)
    if unknown:
        raise ValueError(f"unknown patch kinds {sorted(unknown)} (one of {', '.join(PATCH_KINDS)})")
    prob = np.array([weights.get(k, 0.0) for k in PATCH_KINDS], float)
    if prob.sum() <= 0:
        raise ValueError("kind_weights must give at least one kind a positive weight")
    kinds = rng.choice(len(PATCH_KINDS), size=batch, p=prob / prob.sum())
    arrays = _empty_arrays(batch)
    for b, k in enumerate(kinds):
        prims, anchors = _build_kind(rng, PATCH_KINDS[k])
        # global pose: random rotation, first anchor moved to a random point near the centre
        Q = _random_rotation(rng)
        shift = rng.uniform(-0.5, 0.5, size=3) - Q @ anchors[0]
        for i, prim in enumerate(prims):
            arrays["kind"][b, i] = prim.kind
            arrays["params"][b, i, : len(prim.params)] = prim.params
            arrays["sign"][b, i] = prim.sign
            arrays["active"][b, i] = True
            arrays["R"][b, i] = Q @ prim.R
            arrays["t"][b, i] = Q @ prim.t + shift
        for i, anchor in enumerate(anchors):
            arrays["anchors"][b, i] = Q @ anchor + shift
        arrays["n_sensors"][b] = len(anchors) if len(anchors) > 1 else 1 + (rng.random() < 0.25)
    return arrays, kinds


# ---------------------------------------------------------------------------------------------
# Patches
# ---------------------------------------------------------------------------------------------
