"""Procedural training patches with exact signed distance, as a depth sensor would see them.

Everything is in voxel units (vu) around one voxel centre at the origin: the encoder sees the points
inside the 2V cube ``[-1, 1]^3`` (each point belongs to its 8 nearest voxels) and the decoder is
queried on the same cube (the meshing lattice reaches half a voxel beyond the voxel's faces).

The scenes (geometry and exactness of unions) are :mod:`mapping.training.scenes`.

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

from mapping.training.scenes import MAX_SENSORS, Scenes, build_scenes, safe_norm, torch_scenes


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
        None,
        description="Relative frequency of each kind in scenes.PATCH_KINDS (None: built-in mix).",
    )


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
        kind: (B,) index into :data:`mapping.training.scenes.PATCH_KINDS`.
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
    return x / safe_norm(x).unsqueeze(-1)


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
    rng = safe_norm(to_sensor)
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
    rng = safe_norm(sensor_pos - pool)
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
    scenes = torch_scenes(arrays)
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
