"""Procedural training patches with exact signed distance, as a depth sensor would see them.

Everything is in voxel units (vu) around one voxel centre at the origin: the encoder sees the points
inside the 2V cube ``[-1, 1]^3`` (each point belongs to its 8 nearest voxels) and the decoder is
queried on the same cube (the meshing lattice reaches half a voxel beyond the voxel's faces).

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

Sign. Normals point towards the sensor and the sensor is in free space, so the SDF is positive in
front of an observed surface (free space) and negative behind it (solid), as in the map.

Observation. One or two sensors sit in free space 1.5 to 40 vu away (closer inside small
cavities), looking at the patch. A surface point is observed when it faces a sensor (incidence
below ``max_incidence_deg``) and the ray to the sensor is not blocked (sphere tracing on the SDF).
The encoder's points are drawn from the observed points with uneven density
(``cos(incidence) / range^2`` times a random exponential ramp, sometimes cut by a random plane,
as at the border of a depth image), get noise along the viewing ray (sigma drawn per patch up to
``2 * point_noise_vu``), and normals tilted by up to ``normal_tilt_deg`` and then oriented
towards the sensor.

Supervision of one-sided observations. An SDF sample is supervised only when its nearest surface
point faces a sensor (occlusion is not tested for samples) and lies within ``0.1`` vu of the cube.
So behind a thin wall seen from one side, only the part of the wall closer to the observed face is
supervised (negative); the far half of the wall and the space behind it are not, since nothing in
the patch can tell how thick the wall is. Likewise the far side of a sphere or box seen from one
side is not supervised. Supervised samples are balanced: half with SDF > 0, half with SDF <= 0
(drawn with replacement when one side has too few).

All sampling is vectorised in torch and deterministic by seed (numpy for the per-patch scene
parameters, a torch generator for the rest).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field

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


class PatchConfig(BaseModel):
    """How training patches are generated (all lengths in voxel units)."""

    model_config = ConfigDict(extra="forbid")

    n_points: int = Field(128, ge=1, description="Surface points given to the encoder per patch.")
    n_queries: int = Field(4096, ge=2, description="SDF samples per patch (half in, half out).")
    point_noise_vu: float = Field(
        0.025, ge=0.0, description="Typical position noise; per patch sigma ~ U(0, 2x this)."
    )
    normal_tilt_deg: float = Field(
        40.0, ge=0.0, le=89.0, description="Largest tilt of a noisy normal from the true normal."
    )
    max_incidence_deg: float = Field(
        85.0,
        gt=0.0,
        lt=90.0,
        description="Surfaces seen more obliquely than this are not observed.",
    )
    sdf_clamp_vu: float = Field(
        0.5,
        gt=0.0,
        description="Training clamp of the SDF; union samples whose SDF is only a bound are kept "
        "when that bound is below -sdf_clamp_vu (the clamped target is then exact).",
    )
    uniform_query_fraction: float = Field(
        0.25, ge=0.0, le=1.0, description="Fraction of candidate SDF samples uniform in the cube."
    )
    query_offset_scales_vu: tuple[float, ...] = Field(
        (0.01, 0.03, 0.08, 0.2, 0.5),
        description="Gaussian offset scales of near-surface SDF samples around surface points.",
    )
    shell_candidates: int = Field(
        6144,
        ge=256,
        description="Uniform candidates per patch from which surface points are drawn.",
    )
    surface_pool: int = Field(
        512, ge=16, description="Surface points per patch kept for visibility tests and sampling."
    )
    march_steps: int = Field(32, ge=4, description="Sphere-tracing steps of a visibility test.")
    kind_weights: dict[str, float] | None = Field(
        None, description="Relative frequency of each kind in PATCH_KINDS (None: built-in mix)."
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


def _safe_norm(x: torch.Tensor) -> torch.Tensor:
    return torch.sqrt((x * x).sum(-1).clamp_min(1e-12))


def _box_sdf(x: torch.Tensor, half: torch.Tensor, rounding: torch.Tensor) -> torch.Tensor:
    q = x.abs() - half
    inner = q.amax(-1)  # written with where() so the gradient is defined on the surface itself
    return torch.where(inner > 0, _safe_norm(q.clamp_min(0.0)), inner) - rounding


def _cylinder_sdf(x: torch.Tensor, radius: torch.Tensor, half_height: torch.Tensor) -> torch.Tensor:
    """Capped cylinder along local z (exact)."""
    dr = _safe_norm(x[..., :2]) - radius
    dz = x[..., 2].abs() - half_height
    d = torch.stack([dr, dz], dim=-1)
    inner = d.amax(-1)
    return torch.where(inner > 0, _safe_norm(d.clamp_min(0.0)), inner)


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

    def sdf_grad_flat(
        self, x: torch.Tensor, patch: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Union SDF and its unit gradient (the outward normal direction) at flat points."""
        with torch.enable_grad():
            xg = x.detach().requires_grad_(True)
            d = self.sdf_flat(xg, patch)
            (g,) = torch.autograd.grad(d.sum(), xg)
        return d.detach(), g / _safe_norm(g).unsqueeze(-1)

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
        g = g / _safe_norm(g).unsqueeze(-1)
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


def _torch_scenes(arrays: dict[str, np.ndarray]) -> Scenes:
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
    return _torch_scenes(arrays)


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


@dataclass
class PatchBatch:
    """A batch of B training patches (torch, float32, voxel units, voxel centre at the origin).

    Attributes:
        points: (B, N, 3) noisy observed surface points.
        normals: (B, N, 3) noisy unit normals pointing towards the sensor.
        point_mask: (B, N) valid points (all True unless a patch saw nothing).
        queries: (B, Q, 3) SDF sample positions in ``[-1, 1]^3``.
        sdf: (B, Q) exact signed distance (positive in free space), or a bound below
            ``-sdf_clamp_vu`` where only a bound is known.
        sdf_mask: (B, Q) samples to supervise.
        sensors: (B, S, 3) sensor positions; (B, S) ``sensor_mask`` says which exist.
        kind: (B,) index into :data:`PATCH_KINDS`.
    """

    points: torch.Tensor
    normals: torch.Tensor
    point_mask: torch.Tensor
    queries: torch.Tensor
    sdf: torch.Tensor
    sdf_mask: torch.Tensor
    sensors: torch.Tensor
    sensor_mask: torch.Tensor
    kind: torch.Tensor

    def to(self, device: torch.device | str) -> PatchBatch:
        return PatchBatch(**{f.name: getattr(self, f.name).to(device) for f in fields(self)})


def _unit(x: torch.Tensor) -> torch.Tensor:
    return x / _safe_norm(x).unsqueeze(-1)


def _random_unit(shape: tuple[int, ...], g: torch.Generator) -> torch.Tensor:
    return _unit(torch.randn(*shape, 3, generator=g))


def _tilt(n: torch.Tensor, max_angle: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """Tilt unit vectors by an angle uniform in [0, max_angle] towards a random direction."""
    other = _random_unit(n.shape[:-1], g)
    perp = _unit(other - (other * n).sum(-1, keepdim=True) * n)
    angle = torch.rand(n.shape[:-1], generator=g) * max_angle
    return torch.cos(angle).unsqueeze(-1) * n + torch.sin(angle).unsqueeze(-1) * perp


def _pick(weights: torch.Tensor, count: int, g: torch.Generator) -> torch.Tensor:
    """Indices drawn with replacement per row ``∝ weights``; rows of zeros draw uniformly."""
    w = weights.clamp_min(0.0)
    w = torch.where(w.sum(-1, keepdim=True) > 0, w, torch.ones_like(w))
    return torch.multinomial(w, count, replacement=True, generator=g)


def _gather(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    if x.dim() == idx.dim():
        return torch.gather(x, 1, idx)
    return torch.gather(x, 1, idx.unsqueeze(-1).expand(*idx.shape, x.shape[-1]))


def _surface_pool(
    scenes: Scenes, batch: int, cfg: PatchConfig, g: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Points on the surface inside the cube, roughly uniform by area: (B, P, 3), normals, valid.

    Uniform candidates within a thin shell around the surface are projected onto it.
    """
    shell = 0.06
    m = cfg.shell_candidates
    x = torch.rand(batch * m, 3, generator=g) * 2.1 - 1.05
    patch = torch.arange(batch).repeat_interleave(m)
    near = (scenes.sdf_flat(x, patch).abs() < shell).nonzero(as_tuple=True)[0]
    d, grad, exact = scenes.sdf_exact_flat(x[near], patch[near])
    p = x[near] - d.unsqueeze(-1) * grad
    ok_near = exact & (p.abs() <= 1.0).all(-1)
    ok = torch.zeros(batch * m, dtype=torch.bool).index_put((near,), ok_near)
    projected = torch.zeros(batch * m, 3).index_put((near,), p)
    normals = torch.zeros(batch * m, 3).index_put((near,), grad)
    ok = ok.view(batch, m)
    projected, normals = projected.view(batch, m, 3), normals.view(batch, m, 3)
    # keep a random subset of the accepted candidates (top-k of random keys among the accepted)
    keys = torch.rand(ok.shape, generator=g) + ok.float()
    idx = keys.topk(cfg.surface_pool, dim=1).indices
    valid = _gather(ok, idx)
    points, normals = _gather(projected, idx), _gather(normals, idx)
    # one projection step is exact for an exact SDF; re-project once to absorb float error
    return points - scenes.sdf(points).unsqueeze(-1) * normals, normals, valid


def _place_sensors(
    scenes: Scenes,
    arrays: dict[str, np.ndarray],
    pool: torch.Tensor,
    pool_normals: torch.Tensor,
    pool_valid: torch.Tensor,
    cfg: PatchConfig,
    g: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Sensors in free space looking at the patch: (B, S, 3) and (B, S) mask."""
    batch = pool.shape[0]
    anchors = torch.from_numpy(arrays["anchors"])
    # snap each intended anchor to the nearest valid surface point of the pool
    # (skipping points whose normal is ambiguous, e.g. at the apex of a concave edge)
    clean = pool_valid & (scenes.sdf(pool + 0.02 * pool_normals) > 0.015)
    clean = torch.where(clean.any(-1, keepdim=True), clean, pool_valid)
    dist = torch.cdist(anchors, pool) + (~clean).unsqueeze(1).float() * 1e3
    idx = dist.argmin(-1)
    base, normal = _gather(pool, idx), _gather(pool_normals, idx)
    # candidate view directions within 75 deg of the normal (the first is the preferred one) and
    # the normal itself; take the preferred one when it has enough free space, else the freest
    n_dirs = 8
    max_angle = torch.full((batch, MAX_SENSORS, n_dirs), math.radians(75.0))
    dirs = _tilt(normal.unsqueeze(2).expand(-1, -1, n_dirs, -1), max_angle, g)
    dirs = torch.cat([dirs, normal.unsqueeze(2)], dim=2)  # (B, S, D, 3)
    want = torch.exp(
        torch.empty(batch, MAX_SENSORS).uniform_(math.log(1.5), math.log(40.0), generator=g)
    )
    start = base + 0.02 * normal
    origin = start.unsqueeze(2).expand_as(dirs).reshape(batch, -1, 3)
    reach = want.unsqueeze(2).expand(dirs.shape[:-1]).reshape(batch, -1)
    hit = scenes.march(origin, dirs.reshape(batch, -1, 3), reach, cfg.march_steps)
    free = torch.minimum(reach, 0.8 * hit).reshape(dirs.shape[:-1])  # (B, S, D)
    preferred_ok = free[..., 0] >= torch.minimum(want, torch.ones_like(want))
    best = torch.where(preferred_ok, torch.zeros_like(want, dtype=torch.long), free.argmax(-1))
    length = torch.gather(free, 2, best.unsqueeze(-1)).squeeze(-1)
    chosen = torch.gather(dirs, 2, best[..., None, None].expand(-1, -1, 1, 3)).squeeze(2)
    sensors = start + length.unsqueeze(-1) * chosen
    n_sensors = torch.from_numpy(arrays["n_sensors"])
    mask = torch.arange(MAX_SENSORS).unsqueeze(0) < n_sensors.unsqueeze(1)
    return sensors, mask & (length > 0.05)


def _visibility(
    scenes: Scenes,
    points: torch.Tensor,
    normals: torch.Tensor,
    sensors: torch.Tensor,
    sensor_mask: torch.Tensor,
    cos_min: float,
    steps: int | None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per sensor: observed (B, M, S) and cosine of incidence (B, M, S).

    ``steps=None`` tests facing only; otherwise also occlusion by sphere tracing.
    """
    to_sensor = sensors.unsqueeze(1) - points.unsqueeze(2)  # (B, M, S, 3)
    rng = _safe_norm(to_sensor)
    cos = (normals.unsqueeze(2) * to_sensor).sum(-1) / rng
    seen = (cos > cos_min) & sensor_mask.unsqueeze(1)
    if steps is not None:
        b, m, s = seen.shape
        origin = (points + 0.02 * normals).unsqueeze(2).expand(b, m, s, 3).reshape(b, m * s, 3)
        direction = (to_sensor / rng.unsqueeze(-1)).reshape(b, m * s, 3)
        hit = scenes.march(origin, direction, rng.reshape(b, m * s) - 0.05, steps)
        seen = seen & torch.isinf(hit).reshape(b, m, s)
    return seen, cos


def _observe(
    scenes: Scenes,
    pool: torch.Tensor,
    pool_normals: torch.Tensor,
    pool_valid: torch.Tensor,
    sensors: torch.Tensor,
    sensor_mask: torch.Tensor,
    cfg: PatchConfig,
    g: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Noisy points and normals as the sensors see them: (B, N, 3), (B, N, 3), (B, N) mask."""
    batch = pool.shape[0]
    cos_min = math.cos(math.radians(cfg.max_incidence_deg))
    seen, cos = _visibility(
        scenes, pool, pool_normals, sensors, sensor_mask, cos_min, cfg.march_steps
    )
    seen = seen & pool_valid.unsqueeze(-1)
    # each surface point is reported by one of the sensors that see it (random among them)
    sensor_pick = (torch.rand(seen.shape, generator=g) + seen.float()).argmax(-1)  # (B, P)
    seen_any = seen.any(-1)
    cos_pick = torch.gather(cos, 2, sensor_pick.unsqueeze(-1)).squeeze(-1)
    sensor_pos = _gather(sensors, sensor_pick)
    rng = _safe_norm(sensor_pos - pool)
    # uneven density: projected area / range^2, a random exponential ramp, sometimes a cut
    ramp = torch.randn(batch, 1, 3, generator=g) * 1.0
    density = cos_pick.clamp_min(0.0) / rng.square() * torch.exp((pool * ramp).sum(-1))
    cut_dir = _random_unit((batch, 1), g)
    cut_off = torch.rand(batch, 1, generator=g) * 1.2 - 0.2
    do_cut = torch.rand(batch, 1, generator=g) < 0.2
    kept = ~do_cut | ((pool * cut_dir).sum(-1) < cut_off)
    weight = density * (seen_any & kept).float()
    weight = torch.where((weight > 0).any(-1, keepdim=True), weight, density * seen_any.float())
    idx = _pick(weight, cfg.n_points, g)
    point_mask = _gather(seen_any, idx)
    points, normals = _gather(pool, idx), _gather(pool_normals, idx)
    sensor_pos = _gather(sensor_pos, idx)
    view = _unit(points - sensor_pos)
    sigma = torch.rand(batch, 1, generator=g) * 2.0 * cfg.point_noise_vu
    noisy = points + (torch.randn(points.shape[:-1], generator=g) * sigma).unsqueeze(-1) * view
    noisy = noisy + 0.1 * sigma.unsqueeze(-1) * torch.randn(points.shape, generator=g)
    max_tilt = torch.rand(batch, 1, generator=g) * math.radians(cfg.normal_tilt_deg)
    tilted = _tilt(normals, max_tilt.expand(normals.shape[:-1]), g)
    facing = (tilted * (sensor_pos - noisy)).sum(-1, keepdim=True)
    tilted = torch.where(facing < 0, -tilted, tilted)
    return noisy, tilted, point_mask


def _queries(
    scenes: Scenes,
    pool: torch.Tensor,
    pool_valid: torch.Tensor,
    sensors: torch.Tensor,
    sensor_mask: torch.Tensor,
    cfg: PatchConfig,
    g: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Balanced supervised SDF samples: positions (B, Q, 3), SDF (B, Q), mask (B, Q)."""
    batch = pool.shape[0]
    n_cand = 2 * cfg.n_queries
    n_uniform = round(cfg.uniform_query_fraction * n_cand)
    n_near = n_cand - n_uniform
    base = _gather(pool, _pick(pool_valid.float(), n_near, g))
    scales = torch.tensor(cfg.query_offset_scales_vu)
    scale = scales[torch.randint(len(scales), (batch, n_near), generator=g)]
    near = base + torch.randn(batch, n_near, 3, generator=g) * scale.unsqueeze(-1)
    uniform = torch.rand(batch, n_uniform, 3, generator=g) * 2.0 - 1.0
    x = torch.cat([near, uniform], dim=1).clamp(-1.0, 1.0)
    d, grad, exact = scenes.sdf_exact(x)
    nearest = x - d.unsqueeze(-1) * grad
    cos_min = math.cos(math.radians(cfg.max_incidence_deg))
    seen, _ = _visibility(scenes, nearest, grad, sensors, sensor_mask, cos_min, None)
    in_reach = (nearest.abs() <= 1.1).all(-1)
    ok = seen.any(-1) & in_reach & (exact | (d <= -cfg.sdf_clamp_vu))
    half = cfg.n_queries // 2
    pos = _pick((ok & (d > 0)).float(), half, g)
    neg = _pick((ok & (d <= 0)).float(), cfg.n_queries - half, g)
    # a patch with no supervised sample on one side takes both halves from the other side
    has_neg = (ok & (d <= 0)).any(-1, keepdim=True)
    has_pos = (ok & (d > 0)).any(-1, keepdim=True)
    neg = torch.where(has_neg, neg, _pick((ok & (d > 0)).float(), neg.shape[1], g))
    pos = torch.where(has_pos, pos, _pick((ok & (d <= 0)).float(), pos.shape[1], g))
    idx = torch.cat([pos, neg], dim=1)
    return _gather(x, idx), _gather(d, idx), _gather(ok, idx)


def generate_patches_with_scenes(
    batch: int, seed: int, cfg: PatchConfig | None = None
) -> tuple[PatchBatch, Scenes]:
    """:func:`generate_patches` and the scenes the patches were cut from (for checks)."""
    cfg = cfg or PatchConfig()
    rng = np.random.default_rng(seed)
    g = torch.Generator().manual_seed(int(rng.integers(2**62)))
    arrays, kinds = build_scenes(rng, batch, cfg.kind_weights)
    scenes = _torch_scenes(arrays)
    with torch.no_grad():
        pool, pool_normals, pool_valid = _surface_pool(scenes, batch, cfg, g)
        sensors, sensor_mask = _place_sensors(
            scenes, arrays, pool, pool_normals, pool_valid, cfg, g
        )
        points, normals, point_mask = _observe(
            scenes, pool, pool_normals, pool_valid, sensors, sensor_mask, cfg, g
        )
        queries, sdf, sdf_mask = _queries(scenes, pool, pool_valid, sensors, sensor_mask, cfg, g)
    patches = PatchBatch(
        points=points,
        normals=normals,
        point_mask=point_mask,
        queries=queries,
        sdf=sdf,
        sdf_mask=sdf_mask,
        sensors=sensors,
        sensor_mask=sensor_mask,
        kind=torch.from_numpy(kinds),
    )
    return patches, scenes


def generate_patches(batch: int, seed: int, cfg: PatchConfig | None = None) -> PatchBatch:
    """Generate ``batch`` patches, deterministic for a given ``seed`` and config."""
    return generate_patches_with_scenes(batch, seed, cfg)[0]
