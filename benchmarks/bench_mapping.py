"""Neural implicit map: transform fidelity (the paper's "two paths") and speed.

    python -m benchmarks.bench_mapping [--quick] [--threads N]

Writes ``benchmarks/results/mapping.md``.

1. Transform fidelity at V = 0.1 m on a synthetic room (a box room seen from inside with a table,
   a cabinet, a sphere and a cylinder; points sampled uniformly on its surfaces with 2 mm noise):
   encode at pose A and transform the map by D (path 1), versus encode the moved points (path 2);
   the two meshes are compared by mean surface distance both ways. Variants: ours (compact
   gaussian weights, first-order Jacobian term), ours without the Jacobian term, and the paper's
   scheme (uniform average of the 8 nearest sources, no usable Jacobian, targets within one voxel).
2. Speed: encoding one 640x480 depth frame (ray-cast in the room, subsampled), transform and
   re-gridding of a ~2,000-voxel submap, fuse and remove, meshing a ~20,000-voxel map; memory
   per voxel and per stored submap.
"""

from __future__ import annotations

import argparse
import logging
import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation

from benchmarks.harness.machine import section_header
from benchmarks.harness.paths import RESULTS_DIR
from benchmarks.harness.repeat import REPEATS, Timing, repeats_line, timed
from common.atomic_io import write_text_atomic
from mapping.analytic_prior import planar_prior
from mapping.compact_block import CompactBlock
from mapping.config import MapConfig
from mapping.encoding import encode_points
from mapping.networks import DEFAULT_WEIGHTS, PriorModel
from mapping.neural_map import NeuralMap, Submap
from mapping.transform import transform_block
from mapping.voxel_block import VoxelBlock
from slam.evaluation.metrics.mesh import mesh_metrics

log = logging.getLogger("benchmarks.bench_mapping")

RESULTS = RESULTS_DIR / "mapping.md"
V = 0.1
JACOBIAN_PAIRS = MapConfig().jacobian_pairs_per_voxel
TABLE_NODES = MapConfig().encoder_table_nodes


# ---------------------------------------------------------------------------- scene
def room_mesh(size: tuple[float, float, float]) -> trimesh.Trimesh:
    """A closed box room (normals inwards) with furniture; floor at z = 0."""
    sx, sy, sz = size
    shell = trimesh.creation.box(extents=size)
    shell.apply_translation([0.0, 0.0, sz / 2])
    shell.invert()
    parts = [shell]

    def box(extents, centre) -> trimesh.Trimesh:
        b = trimesh.creation.box(extents=extents)
        b.apply_translation(centre)
        return b

    parts.append(box((1.2, 0.8, 0.05), (0.3, -0.2, 0.75)))
    for dx in (-0.55, 0.55):
        for dy in (-0.35, 0.35):
            parts.append(box((0.06, 0.06, 0.725), (0.3 + dx, -0.2 + dy, 0.3625)))
    parts.append(box((0.6, 0.4, 1.8), (-sx / 2 + 0.3, sy / 2 - 0.2, 0.9)))
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    sphere.apply_translation([sx / 2 - 0.8, sy / 2 - 0.7, 0.3])
    parts.append(sphere)
    cylinder = trimesh.creation.cylinder(radius=0.2, height=1.0, sections=48)
    cylinder.apply_translation([-sx / 2 + 1.0, -sy / 2 + 0.7, 0.5])
    parts.append(cylinder)
    return trimesh.util.concatenate(parts)


def sample_surface(
    mesh: trimesh.Trimesh, density_per_m2: float, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    points, face = trimesh.sample.sample_surface(mesh, int(mesh.area * density_per_m2), seed=seed)
    rng = np.random.default_rng(seed)
    return points + rng.normal(scale=0.002, size=points.shape), mesh.face_normals[face]


def depth_frame_points(
    mesh: trimesh.Trimesh, width: int = 640, height: int = 480, keep: int = 30000
) -> tuple[np.ndarray, np.ndarray, int]:
    """Ray-cast one pinhole frame (f = 525 px) inside the room; subsample to ``keep`` points."""
    fx = 525.0
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    dirs_C = np.stack([(u - width / 2) / fx, (v - height / 2) / fx, np.ones_like(u)], -1).reshape(
        -1, 3
    )
    dirs_C /= np.linalg.norm(dirs_C, axis=1, keepdims=True)
    # camera at the room centre, 1.4 m high, looking along +x and slightly down (OpenCV axes)
    R_W_C = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    R_W_C = Rotation.from_rotvec([0.0, 0.25, 0.0]).as_matrix() @ R_W_C
    origin = np.array([-0.5, 0.0, 1.4])
    dirs_W = dirs_C @ R_W_C.T
    hits, ray, tri = mesh.ray.intersects_location(
        np.repeat(origin[None], len(dirs_W), 0), dirs_W, multiple_hits=False
    )
    normals = mesh.face_normals[tri]
    flip = np.einsum("ij,ij->i", normals, dirs_W[ray]) > 0
    normals[flip] *= -1.0
    rng = np.random.default_rng(0)
    pick = rng.choice(len(hits), size=min(keep, len(hits)), replace=False)
    noise = rng.normal(scale=0.002, size=(len(pick), 3))
    return hits[pick] + noise, normals[pick], len(hits)


# ---------------------------------------------------------------------------- helpers
def load_model() -> tuple[PriorModel, str]:
    if DEFAULT_WEIGHTS.is_file():
        model = PriorModel.load(DEFAULT_WEIGHTS)
        return model, f"shipped prior `{DEFAULT_WEIGHTS.name}` (identity {model.identity()})"
    return planar_prior(), (
        "**no trained weights shipped yet**: the analytic tangent-plane prior "
        "(`mapping.analytic_prior.planar_prior`; its SDF is the local plane of each voxel's "
        "points, so the first-order transform is exact on planes and these numbers flatter the "
        "method) - rerun once `mapping/weights/prior.pt` exists"
    )


def fresh_submap(block: VoxelBlock, submap_id: int = 0) -> Submap:
    """An unmoved submap holding ``block`` exactly (float32, every channel kept)."""
    if block.jacobians is None:
        zeros = torch.zeros(block.num_voxels, block.channels, 3, 3)
        block = VoxelBlock(block.keys, block.latents, block.weights, zeros)
    compact = CompactBlock.compress(block, block.channels, block.channels, "float32")
    return Submap(submap_id, np.eye(4), compact, np.eye(4))


# (latent dtype, latent rank, Jacobian rank, Jacobian storage) of a submap's stored original
STORAGE_VARIANTS = [
    ("float16 latents rank 4, int8 Jacobians rank 4 (default)", ("float16", 4, 4, "int8")),
    ("float16 latents rank 16, float16 Jacobians rank 16", ("float16", 16, 16, "float16")),
    ("bfloat16 latents rank 4, int8 Jacobians rank 4", ("bfloat16", 4, 4, "int8")),
    ("float16 latents rank 3, int8 Jacobians rank 3", ("float16", 3, 3, "int8")),
    ("float16 latents rank 4, int8 Jacobians rank 2", ("float16", 4, 2, "int8")),
]


def stored(
    block: VoxelBlock, dtype: str, latent_rank: int, jacobian_rank: int, jacobian_storage: str
) -> VoxelBlock:
    """``block`` as a submap keeps it (``CompactBlock``), decompressed for the transform."""
    compact = CompactBlock.compress(block, latent_rank, jacobian_rank, dtype, jacobian_storage)
    return compact.decompress()


def mesh_of(model: PriorModel, cfg: MapConfig, block) -> trimesh.Trimesh:
    nm = NeuralMap(cfg, model)
    nm.fuse(fresh_submap(block))
    return nm.extract_mesh()


def mesh_distance(a: trimesh.Trimesh, b: trimesh.Trimesh, samples: int) -> tuple[float, float]:
    """Mean distance a -> b and b -> a (metres)."""
    if len(a.faces) == 0 or len(b.faces) == 0:
        return float("inf"), float("inf")
    m = mesh_metrics(a, b, num_samples=samples)
    return m.accuracy_m, m.completion_m


def pose(axis, degrees: float, t) -> np.ndarray:
    T = np.eye(4)
    axis = np.asarray(axis, dtype=np.float64)
    T[:3, :3] = Rotation.from_rotvec(np.deg2rad(degrees) * axis / np.linalg.norm(axis)).as_matrix()
    T[:3, 3] = t
    return T


@dataclass
class Variant:
    name: str
    weighting: str
    use_jacobian: bool
    sigma_vu: float = 0.5
    target_rule: str | None = None
    storage: tuple[str, int, int, str] | None = None  # see STORAGE_VARIANTS
    jacobian_pairs: int = 0  # mapping.jacobian_pairs_per_voxel of the encoding (0: every pair)
    table_nodes: int = 0  # mapping.encoder_table_nodes of the encoding (0: the network)


def wall_cpu(fn, repeats: int) -> tuple[Timing, Timing]:
    """Wall and CPU seconds (all threads) of ``fn()`` over ``repeats`` runs (+1 warm-up)."""
    measured = timed(fn, repeats, warmup=True)
    return measured["wall_s"], measured["cpu_s"]


def cold_mesh(cfg, model, block, repeats: int) -> tuple[Timing, Timing, Any]:
    """Wall and CPU seconds of meshing a fresh map of ``block`` from cold, ``repeats`` times
    (each on a map built anew: a second extraction of one map is not cold); the last mesh."""
    walls, cpus, mesh = [], [], None
    for _ in range(repeats):
        neural_map = NeuralMap(cfg, model)
        neural_map.fuse(fresh_submap(block))
        t, c = time.perf_counter(), time.process_time()
        mesh = neural_map.extract_mesh()
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    return Timing(walls), Timing(cpus), mesh


# ---------------------------------------------------------------------------- experiments
def fidelity(model, quick: bool, lines: list[str]) -> None:
    size = (2.4, 2.0, 2.2) if quick else (4.0, 3.0, 2.5)
    density = 300 if quick else 1500
    room = room_mesh(size)
    points, normals = sample_surface(room, density)
    cfg = MapConfig(min_points_per_voxel=1, min_weight_to_decode=4.0, device="cpu")
    encoded = timed(
        lambda: encode_points(model, torch.from_numpy(points), torch.from_numpy(normals), V)
    )
    base, encode_s = encoded["result"], encoded["wall_s"]
    sources = {
        (pairs, nodes): encode_points(
            model,
            torch.from_numpy(points),
            torch.from_numpy(normals),
            V,
            jacobian_pairs_per_voxel=pairs,
            table_nodes=nodes,
        )
        for pairs, nodes in ((JACOBIAN_PAIRS, 0), (JACOBIAN_PAIRS, TABLE_NODES))
    }
    sources[(0, 0)] = base
    samples = 10_000 if quick else 150_000
    lines += [
        "### Transform fidelity (two paths)",
        "",
        f"Room {size[0]} x {size[1]} x {size[2]} m with furniture, {len(points):,} points "
        f"({density} per m^2, 2 mm noise), V = {V} m -> {base.num_voxels:,} voxels "
        f"(encoding with Jacobians took {encode_s:.1f} s). Distances are mean point-to-surface "
        f"distances between the meshes of the two paths ({samples:,} samples each way); "
        "'vs GT' is the accuracy of the path-1 mesh against the moved ground-truth room.",
        "",
        "| motion | variant | path1 -> path2 [cm] | path2 -> path1 [cm] | path 1 vs GT [cm] "
        "| path 2 vs GT [cm] | voxels path 1 / path 2 |",
        "|---|---|---|---|---|---|---|",
    ]
    motions = {
        "(a) 30 deg tilted axis + 16 cm": pose([0.3, -0.5, 0.8], 30.0, [0.16, 0.0, 0.0]),
        "(b) grid-aligned 90 deg + 3 voxels": pose([0.0, 0.0, 1.0], 90.0, [0.3, -0.1, 0.2]),
        "(c) 3 deg + 2.7 cm": pose([0.2, 0.9, -0.3], 3.0, [0.027, 0.0, 0.0]),
    }
    motions["(b) grid-aligned 90 deg + 3 voxels"][:3, :3] = np.round(
        motions["(b) grid-aligned 90 deg + 3 voxels"][:3, :3]
    )
    variants = [
        Variant("ours (gaussian sigma 0.5 vu, Jacobian), float32 original", "gaussian", True),
        *(
            Variant(f"ours, stored {label}", "gaussian", True, storage=storage)
            for label, storage in STORAGE_VARIANTS
        ),
        Variant(
            f"ours, stored {STORAGE_VARIANTS[0][0]}, Jacobian from <= {JACOBIAN_PAIRS} pairs "
            "per voxel",
            "gaussian",
            True,
            storage=STORAGE_VARIANTS[0][1],
            jacobian_pairs=JACOBIAN_PAIRS,
        ),
        Variant(
            f"ours, as above, latents from the encoder's {TABLE_NODES}-node table (the default)",
            "gaussian",
            True,
            storage=STORAGE_VARIANTS[0][1],
            jacobian_pairs=JACOBIAN_PAIRS,
            table_nodes=TABLE_NODES,
        ),
        Variant("ours without Jacobian", "gaussian", False),
        Variant(
            "ours, paper's target rule (nearest source < 1 voxel)", "gaussian", True, 0.5, "radius"
        ),
        Variant("paper-style (uniform K=8, no Jacobian)", "uniform", False),
    ]
    if quick:
        motions.pop("(c) 3 deg + 2.7 cm")
        motions.pop("(b) grid-aligned 90 deg + 3 voxels")
        # the product's default (stored, capped Jacobian, latent table) against the paper's
        variants = [v for v in variants if "table" in v.name or v.name.startswith("paper")]
    sweep: dict[str, list[tuple[float, float]]] = {}
    for label, D in motions.items():
        moved_pts = points @ D[:3, :3].T + D[:3, 3]
        moved_nrm = normals @ D[:3, :3].T
        gt = room.copy()
        gt.apply_transform(D)
        ref_block = encode_points(
            model, torch.from_numpy(moved_pts), torch.from_numpy(moved_nrm), V, with_jacobian=False
        )
        ref_mesh = mesh_of(model, cfg, ref_block)
        ref_gt = mesh_distance(ref_mesh, gt, samples)[0]
        for var in variants:
            source = sources[(var.jacobian_pairs, var.table_nodes)]
            source = source if var.storage is None else stored(source, *var.storage)
            block = transform_block(
                source,
                D,
                V,
                weighting=var.weighting,
                use_jacobian=var.use_jacobian,
                sigma_vu=var.sigma_vu,
                target_rule=var.target_rule,
            )
            mesh = mesh_of(model, cfg, block)
            d12, d21 = mesh_distance(mesh, ref_mesh, samples)
            d_gt = mesh_distance(mesh, gt, samples)[0]
            lines.append(
                f"| {label} | {var.name} | {100 * d12:.3f} | {100 * d21:.3f} | {100 * d_gt:.3f} "
                f"| {100 * ref_gt:.3f} | {block.num_voxels:,} / {ref_block.num_voxels:,} |"
            )
            log.info("%s %s: %.4f %.4f", label, var.name, d12, d21)
        if not quick and not label.startswith("(b)"):
            for sigma in (0.2, 0.3, 0.5, 0.7, 1.0):
                block = transform_block(base, D, V, sigma_vu=sigma)
                d12, d21 = mesh_distance(mesh_of(model, cfg, block), ref_mesh, samples)
                sweep.setdefault(label, []).append((sigma, 0.5 * (d12 + d21)))
    lines.append("")
    if sweep:
        sigmas = [s for s, _ in next(iter(sweep.values()))]
        lines += [
            "Width of the gaussian weighting (ours, with Jacobian): mean of both directions [cm]",
            "",
            "| motion | " + " | ".join(f"sigma = {s} vu" for s in sigmas) + " |",
            "|---|" + "---|" * len(sigmas),
        ]
        for label, row in sweep.items():
            lines.append(f"| {label} | " + " | ".join(f"{100 * d:.3f}" for _, d in row) + " |")
        lines.append("")


def speed(model, quick: bool, lines: list[str]) -> None:
    repeats = REPEATS if quick else 5
    room = room_mesh((2.4, 2.0, 2.2) if quick else (5.0, 4.0, 2.6))
    cfg = MapConfig(min_points_per_voxel=1, min_weight_to_decode=4.0, device="cpu")
    nm = NeuralMap(cfg, model)
    rows: list[tuple[str, str, tuple[float, float], str, str]] = []

    keep = 10000 if quick else 30000
    frame_pts, frame_nrm, hits = depth_frame_points(room, keep=keep)
    frame_sub = nm.encode(1, frame_pts, frame_nrm, np.eye(4))
    enc = wall_cpu(lambda: nm.encode(1, frame_pts, frame_nrm, np.eye(4)), repeats)
    size = (
        f"{len(frame_pts):,} points (of {hits:,} hits) -> {frame_sub.original.num_voxels:,} voxels"
    )
    rows.append(
        (
            f"encode one 640x480 depth frame, with Jacobians (<= {JACOBIAN_PAIRS} pairs per "
            f"voxel), latent table ({TABLE_NODES} nodes)",
            size,
            enc,
            "frames",
            ">= 30/s",
        )
    )
    pts_t, nrm_t = torch.from_numpy(frame_pts), torch.from_numpy(frame_nrm)
    enc_net = wall_cpu(
        lambda: encode_points(nm.model, pts_t, nrm_t, V, jacobian_pairs_per_voxel=JACOBIAN_PAIRS),
        repeats,
    )
    rows.append(("encode, the same by the encoder network", "same", enc_net, "frames", "-"))
    enc_all = wall_cpu(lambda: encode_points(nm.model, pts_t, nrm_t, V), repeats)
    rows.append(("encode, network, Jacobians from every pair", "same", enc_all, "frames", "-"))
    enc_nj = wall_cpu(
        lambda: encode_points(nm.model, pts_t, nrm_t, V, with_jacobian=False), repeats
    )
    rows.append(("encode, network, latents only (no Jacobians)", "same", enc_nj, "frames", "-"))

    points, normals = sample_surface(room, 800 if quick else 1200, seed=1)
    big = encode_points(nm.model, torch.from_numpy(points), torch.from_numpy(normals), V)
    # a compact ~2,000-voxel submap: the voxels nearest to one surface point
    centres = big.centers(V)
    order = np.argsort(np.linalg.norm(centres - points[0], axis=1))
    sub_block = big.select(torch.from_numpy(np.sort(order[: min(2000, len(order))])))
    D = pose([0.3, -0.5, 0.8], 2.0, [0.013, -0.02, 0.004])
    tr = wall_cpu(lambda: transform_block(sub_block, D, V), 10 * repeats)
    n_sub = f"{sub_block.num_voxels:,} voxels"
    rows.append(
        ("transform + re-grid (ours: gaussian, Jacobian)", n_sub, tr, "submaps", ">= 100/s")
    )
    if not quick:
        tr_paper = wall_cpu(
            lambda: transform_block(sub_block, D, V, weighting="uniform", use_jacobian=False),
            10 * repeats,
        )
        rows.append(("transform + re-grid (paper-style)", n_sub, tr_paper, "submaps", "-"))

    big_map = NeuralMap(cfg, model)
    big_map.fuse(fresh_submap(big))
    moving = fresh_submap(sub_block, 7)

    def fuse_remove() -> None:
        big_map.fuse(moving)
        big_map.remove(moving)

    fr = wall_cpu(fuse_remove, 20 * repeats)
    rows.append(
        (
            f"fuse or remove (map of {big_map.num_voxels:,} voxels)",
            n_sub,
            (fr[0].scaled(0.5), fr[1].scaled(0.5)),
            "ops",
            ">= 1000/s",
        )
    )
    *mesh_t, mesh = cold_mesh(cfg, model, big, repeats)
    rows.append(
        (
            f"mesh the whole map, cold (s = {cfg.mesh_subdivisions})",
            f"{big_map.num_voxels:,} voxels -> {len(mesh.faces):,} faces",
            mesh_t,
            "",
            "< 5 s (20k voxels)",
        )
    )
    big_map.fuse(moving)
    big_map.extract_mesh()
    remesh_t = wall_cpu(lambda: (big_map.move(moving, D), big_map.extract_mesh()), repeats)
    rows.append(("move one submap + incremental re-mesh", n_sub, remesh_t, "", "-"))

    lines += [
        "### Speed and memory",
        "",
        repeats_line(),
        "",
        "| operation | size | wall | CPU (all threads) | rate (wall) | goal |",
        "|---|---|---|---|---|---|",
    ]
    for name, size_text, (wall, cpu), unit, goal in rows:
        rate = f"{1 / wall:.1f} {unit}/s" if unit else "-"
        lines.append(f"| {name} | {size_text} | {_fmt_s(wall)} | {_fmt_s(cpu)} | {rate} | {goal} |")
    per_voxel = big_map.memory_bytes() / max(big_map.num_voxels, 1)
    payload = model.latent_channels * 3 * 4 + 8 + 16
    sub_bytes = frame_sub.nbytes() / max(frame_sub.original.num_voxels, 1)
    lines += [
        "",
        f"Memory: {per_voxel:.0f} bytes per global-map voxel as allocated (capacity included; "
        f"payload {payload} B: latent {model.latent_channels}x3 float32, float64 weight, sorted "
        f"key and row index; no Jacobians). A stored submap holds {sub_bytes:.0f} B per voxel "
        f"(the frame above: {frame_sub.nbytes() / 1e6:.2f} MB for "
        f"{frame_sub.original.num_voxels:,} voxels: packed key, float32 weight, "
        f"{nm.cfg.storage_dtype} latents at rank {min(nm.cfg.latent_rank, 16)} and Jacobians at "
        f"rank {nm.cfg.jacobian_rank}); moving it stores nothing more (the placed block is "
        "recomputed when it is removed).",
        "",
        f"The same frame's raw data against what the map keeps of it: {len(frame_pts):,} points "
        f"with normals as float32 = {24 * len(frame_pts) / 1e6:.2f} MB; its stored submap = "
        f"{frame_sub.nbytes() / 1e6:.2f} MB; its voxels' float32 Jacobians alone, as version-1 "
        f"map files kept them = {frame_sub.original.num_voxels * 16 * 9 * 4 / 1e6:.2f} MB.",
        "",
    ]


def _fmt_s(seconds: Timing) -> str:
    return f"{seconds:.2f} s" if seconds >= 1 else f"{seconds.scaled(1000):.1f} ms"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small scene, fewer repetitions")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    parser.add_argument("--out", type=Path, default=RESULTS, help="Markdown section to write")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(args.threads)
    model, model_label = load_model()
    cli_args = sys.argv[1:] if argv is None else argv
    command = shlex.join(["python", "-m", "benchmarks.bench_mapping", *cli_args])
    lines = [
        *section_header("Neural implicit map (mapping/)", command),
        f"- torch threads: {torch.get_num_threads()}, CPU only",
        f"- Weights: {model_label}",
        "",
    ]
    fidelity(model, args.quick, lines)
    speed(model, args.quick, lines)
    write_text_atomic(args.out, "\n".join(lines) + "\n")
    log.info("wrote %s", args.out)


if __name__ == "__main__":
    main()
