"""Configuration of the neural implicit map (grid, encoding, transform, meshing, device)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

if TYPE_CHECKING:
    import torch


class MapConfig(BaseModel):
    """Everything the neural implicit map needs besides the prior network's weights."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    voxel_size_m: float = Field(
        0.1,
        ge=0.01,
        le=100.0,
        description="edge length V of a voxel in metres (0.1 indoors, metres outdoors; 0.01 to "
        "100: finer voxels leave the 21-bit voxel keys within a few metres and multiply memory)",
    )
    min_points_per_voxel: int = Field(
        8,
        ge=1,
        le=100000,
        description=(
            "encoding-time pruning: a point is encoded only if its own voxel (the one containing "
            "it) holds at least this many of the submap's points; 1 keeps every point (the paper "
            "keeps a point when its voxel has more than 16, i.e. 17 here); at most 100000"
        ),
    )
    min_weight_to_decode: float = Field(
        8.0,
        ge=0.0,
        allow_inf_nan=False,
        description=(
            "voxels whose weight (number of fused point-voxel associations) is below this are kept "
            "in the map but neither decoded by query_sdf nor meshed"
        ),
    )
    transform_neighbors: int = Field(
        8,
        ge=1,
        le=64,
        description="K: number of nearest moved source voxels blended per target voxel; at most 64",
    )
    transform_use_jacobian: bool = Field(
        True,
        description=(
            "apply the first-order correction h = F' - J' v when moving latents off-grid "
            "(False gives the zeroth-order hypothesis h = F')"
        ),
    )
    transform_weighting: Literal["gaussian", "uniform"] = Field(
        "gaussian",
        description=(
            "blending of the K hypotheses: 'gaussian' = exp(-|v|^2 / 2 s^2) (1 - |v|^2)^2 with |v| "
            "in voxel units, support 1 vu, so a source on a target is reproduced exactly; "
            "'uniform' = the paper's (near-)uniform average of the K nearest sources"
        ),
    )
    transform_sigma_vu: float = Field(
        0.5,
        gt=0.0,
        le=10.0,
        allow_inf_nan=False,
        description=(
            "width s (voxel units) of the 'gaussian' transform weighting; on the two-path room "
            "benchmark 0.2 is worse and 0.5-0.7 are equal within 0.005 cm"
        ),
    )
    storage_dtype: Literal["int8", "float16", "bfloat16", "float32"] = Field(
        "float16",
        description=(
            "precision of the stored submap latent coefficients, in memory and on disk; "
            "arithmetic is float32 either way. float16 keeps 3 more mantissa bits than bfloat16 "
            "and the values are small (|F| < 10), so it is the default; int8 (one step per basis "
            "direction, its peak / 127) halves the latents' bytes, for maps whose file must be "
            "small (0.5 m voxels on the generated street: precision at 10 cm 0.924 instead of "
            "0.926, recall unchanged; the two-path transform benchmark unchanged)"
        ),
    )
    jacobian_storage: Literal["int4", "int8", "float16", "bfloat16", "float32"] = Field(
        "int8",
        description=(
            "format of the stored Jacobian coefficients: int8 with one scale per basis direction "
            "(default; the two-path transform benchmark is unchanged by it), int4 (codes within "
            "+-7, one per byte in memory; deflate stores them in a fifth of int8's file bytes; "
            "the two-path benchmark's mean distances 10-16 % larger) or a float format"
        ),
    )
    latent_rank: int = Field(
        4,
        ge=1,
        le=64,
        description=(
            "channel-basis rank of a stored submap's latents (mapping/compact_block.py); the "
            "number of latent channels (16) or more keeps every channel. Rank 4 changed neither "
            "mesh accuracy nor transform fidelity on the benchmark room "
            "(benchmarks/bench_mapping); at most 64"
        ),
    )
    jacobian_rank: int = Field(
        4,
        ge=1,
        le=64,
        description=(
            "channel-basis rank of a stored submap's Jacobians (they only feed the transform's "
            "first-order term); 4 matches full rank on the two-path benchmark, 2 does not; at "
            "most 64"
        ),
    )
    jacobian_pairs_per_voxel: int = Field(
        16,
        ge=0,
        le=4096,
        description=(
            "a voxel's Jacobian (the transform's first-order term) is the mean of dF/dr over at "
            "most this many of its point-voxel pairs, spread over the voxel; its latent always "
            "uses every pair. The tangents cost about 4x the latent: 16 cut the encoding CPU time "
            "of a generated KITTI submap by ~40 % and of a demo RGB-D submap by ~65 %, for a "
            "transform fidelity 1.6-4 % worse on the benchmark room and an unchanged demo mesh "
            "(BENCHMARKS.md, Mapping); 0 uses every pair; at most 4096"
        ),
    )
    mesh_subdivisions: int = Field(
        4,
        ge=1,
        le=16,
        description="lattice cells per voxel edge for meshing (4 gives 2.5 cm at V = 0.1 m) (1 to "
        "16: the lattice grows with the cube)",
    )
    mesh_max_sigma_vu: float = Field(
        0.15,
        gt=0.0,
        allow_inf_nan=False,
        description="triangles with a vertex whose predicted SDF std. dev. (vu) is above are cut",
    )
    mesh_chunk_voxels: int = Field(
        8,
        ge=2,
        le=64,
        description="meshing chunk edge in voxels; chunk meshes are cached, re-meshed when dirty "
        "(2 to 64)",
    )
    encoder_table_nodes: int = Field(
        256,
        ge=0,
        le=2048,
        description=(
            "per-point latents are looked up in a table of the prior's encoder over its two "
            "invariants (r . n, |r_perp|) with this many nodes per axis, built once per process "
            "(about 0.1 s at 256), instead of evaluating the network for every point-voxel pair: "
            "a 30k-point depth frame encodes 2x faster; its voxel latents differ from the "
            "network's by 2e-5 (median; largest 2e-4), its Jacobians by 0.3 % (median; "
            "mapping/latent_table.py). 0 evaluates the network; at most 2048 (4M nodes)"
        ),
    )
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="torch device of the map and networks; auto = cuda when available"
    )
    weights_path: str | None = Field(
        None,
        description="prior weights file; None = the shipped prior (networks.load_default_prior)",
    )

    @field_validator("encoder_table_nodes")
    @classmethod
    def _table_has_cells(cls, nodes: int) -> int:
        if nodes == 1:
            raise ValueError("encoder_table_nodes: 0 (no table) or at least 2 nodes per axis")
        return nodes


def resolve_device(device: str, setting: str = "mapping.device") -> torch.device:
    """Map ``auto``/``cpu``/``cuda`` to a torch device; asking for CUDA without one is an error
    that names ``setting`` (the config key or option the device came from)."""
    import torch  # here, not at the top: reading a config must not cost torch's import

    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"{setting} is 'cuda' but no CUDA device is available; use auto or cpu")
    return torch.device(device)
