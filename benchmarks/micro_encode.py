"""Micro-benchmarks of encoding and meshing, for ``bench_throughput --only micro``."""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np

from benchmarks.harness.repeat import timed


def scenario_micro(_: int = 0) -> dict:
    """Encode one 30k-point depth frame with Jacobians: by the encoder network over every pair
    and over the default Jacobian sample, and by the encoder's latent table (the default; its
    build time and its per-voxel relative difference to the network); mesh a ~20k-voxel room map
    from cold (1 thread, and 2)."""
    import torch

    from benchmarks.bench_mapping import V, depth_frame_points, room_mesh, sample_surface
    from mapping.config import MapConfig
    from mapping.encoding import encode_points
    from mapping.latent_table import latent_table
    from mapping.networks import load_default_prior
    from mapping.neural_map import NeuralMap

    def wall_cpu(fn) -> tuple[float, float]:
        measured = timed(fn, repeats=15)
        return measured["wall_s"], measured["cpu_s"]

    def rel_errors(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Per-voxel relative difference of ``a`` to ``b``."""
        scale = b.flatten(1).norm(dim=1).clamp_min(1e-12)
        return (a - b).flatten(1).norm(dim=1) / scale

    model = load_default_prior().eval()
    room = room_mesh((5.0, 4.0, 2.6))
    points, normals, _ = depth_frame_points(room, keep=30000)
    p, n = torch.from_numpy(points), torch.from_numpy(normals)
    out: dict[str, Any] = {"encode_points": len(points)}
    for threads in (1, 2):
        torch.set_num_threads(threads)
        block = encode_points(model, p, n, V)
        wall, cpu = wall_cpu(lambda: encode_points(model, p, n, V))
        out[f"encode_wall_s_{threads}t"], out[f"encode_cpu_s_{threads}t"] = wall, cpu
    out["encode_voxels"] = block.num_voxels
    torch.set_num_threads(1)
    out["encode_nojac_wall_s_1t"] = wall_cpu(
        lambda: encode_points(model, p, n, V, with_jacobian=False)
    )[0]
    cap = MapConfig().jacobian_pairs_per_voxel
    capped = encode_points(model, p, n, V, jacobian_pairs_per_voxel=cap)
    out["encode_capped_pairs"] = cap
    out["encode_capped_jacobian_rel_diff_median"] = float(
        rel_errors(capped.jacobians, block.jacobians).median()
    )
    for threads in (1, 2):
        torch.set_num_threads(threads)
        out[f"encode_capped_wall_s_{threads}t"], out[f"encode_capped_cpu_s_{threads}t"] = wall_cpu(
            lambda: encode_points(model, p, n, V, jacobian_pairs_per_voxel=cap)
        )
    # the product's default: the encoder's latent table (built once per process, timed here)
    nodes = MapConfig().encoder_table_nodes
    torch.set_num_threads(1)
    t = time.perf_counter()
    latent_table(model.encoder, nodes)
    out["encode_table_nodes"] = nodes
    out["encode_table_build_s"] = time.perf_counter() - t
    looked_up = encode_points(model, p, n, V, jacobian_pairs_per_voxel=cap, table_nodes=nodes)
    for name, a, b in (
        ("latent", looked_up.latents, capped.latents),
        ("jacobian", looked_up.jacobians, capped.jacobians),
    ):
        error = rel_errors(a, b)
        out[f"encode_table_{name}_rel_diff_median"] = float(error.median())
        out[f"encode_table_{name}_rel_diff_max"] = float(error.max())
    for threads in (1, 2):
        torch.set_num_threads(threads)
        out[f"encode_table_wall_s_{threads}t"], out[f"encode_table_cpu_s_{threads}t"] = wall_cpu(
            lambda: encode_points(model, p, n, V, jacobian_pairs_per_voxel=cap, table_nodes=nodes)
        )
    cfg = MapConfig(min_points_per_voxel=1, min_weight_to_decode=4.0, device="cpu")
    surface, surface_normals = sample_surface(room, 1500, seed=1)
    submap = NeuralMap(cfg, model).encode(0, surface, surface_normals, np.eye(4))
    torch.set_num_threads(1)
    neural_map = NeuralMap(cfg, model)
    neural_map.fuse(submap)
    t, c = time.perf_counter(), time.process_time()
    mesh = neural_map.extract_mesh()
    out["mesh_cold_wall_s"] = time.perf_counter() - t
    out["mesh_cold_cpu_s"] = time.process_time() - c
    out["mesh_voxels"] = neural_map.num_voxels
    out["mesh_faces"] = len(mesh.faces)
    t = time.perf_counter()
    neural_map.extract_mesh()
    out["mesh_again_wall_s"] = time.perf_counter() - t
    # from cold on the whole 2-thread budget, as the final mesh of a run (torch 1 thread each)
    submap.fused = False
    neural_map = NeuralMap(cfg, model)
    neural_map.fuse(submap)
    t, c = time.perf_counter(), time.process_time()
    neural_map.extract_mesh(threads=2)
    out["mesh_cold_wall_s_2t"] = time.perf_counter() - t
    out["mesh_cold_cpu_s_2t"] = time.process_time() - c
    out["load"] = os.getloadavg()[0]
    return out
