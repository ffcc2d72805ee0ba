"""A compact LiDAR TSDF in numpy: the map a LiDAR mapping system would otherwise keep.

Each scan point is sampled at offsets of one voxel from ``-truncation`` to ``+truncation`` along
its ray; each sample's voxel receives the projective signed distance ``range(point) - |centre -
origin|`` (clipped to the truncation) with weight 1, and a voxel's value is the mean over all
scans. Samples are reduced per batch with ``np.unique``/``np.bincount`` into one sorted array of
packed voxel keys (``common.voxel_keys``). The surface is meshed by marching cubes on blocks of
``BLOCK``^3 voxels, many blocks per call. Memory is reported as a block-hashed TSDF allocates
it (Voxblox, Open3D): every block holding an observed voxel, times ``BYTES_PER_VOXEL``.
"""

from __future__ import annotations

import numpy as np
import trimesh

from common.voxel_keys import pack_keys, unpack_keys

BLOCK = 8
"""Voxels per block edge, for meshing and the memory estimate."""
BYTES_PER_VOXEL = 8
"""float32 signed distance and float32 weight per voxel of an allocated block."""
BATCH_SAMPLES = 4_000_000
"""Ray samples reduced at a time before they are merged into the store."""
BLOCKS_PER_CALL = 4096
"""Blocks stacked into one marching-cubes volume."""


class LidarTsdf:
    """Sparse TSDF of LiDAR scans (see the module docstring).

    Args:
        voxel_m: voxel edge (metres).
        truncation_m: half-width of the band integrated around each hit (default 3 voxels).
        min_weight: voxels with fewer samples are left out of the mesh.
    """

    def __init__(self, voxel_m: float, truncation_m: float | None = None, min_weight: float = 1.0):
        self.voxel_m = float(voxel_m)
        self.truncation_m = 3.0 * self.voxel_m if truncation_m is None else float(truncation_m)
        self.min_weight = float(min_weight)
        self._keys = np.zeros(0, dtype=np.int64)
        self._sdf_sum = np.zeros(0, dtype=np.float64)
        self._weight = np.zeros(0, dtype=np.float64)
        self._pending: list[tuple[np.ndarray, np.ndarray]] = []
        self._pending_samples = 0

    def integrate(self, points_S: np.ndarray, T_W_S: np.ndarray) -> None:
        """Add one scan: its points in the sensor frame S, and the sensor pose ``T_W_S``."""
        points_S = np.asarray(points_S, dtype=np.float64).reshape(-1, 3)
        ranges = np.linalg.norm(points_S, axis=1)
        keep = ranges > 1e-6
        points_S, ranges = points_S[keep], ranges[keep]
        if len(points_S) == 0:
            return
        # float32 is exact enough here (5e-5 m at 1 km) and halves the memory traffic
        R, origin = T_W_S[:3, :3], T_W_S[:3, 3].astype(np.float32)
        points_W = (points_S @ R.T + T_W_S[:3, 3]).astype(np.float32)
        rays_W = ((points_S / ranges[:, None]) @ R.T).astype(np.float32)
        ranges = ranges.astype(np.float32)
        steps = int(np.ceil(self.truncation_m / self.voxel_m))
        scale = np.float32(1.0 / self.voxel_m)
        for offset in self.voxel_m * np.arange(-steps, steps + 1):
            grid = np.floor((points_W - np.float32(offset) * rays_W) * scale)
            centres = (grid + np.float32(0.5)) * np.float32(self.voxel_m) - origin
            sdf = ranges - np.sqrt(np.einsum("ij,ij->i", centres, centres))
            inside = np.abs(sdf) <= self.truncation_m
            self._pending.append((pack_keys(grid[inside].astype(np.int64)), sdf[inside]))
            self._pending_samples += int(inside.sum())
        if self._pending_samples >= BATCH_SAMPLES:
            self.flush()

    def flush(self) -> None:
        """Reduce the pending samples per voxel and merge them into the sorted store."""
        if not self._pending:
            return
        keys = np.concatenate([k for k, _ in self._pending])
        sdf = np.concatenate([s for _, s in self._pending])
        self._pending, self._pending_samples = [], 0
        unique, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
        sums = np.bincount(inverse.ravel(), weights=sdf, minlength=len(unique))
        position = np.searchsorted(self._keys, unique)
        found = position < len(self._keys)
        found[found] = self._keys[position[found]] == unique[found]
        self._sdf_sum[position[found]] += sums[found]  # the keys are unique: no repeats
        self._weight[position[found]] += counts[found]
        new = ~found
        self._keys = np.insert(self._keys, position[new], unique[new])
        self._sdf_sum = np.insert(self._sdf_sum, position[new], sums[new])
        self._weight = np.insert(self._weight, position[new], counts[new].astype(np.float64))

    @property
    def num_voxels(self) -> int:
        """Observed voxels."""
        self.flush()
        return len(self._keys)

    def memory_bytes(self) -> int:
        """Bytes a block-hashed TSDF allocates for the observed voxels (module docstring)."""
        self.flush()
        blocks = np.unique(np.floor_divide(unpack_keys(self._keys), BLOCK), axis=0)
        return len(blocks) * BLOCK**3 * BYTES_PER_VOXEL

    def extract_mesh(self) -> trimesh.Trimesh:
        """The zero level set of the observed voxels (world frame)."""
        from skimage.measure import marching_cubes

        self.flush()
        observed = self._weight >= self.min_weight
        keys = self._keys[observed]
        values = (self._sdf_sum[observed] / self._weight[observed]).astype(np.float32)
        if len(keys) == 0:
            return trimesh.Trimesh()
        grid = unpack_keys(keys)
        blocks = np.unique(np.floor_divide(grid, BLOCK), axis=0)
        # a block's cubes reach one voxel into its upper neighbours: also mesh the blocks whose
        # upper neighbours alone hold voxels
        shifts = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        blocks = np.unique((blocks[:, None, :] - shifts[None]).reshape(-1, 3), axis=0)
        side = BLOCK + 1
        local = np.stack(np.meshgrid(*(np.arange(side),) * 3, indexing="ij"), axis=-1)
        local = local.reshape(-1, 3)
        vertices, faces, offset = [], [], 0
        for start in range(0, len(blocks), BLOCKS_PER_CALL):
            chunk = blocks[start : start + BLOCKS_PER_CALL]
            lattice = (chunk[:, None, :] * BLOCK + local[None]).reshape(-1, 3)
            wanted = pack_keys(lattice)
            position = np.minimum(np.searchsorted(keys, wanted), len(keys) - 1)
            known = keys[position] == wanted
            volume = np.where(known, values[position], np.float32(1.0))
            volume = volume.reshape(len(chunk), side, side, side)
            known = known.reshape(len(chunk), side, side, side)
            # a cube is meshed when its 8 corners are observed
            corners = known[:, :-1, :-1, :-1].copy()
            for i, j, k in shifts[1:]:
                corners &= known[:, i : i + BLOCK, j : j + BLOCK, k : k + BLOCK]
            if not corners.any() or volume[known].min() > 0 or volume[known].max() < 0:
                continue
            # stacked along axis 0 with one separating layer; a face is kept when the cube it
            # lies in (the one holding its centroid) is an observed cube of a block
            stacked = np.ones((len(chunk), side + 1, side, side), dtype=np.float32)
            stacked[:, :side] = volume
            valid = np.zeros(stacked.shape, dtype=bool)
            valid[:, :BLOCK, :BLOCK, :BLOCK] = corners
            try:
                verts, tris, _, _ = marching_cubes(stacked.reshape(-1, side, side), 0.0)
            except (ValueError, RuntimeError):  # no crossing in this chunk
                continue
            cube = np.floor(verts[tris].mean(axis=1)).astype(np.int64)
            cube = np.minimum(cube, np.array(valid.reshape(-1, side, side).shape) - 1)
            tris = tris[valid.reshape(-1, side, side)[cube[:, 0], cube[:, 1], cube[:, 2]]]
            if len(tris) == 0:
                continue
            used, tris = np.unique(tris, return_inverse=True)
            tris = tris.reshape(-1, 3)
            verts = verts[used]
            block_of = np.floor(verts[:, 0] / (side + 1)).astype(np.int64)
            verts[:, 0] -= block_of * (side + 1)
            world = (chunk[block_of] * BLOCK + verts + 0.5) * self.voxel_m
            vertices.append(world)
            faces.append(tris + offset)
            offset += len(world)
        if not vertices:
            return trimesh.Trimesh()
        return trimesh.Trimesh(np.concatenate(vertices), np.concatenate(faces), process=False)
