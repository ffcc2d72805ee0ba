"""The global neural implicit map and its submaps: encode, fuse, remove, move, query, mesh, save.

A :class:`Submap` keeps its *original* encoding (on the world grid at the pose it was encoded at)
for life, compactly (:class:`~mapping.compact_block.CompactBlock`). Moving it never re-encodes
points: the original is transformed by ``D = T_W_A inv(T_W_A_encoded)``
(:func:`mapping.transform.transform_block`) into its *placed* block, which is what the global map
holds while the submap is fused. The placed block is not stored: it is a deterministic function of
the original and the pose, recomputed when the submap is removed, so removal subtracts exactly what
was added. Fusion and removal are exact weighted averages in float32, so
``remove(fuse(map, s), s) == map`` up to float32 rounding; half precision only rounds the original
once, when it is encoded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh

from common.voxel_keys import unpack_keys
from mapping.compact_block import CompactBlock
from mapping.config import MapConfig, resolve_device
from mapping.encoding import encode_points
from mapping.field import query_field
from mapping.meshing import CHUNKS_PER_BATCH, ChunkMesher
from mapping.networks import PriorModel, load_default_prior
from mapping.transform import check_rigid, transform_block
from mapping.voxel_block import VoxelBlock
from mapping.voxel_store import VoxelStore


@dataclass
class Submap:
    """One unit of remapping.

    Attributes:
        submap_id: caller's identifier (unique within a map).
        T_W_A_encoded: 4x4 pose at which ``original`` was encoded (kept for life).
        original: the encoding on the world grid at ``T_W_A_encoded``; never modified.
        T_W_A: 4x4 pose the submap currently sits at.
        fused: whether its placed block (``NeuralMap.placed``) is currently fused into the map.
    """

    submap_id: int
    T_W_A_encoded: np.ndarray
    original: CompactBlock
    T_W_A: np.ndarray
    fused: bool = False

    @property
    def is_moved(self) -> bool:
        """Whether it sits anywhere but where it was encoded."""
        return not np.array_equal(self.T_W_A, self.T_W_A_encoded)

    def nbytes(self) -> int:
        """Bytes the submap keeps (its compact original and two poses)."""
        return self.original.nbytes() + 2 * 16 * 8


def _model_from_config(cfg: MapConfig) -> PriorModel:
    """The prior of ``cfg``: its weights file, else the shipped prior (an error if missing)."""
    if cfg.weights_path is None:
        return load_default_prior()
    return PriorModel.load(cfg.weights_path)


class NeuralMap:
    """Sparse global map of voxel latents (see :mod:`mapping` and docs/design.md §3)."""

    def __init__(self, cfg: MapConfig, model: PriorModel | None = None) -> None:
        self.cfg = cfg
        self.device = resolve_device(cfg.device)
        model = model if model is not None else _model_from_config(cfg)
        # the map moves the model to its device and puts it in eval mode (all map code runs
        # under torch.no_grad, so a model that is being trained elsewhere is not frozen)
        self.model = model.to(self.device).eval()
        self.voxel_size_m = cfg.voxel_size_m
        self._store = VoxelStore(self.model.latent_channels, self.device)
        self._fused_ids: set[int] = set()
        self._mesher = ChunkMesher(
            voxel_size_m=cfg.voxel_size_m,
            subdivisions=cfg.mesh_subdivisions,
            chunk_voxels=cfg.mesh_chunk_voxels,
            max_sigma_vu=cfg.mesh_max_sigma_vu,
            min_weight=cfg.min_weight_to_decode,
        )

    # ------------------------------------------------------------------ submaps
    def encode(
        self, submap_id: int, points_A: np.ndarray, normals_A: np.ndarray, T_W_A: np.ndarray
    ) -> Submap:
        """Encode points (anchor frame ``A``) at pose ``T_W_A`` onto the world grid; no fusing.

        Points or normals that are not finite, and zero normals, are dropped; the rest are
        pruned by ``min_points_per_voxel`` and encoded with their Jacobians.
        """
        T = check_rigid(T_W_A, "T_W_A")
        points_A = np.asarray(points_A, dtype=np.float64)
        normals_A = np.asarray(normals_A, dtype=np.float64)
        if points_A.ndim != 2 or points_A.shape[1] != 3 or normals_A.shape != points_A.shape:
            raise ValueError(
                f"encode: points {points_A.shape} and normals {normals_A.shape} must both be (N, 3)"
            )
        finite = np.isfinite(points_A).all(1) & np.isfinite(normals_A).all(1)
        points_W = points_A[finite] @ T[:3, :3].T + T[:3, 3]
        normals_W = normals_A[finite] @ T[:3, :3].T
        norm = np.linalg.norm(normals_W, axis=1, keepdims=True)
        good = norm[:, 0] > 1e-9
        block = encode_points(
            self.model,
            torch.from_numpy(points_W[good]),
            torch.from_numpy(normals_W[good] / norm[good]),
            self.voxel_size_m,
            min_points_per_voxel=self.cfg.min_points_per_voxel,
            jacobian_pairs_per_voxel=self.cfg.jacobian_pairs_per_voxel,
            table_nodes=self.cfg.encoder_table_nodes,
        )
        return Submap(
            submap_id=int(submap_id),
            T_W_A_encoded=T.copy(),
            original=self.compress(block),
            T_W_A=T.copy(),
            fused=False,
        )

    def compress(self, block: VoxelBlock) -> CompactBlock:
        """A block with Jacobians in this map's storage form (ranks and dtype of the config)."""
        cfg = self.cfg
        return CompactBlock.compress(
            block, cfg.latent_rank, cfg.jacobian_rank, cfg.storage_dtype, cfg.jacobian_storage
        )

    def placed(self, submap: Submap) -> VoxelBlock:
        """What the submap contributes to the global map at its current pose ``T_W_A``.

        Deterministic in the original and the pose, so removing a submap subtracts exactly the
        block that fusing it added.
        """
        if not submap.is_moved:
            return submap.original.decompress(with_jacobians=False)
        return transform_block(
            submap.original.decompress(with_jacobians=self.cfg.transform_use_jacobian),
            submap.T_W_A @ np.linalg.inv(submap.T_W_A_encoded),
            self.voxel_size_m,
            neighbors=self.cfg.transform_neighbors,
            use_jacobian=self.cfg.transform_use_jacobian,
            weighting=self.cfg.transform_weighting,
            sigma_vu=self.cfg.transform_sigma_vu,
        )

    def fuse(self, submap: Submap) -> None:
        """Add the submap's placed block to the global map."""
        if submap.fused or submap.submap_id in self._fused_ids:
            raise ValueError(f"submap {submap.submap_id} is already fused; remove it first")
        self._store.add(self.placed(submap))
        submap.fused = True
        self._fused_ids.add(submap.submap_id)

    def remove(self, submap: Submap) -> None:
        """Subtract the submap's placed block; refuses a submap that is not fused."""
        if not submap.fused or submap.submap_id not in self._fused_ids:
            raise ValueError(
                f"submap {submap.submap_id} is not fused in this map; cannot remove it"
            )
        self._store.subtract(self.placed(submap))
        submap.fused = False
        self._fused_ids.discard(submap.submap_id)

    def move(self, submap: Submap, T_W_A_new: np.ndarray) -> None:
        """Re-place a submap at ``T_W_A_new`` from its original encoding.

        A fused submap is removed at its old pose and fused at the new one; an unfused one only
        gets the new pose.
        """
        T_new = check_rigid(T_W_A_new, "T_W_A_new")
        was_fused = submap.fused
        if was_fused:
            self.remove(submap)
        submap.T_W_A = T_new.copy()
        if was_fused:
            self.fuse(submap)

    # ------------------------------------------------------------------ field
    def query_sdf(self, points_W: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """SDF mean and std. dev. in metres and validity at world points ``(N, 3)``."""
        pts = torch.from_numpy(np.asarray(points_W, dtype=np.float64).reshape(-1, 3))
        sdf, sigma, valid = query_field(
            self._store,
            self.model.decoder,
            pts,
            self.voxel_size_m,
            self.cfg.min_weight_to_decode,
        )
        v = self.voxel_size_m
        return (
            sdf.cpu().numpy().astype(np.float64) * v,
            sigma.cpu().numpy().astype(np.float64) * v,
            valid.cpu().numpy(),
        )

    def extract_mesh(
        self, threads: int = 1, chunks_per_batch: int = CHUNKS_PER_BATCH
    ) -> trimesh.Trimesh:
        """The map's mesh; only chunks touched since the last call are re-meshed.

        ``threads > 1`` meshes on that many threads, each running torch with its intra-op
        threads: give more than one only where torch has a single intra-op thread and the
        cores are otherwise idle (the whole-map mesh after a run). ``chunks_per_batch``: see
        :meth:`~mapping.meshing.ChunkMesher.update`.
        """
        self._mesher.update(
            self._store,
            self.model.decoder,
            self._store.take_dirty(),
            threads=threads,
            chunks_per_batch=chunks_per_batch,
        )
        return self._mesher.mesh()

    # ------------------------------------------------------------------ inspection
    def voxel_centers(self) -> tuple[np.ndarray, np.ndarray]:
        """World centres ``(M, 3)`` float64 and weights ``(M,)`` float32 of all voxels (keys and
        weights only: a viewer's snapshot of the map after every map job copies no latents)."""
        keys = unpack_keys(self._store.sorted_keys()).cpu().numpy()
        weights = self._store.weights64().to(torch.float32).cpu().numpy()
        return (keys.astype(np.float64) + 0.5) * self.voxel_size_m, weights

    def voxel_block(self) -> VoxelBlock:
        """All voxels of the global map as a block (a copy, without Jacobians)."""
        return self._store.block()

    @property
    def num_voxels(self) -> int:
        return self._store.num_voxels

    @property
    def fused_ids(self) -> frozenset[int]:
        return frozenset(self._fused_ids)

    def memory_bytes(self) -> int:
        """Bytes of the global voxel storage (allocated capacity included; submaps not counted)."""
        return self._store.memory_bytes()
