"""Neural implicit map: transform fidelity (the paper's "two paths") and speed.

    python -m benchmarks.bench_mapping [--quick] [--threads N]

Writes ``benchmarks/results/mapping.md``.

1. Transform fidelity at V = 0.1 m on a synthetic room with furniture (surface samples, 2 mm
   noise): encode at pose A and transform the map by D (path 1), versus encode the moved points
   (path 2); the two meshes are compared by mean surface distance both ways, for ours (with
   storage, Jacobian and latent-table variants) and the paper's scheme (uniform average of the 8
   nearest sources, no Jacobian).
2. Speed: encoding one 640x480 depth frame, transform and re-gridding of a ~2,000-voxel submap,
   fuse and remove, meshing a ~20,000-voxel map; memory per voxel and per stored submap.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation

from benchmarks.harness.cli import bench_parser, command_line, start_logging
from benchmarks.harness.machine import section_header
from benchmarks.harness.paths import RESULTS_DIR
from benchmarks.harness.repeat import REPEATS, Timing, repeats_line, timed
from benchmarks.harness.results import table
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

V = 0.1
JACOBIAN_PAIRS = MapConfig().jacobian_pairs_per_voxel
TABLE_NODES = MapConfig().encoder_table_nodes


def room_mesh(size: tuple[float, float, float]) -> trimesh.Trimesh:
    """A closed box room (normals inwards) with furniture; floor at z = 0."""
    sx, sy, sz = size
    shell = trimesh.creation.box(extents=size)
    shell.apply_translation([0.0, 0.0, sz / 2])
    shell.invert()
    box = trimesh.creation.box
    parts = [
        (shell, None),
        (box(extents=(1.2, 0.8, 0.05)), (0.3, -0.2, 0.75)),
        *(
            (box(extents=(0.06, 0.06, 0.725)), (0.3 + dx, -0.2 + dy, 0.3625))
            for dx in (-0.55, 0.55)
            for dy in (-0.35, 0.35)
        ),
        (box(extents=(0.6, 0.4, 1.8)), (-sx / 2 + 0.3, sy / 2 - 0.2, 0.9)),
        (trimesh.creation.icosphere(subdivisions=4, radius=0.3), (sx / 2 - 0.8, sy / 2 - 0.7, 0.3)),
        (
            trimesh.creation.cylinder(radius=0.2, height=1.0, sections=48),
            (-sx / 2 + 1.0, -sy / 2 + 0.7, 0.5),
        ),
    ]
    for part, centre in parts:
        if centre is not None:
            part.apply_translation(centre)
    return trimesh.util.concatenate([part for part, _ in parts])


def sample_surface(mesh: trimesh.Trimesh, density_per_m2: float, seed: int = 0):
    points, face = trimesh.sample.sample_surface(mesh, int(mesh.area * density_per_m2), seed=seed)
    rng = np.random.default_rng(seed)
    return points + rng.normal(scale=0.002, size=points.shape), mesh.face_normals[face]


def depth_frame_points(mesh: trimesh.Trimesh, width=640, height=480, keep=30000):
    """Ray-cast one pinhole frame (f = 525 px) inside the room; subsample to ``keep`` points."""
    fx = 525.0
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    dirs_C = np.stack([(u - width / 2) / fx, (v - height / 2) / fx, np.ones_like(u)], -1)
    dirs_C = dirs_C.reshape(-1, 3) / np.linalg.norm(dirs_C.reshape(-1, 3), axis=1, keepdims=True)
    # camera at the room centre, 1.4 m high, looking along +x and slightly down (OpenCV axes)
    R_W_C = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    dirs_W = dirs_C @ (Rotation.from_rotvec([0.0, 0.25, 0.0]).as_matrix() @ R_W_C).T
    origins = np.repeat(np.array([[-0.5, 0.0, 1.4]]), len(dirs_W), 0)
    hits, ray, tri = mesh.ray.intersects_location(origins, dirs_W, multiple_hits=False)
    normals = mesh.face_normals[tri]
    normals[np.einsum("ij,ij->i", normals, dirs_W[ray]) > 0] *= -1.0
    rng = np.random.default_rng(0)
    pick = rng.choice(len(hits), size=min(keep, len(hits)), replace=False)
    noise = rng.normal(scale=0.002, size=(len(pick), 3))
    return hits[pick] + noise, normals[pick], len(hits)


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
    weighting: str = "gaussian"
    use_jacobian: bool = True
    target_rule: str | None = None
    storage: tuple[str, int, int, str] | None = None  # see STORAGE_VARIANTS
    jacobian_pairs: int = 0  # mapping.jacobian_pairs_per_voxel of the encoding (0: every pair)
    table_nodes: int = 0  # mapping.encoder_table_nodes of the encoding (0: the network)


VARIANTS = [
    Variant("ours (gaussian sigma 0.5 vu, Jacobian), float32 original"),
    *(Variant(f"ours, stored {label}", storage=storage) for label, storage in STORAGE_VARIANTS),
    Variant(
        f"ours, stored {STORAGE_VARIANTS[0][0]}, Jacobian from <= {JACOBIAN_PAIRS} pairs per voxel",
        storage=STORAGE_VARIANTS[0][1],
        jacobian_pairs=JACOBIAN_PAIRS,
    ),
    Variant(
        f"ours, as above, latents from the encoder's {TABLE_NODES}-node table (the default)",
        storage=STORAGE_VARIANTS[0][1],
        jacobian_pairs=JACOBIAN_PAIRS,
        table_nodes=TABLE_NODES,
    ),
    Variant("ours without Jacobian", use_jacobian=False),
    Variant("ours, paper's target rule (nearest source < 1 voxel)", target_rule="radius"),
    Variant("paper-style (uniform K=8, no Jacobian)", "uniform", False),
]


def fidelity(model, quick: bool, lines: list[str]) -> None:
    size = (2.4, 2.0, 2.2) if quick else (4.0, 3.0, 2.5)
    density = 300 if quick else 1500
    room = room_mesh(size)
    points, normals = sample_surface(room, density)
    cfg = MapConfig(min_points_per_voxel=1, min_weight_to_decode=4.0, device="cpu")

    def encode(pts, nrm, **options):
        return encode_points(model, torch.from_numpy(pts), torch.from_numpy(nrm), V, **options)

    encoded = timed(lambda: encode(points, normals))
    base, encode_s = encoded["result"], encoded["wall_s"]
    sources = {(0, 0): base}
    for pairs, nodes in ((JACOBIAN_PAIRS, 0), (JACOBIAN_PAIRS, TABLE_NODES)):
        sources[(pairs, nodes)] = encode(
            points, normals, jacobian_pairs_per_voxel=pairs, table_nodes=nodes
        )
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
    ]
    grid_aligned = pose([0.0, 0.0, 1.0], 90.0, [0.3, -0.1, 0.2])
    grid_aligned[:3, :3] = np.round(grid_aligned[:3, :3])
    motions = {
        "(a) 30 deg tilted axis + 16 cm": pose([0.3, -0.5, 0.8], 30.0, [0.16, 0.0, 0.0]),
        "(b) grid-aligned 90 deg + 3 voxels": grid_aligned,
        "(c) 3 deg + 2.7 cm": pose([0.2, 0.9, -0.3], 3.0, [0.027, 0.0, 0.0]),
    }
    variants = VARIANTS
    if quick:
        motions = dict(list(motions.items())[:1])
        # the product's default (stored, capped Jacobian, latent table) against the paper's
        variants = [v for v in variants if "table" in v.name or v.name.startswith("paper")]
    rows, sweep = [], {}
    for label, D in motions.items():
        gt = room.copy()
        gt.apply_transform(D)
        moved = (points @ D[:3, :3].T + D[:3, 3], normals @ D[:3, :3].T)
        ref_block = encode(*moved, with_jacobian=False)
        ref_mesh = mesh_of(model, cfg, ref_block)
        ref_gt = mesh_distance(ref_mesh, gt, samples)[0]
        for var in variants:
            source = sources[(var.jacobian_pairs, var.table_nodes)]
            if var.storage is not None:  # as a submap keeps it, decompressed for the transform
                dtype, latent_rank, jacobian_rank, jacobian_storage = var.storage
                source = CompactBlock.compress(
                    source, latent_rank, jacobian_rank, dtype, jacobian_storage
                ).decompress()
            block = transform_block(
                source,
                D,
                V,
                weighting=var.weighting,
                use_jacobian=var.use_jacobian,
                sigma_vu=0.5,
                target_rule=var.target_rule,
            )
            mesh = mesh_of(model, cfg, block)
            d12, d21 = mesh_distance(mesh, ref_mesh, samples)
            d_gt = mesh_distance(mesh, gt, samples)[0]
            rows.append(
                [
                    label,
                    var.name,
                    *(f"{100 * d:.3f}" for d in (d12, d21, d_gt, ref_gt)),
                    f"{block.num_voxels:,} / {ref_block.num_voxels:,}",
                ]
            )
            log.info("%s %s: %.4f %.4f", label, var.name, d12, d21)
        if not quick and not label.startswith("(b)"):
            for sigma in (0.2, 0.3, 0.5, 0.7, 1.0):
                block = transform_block(base, D, V, sigma_vu=sigma)
                d12, d21 = mesh_distance(mesh_of(model, cfg, block), ref_mesh, samples)
                sweep.setdefault(label, []).append(f"{100 * 0.5 * (d12 + d21):.3f}")
    header = (
        "motion | variant | path1 -> path2 [cm] | path2 -> path1 [cm] | path 1 vs GT [cm] "
        "| path 2 vs GT [cm] | voxels path 1 / path 2"
    )
    lines += [*table(header, rows), ""]
    if sweep:
        lines += [
            "Width of the gaussian weighting (ours, with Jacobian): mean of both directions [cm]",
            "",
            *table(
                "motion | " + " | ".join(f"sigma = {s} vu" for s in (0.2, 0.3, 0.5, 0.7, 1.0)),
                ([label, *row] for label, row in sweep.items()),
            ),
            "",
        ]


def speed(model, quick: bool, lines: list[str]) -> None:
    repeats = REPEATS if quick else 5
    room = room_mesh((2.4, 2.0, 2.2) if quick else (5.0, 4.0, 2.6))
    cfg = MapConfig(min_points_per_voxel=1, min_weight_to_decode=4.0, device="cpu")
    nm = NeuralMap(cfg, model)
    rows = []

    def row(name, size, fn, runs, unit="", goal="-", per_call=1.0):
        measured = timed(fn, runs, warmup=True)
        wall, cpu = measured["wall_s"].scaled(per_call), measured["cpu_s"].scaled(per_call)
        rate = f"{1 / wall:.1f} {unit}/s" if unit else "-"
        rows.append([name, size, _fmt_s(wall), _fmt_s(cpu), rate, goal])

    frame_pts, frame_nrm, hits = depth_frame_points(room, keep=10000 if quick else 30000)
    frame_sub = nm.encode(1, frame_pts, frame_nrm, np.eye(4))
    frame_voxels = frame_sub.original.num_voxels
    row(
        f"encode one 640x480 depth frame, with Jacobians (<= {JACOBIAN_PAIRS} pairs per voxel), "
        f"latent table ({TABLE_NODES} nodes)",
        f"{len(frame_pts):,} points (of {hits:,} hits) -> {frame_voxels:,} voxels",
        lambda: nm.encode(1, frame_pts, frame_nrm, np.eye(4)),
        repeats,
        "frames",
        ">= 30/s",
    )
    pts_t, nrm_t = torch.from_numpy(frame_pts), torch.from_numpy(frame_nrm)
    for name, options in (
        ("encode, the same by the encoder network", {"jacobian_pairs_per_voxel": JACOBIAN_PAIRS}),
        ("encode, network, Jacobians from every pair", {}),
        ("encode, network, latents only (no Jacobians)", {"with_jacobian": False}),
    ):
        row(
            name,
            "same",
            lambda o=options: encode_points(nm.model, pts_t, nrm_t, V, **o),
            repeats,
            "frames",
        )

    points, normals = sample_surface(room, 800 if quick else 1200, seed=1)
    big = encode_points(model, torch.from_numpy(points), torch.from_numpy(normals), V)
    # a compact ~2,000-voxel submap: the voxels nearest to one surface point
    order = np.argsort(np.linalg.norm(big.centers(V) - points[0], axis=1))
    sub_block = big.select(torch.from_numpy(np.sort(order[: min(2000, len(order))])))
    D = pose([0.3, -0.5, 0.8], 2.0, [0.013, -0.02, 0.004])
    n_sub = f"{sub_block.num_voxels:,} voxels"
    row(
        "transform + re-grid (ours: gaussian, Jacobian)",
        n_sub,
        lambda: transform_block(sub_block, D, V),
        10 * repeats,
        "submaps",
        ">= 100/s",
    )
    if not quick:
        row(
            "transform + re-grid (paper-style)",
            n_sub,
            lambda: transform_block(sub_block, D, V, weighting="uniform", use_jacobian=False),
            10 * repeats,
            "submaps",
        )

    big_map = NeuralMap(cfg, model)
    big_map.fuse(fresh_submap(big))
    moving = fresh_submap(sub_block, 7)
    row(
        f"fuse or remove (map of {big_map.num_voxels:,} voxels)",
        n_sub,
        lambda: (big_map.fuse(moving), big_map.remove(moving)),
        20 * repeats,
        "ops",
        ">= 1000/s",
        per_call=0.5,
    )
    # each cold extraction on a map built anew: a second extraction of one map is not cold
    walls, cpus, mesh = [], [], None
    for _ in range(repeats):
        cold = NeuralMap(cfg, model)
        cold.fuse(fresh_submap(big))
        t, c = time.perf_counter(), time.process_time()
        mesh = cold.extract_mesh()
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    rows.append(
        [
            f"mesh the whole map, cold (s = {cfg.mesh_subdivisions})",
            f"{big_map.num_voxels:,} voxels -> {len(mesh.faces):,} faces",
            _fmt_s(Timing(walls)),
            _fmt_s(Timing(cpus)),
            "-",
            "< 5 s (20k voxels)",
        ]
    )
    big_map.fuse(moving)
    big_map.extract_mesh()
    row(
        "move one submap + incremental re-mesh",
        n_sub,
        lambda: (big_map.move(moving, D), big_map.extract_mesh()),
        repeats,
    )

    header = "operation | size | wall | CPU (all threads) | rate (wall) | goal"
    lines += ["### Speed and memory", "", repeats_line(), "", *table(header, rows)]
    per_voxel = big_map.memory_bytes() / max(big_map.num_voxels, 1)
    payload = model.latent_channels * 3 * 4 + 8 + 16
    sub_mb = frame_sub.nbytes() / 1e6
    lines += [
        "",
        f"Memory: {per_voxel:.0f} bytes per global-map voxel as allocated (capacity included; "
        f"payload {payload} B: latent {model.latent_channels}x3 float32, float64 weight, sorted "
        f"key and row index; no Jacobians). A stored submap holds "
        f"{frame_sub.nbytes() / max(frame_voxels, 1):.0f} B per voxel "
        f"(the frame above: {sub_mb:.2f} MB for {frame_voxels:,} voxels: packed key, float32 "
        f"weight, {nm.cfg.storage_dtype} latents at rank {min(nm.cfg.latent_rank, 16)} and "
        f"Jacobians at rank {nm.cfg.jacobian_rank}); moving it stores nothing more (the placed "
        "block is recomputed when it is removed).",
        "",
        f"The same frame's raw data against what the map keeps of it: {len(frame_pts):,} points "
        f"with normals as float32 = {24 * len(frame_pts) / 1e6:.2f} MB; its stored submap = "
        f"{sub_mb:.2f} MB; its voxels' float32 Jacobians alone, as version-1 "
        f"map files kept them = {frame_voxels * 16 * 9 * 4 / 1e6:.2f} MB.",
        "",
    ]


def _fmt_s(seconds: Timing) -> str:
    return f"{seconds:.2f} s" if seconds >= 1 else f"{seconds.scaled(1000):.1f} ms"


def build_parser():
    parser = bench_parser(__doc__, "small scene, fewer repetitions", out=RESULTS_DIR / "mapping.md")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    start_logging()
    torch.set_num_threads(args.threads)
    model, model_label = load_model()
    lines = [
        *section_header("Neural implicit map (mapping/)", command_line("bench_mapping", argv)),
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
