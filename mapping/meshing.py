"""Incremental meshing of the neural map (docs/design.md §3.6).

The SDF is sampled on a global lattice of spacing ``h = V / s`` (``s`` = subdivisions) with the
blend of :mod:`mapping.field`: every decodable voxel is decoded at the lattice nodes strictly
inside its ``2V`` cube (``(2s - 1)^3`` nodes for even ``s``; the nodes on the cube's boundary have
zero trilinear weight), and the contributions ``tent / sigma`` are accumulated per node. So a
node's value equals :func:`mapping.field.query_field` at that node.

The lattice is cut into cubic chunks of ``chunk_voxels`` voxels per edge; each chunk holds its own
dense ``(chunk_voxels s + 1)^3`` node array (faces shared with neighbours), runs scikit-image
marching cubes on the cells whose 8 corners are all observed, drops triangles with a vertex sigma
above the threshold and caches the result. Changed voxels mark the chunks their cube reaches as
dirty; only those are re-meshed. The chunk meshes are concatenated and only the vertices on chunk
faces (the only ones two chunks can share) are welded. A chunk whose marching cubes fails is left
out with a warning that counts them (:attr:`ChunkMesher.failed_chunks`); a chunk with no surface in
its observed cells is simply empty.

Memory: a chunk is cached as marching cubes' float32 lattice coordinates and faces in the
smallest integer type that indexes its vertices (a third of float64 world vertices and int64
faces; the world vertices are computed from them exactly when the mesh is assembled); the
assembled mesh is not cached (the caller's is the only copy); and the free heap pages the batches'
temporaries leave in glibc's arenas go back to the OS every few batches and after assembling.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
import trimesh

from common.memory import release_freed_memory
from common.voxel_keys import pack_keys, unpack_keys
from mapping.field import decode_indexed, decode_lattice, voxel_query_terms
from mapping.mesh_lattice import lattice_offsets, needed_fine_nodes, normalise, upsample
from mapping.networks import Decoder
from mapping.voxel_store import VoxelStore

log = logging.getLogger(__name__)

CHUNKS_PER_BATCH = 32
TRIM_EVERY_BATCHES = 8  # free heap pages back to the OS this often while meshing (see update)
FACE_ROWS = 1 << 20  # faces re-indexed per step when welding (bounds the temporary)
_NEIGHBOUR_SHIFTS = torch.stack(
    torch.meshgrid(*(torch.arange(-1, 2),) * 3, indexing="ij"), dim=-1
).reshape(-1, 3)


class ChunkMesher:
    """Caches one triangle mesh per chunk and re-meshes dirty chunks on request."""

    def __init__(
        self,
        voxel_size_m: float,
        subdivisions: int,
        chunk_voxels: int,
        max_sigma_vu: float,
        min_weight: float,
        coarse_to_fine: bool = True,
    ) -> None:
        self.voxel_size_m = voxel_size_m
        self.subdivisions = subdivisions
        self.chunk_voxels = chunk_voxels
        self.max_sigma_vu = max_sigma_vu
        self.min_weight = min_weight
        # per chunk: lattice vertices (from the chunk's corner node), faces, and which vertices
        # lie on the chunk's faces
        self._chunks: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.failed_chunks = 0  # chunks whose marching cubes failed (whole lifetime)
        self.last_remeshed = torch.zeros(0, dtype=torch.int64)  # packed chunk keys, last update
        self._fine = lattice_offsets(subdivisions)
        # coarse-to-fine: a half-voxel lattice decides where the fine lattice is decoded
        even = subdivisions % 2 == 0 and subdivisions >= 4
        self._coarse_factor = subdivisions // 2 if coarse_to_fine and even else 1
        self._coarse = lattice_offsets(2) if self._coarse_factor > 1 else None

    @property
    def num_chunks(self) -> int:
        return len(self._chunks)

    def clear(self) -> None:
        self._chunks.clear()

    def dirty_chunks(self, dirty_voxel_keys: torch.Tensor) -> torch.Tensor:
        """Packed chunk keys whose node range a changed voxel's ``2V`` cube reaches."""
        if dirty_voxel_keys.numel() == 0:
            return dirty_voxel_keys
        grid = unpack_keys(dirty_voxel_keys)
        found = [torch.unique(chunk) for _, chunk in self._reached_chunks(grid)]
        return torch.unique(torch.cat(found))

    def _reached_chunks(self, grid: torch.Tensor) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        """``(voxel index, packed chunk)`` per neighbour shift: the chunks each voxel's ``2V``
        cube reaches, its own and, on a chunk face, the neighbours across it (memory O(D) a
        shift, not O(27 D)): a shift of -1 along an axis only for local == 0, +1 only for
        local == cs - 1."""
        cs = self.chunk_voxels
        own = torch.div(grid, cs, rounding_mode="floor")
        local = grid - own * cs
        low, high = local == 0, local == cs - 1
        for shift in _NEIGHBOUR_SHIFTS.tolist():
            ok = torch.ones(grid.shape[0], dtype=torch.bool, device=grid.device)
            for axis, step in enumerate(shift):
                if step:
                    ok &= (low if step < 0 else high)[:, axis]
            voxel = ok.nonzero().squeeze(1)
            yield voxel, pack_keys(own[voxel] + torch.tensor(shift, device=grid.device))

    @torch.no_grad()
    def update(
        self,
        store: VoxelStore,
        decoder: Decoder,
        dirty_voxel_keys: torch.Tensor,
        threads: int = 1,
        chunks_per_batch: int = CHUNKS_PER_BATCH,
    ) -> None:
        """Re-mesh every chunk touched by ``dirty_voxel_keys`` (packed).

        ``threads > 1`` meshes batches of chunks on that many Python threads (torch and
        scikit-image release the GIL); each batch is meshed alone, so the result is the same.
        A batch of ``chunks_per_batch`` chunks decodes each of its voxels once: a voxel on a chunk
        face also feeds the neighbouring chunk, and where that chunk is in another batch it is
        decoded again there (a fifth more decodes at 32 on a street submap's 300 chunks). More
        chunks per batch decode less twice, for memory that grows with the batch (about 0.15 MiB
        a chunk of 8 voxels at 2 subdivisions); the meshes are the same.
        Every :data:`TRIM_EVERY_BATCHES` batches the free heap pages go back to the OS: a batch's
        decode temporaries are blocks of ~2 MB, below glibc's mmap threshold, and without the
        trims the mesh threads' arenas grew by ~400 MiB over the whole-map mesh of the full
        generated KITTI 00 run. Each trim costs ~10 ms plus re-faulting the pages; on that mesh,
        every 8th batch peaked within ~5 MiB of every 4th (50 MiB below every 16th) for ~2 % more
        CPU time than no trims (every 4th: ~8 %).
        """
        chunks = self.dirty_chunks(dirty_voxel_keys)
        self.last_remeshed = chunks
        if chunks.numel() == 0:
            return
        failures: list[tuple[int, str]] = []
        keys = store.sorted_keys()
        rows = store.rows()
        decodable = store.weights64() >= self.min_weight
        grid = unpack_keys(keys[decodable])
        rows = rows[decodable]
        pair_voxel, pair_chunk = self._voxel_chunk_pairs(grid, chunks)
        batches = torch.split(chunks, chunks_per_batch)

        @torch.no_grad()  # grad mode is per thread: the pool's threads do not inherit it
        def mesh_batch(batch: torch.Tensor) -> list:
            lo = torch.searchsorted(pair_chunk, batch[0])
            hi = torch.searchsorted(pair_chunk, batch[-1], right=True)
            return self._mesh_batch(
                store, decoder, batch, grid, rows, pair_voxel[lo:hi], pair_chunk[lo:hi]
            )

        with ThreadPoolExecutor(max_workers=max(1, threads), thread_name_prefix="mesh") as pool:
            # taken as they finish (in order), so that a batch's meshes are stored at once
            if threads > 1 and len(batches) > 1:
                results = pool.map(mesh_batch, batches)
            else:
                results = map(mesh_batch, batches)
            for i, (batch, meshes) in enumerate(zip(batches, results, strict=True)):
                for key, mesh in zip(batch.tolist(), meshes, strict=True):
                    if isinstance(mesh, str):
                        failures.append((key, mesh))
                        mesh = None
                    if mesh is None:
                        self._chunks.pop(key, None)
                    else:
                        self._chunks[key] = mesh
                if i % TRIM_EVERY_BATCHES == TRIM_EVERY_BATCHES - 1:
                    release_freed_memory()
        release_freed_memory()
        if failures:
            self.failed_chunks += len(failures)
            key, reason = failures[0]
            log.warning(
                "meshing: marching cubes failed on %d of %d re-meshed chunks (%d so far), which "
                "are left out of the mesh; first: chunk %s: %s",
                len(failures),
                chunks.shape[0],
                self.failed_chunks,
                unpack_keys(torch.tensor([key])).tolist()[0],
                reason,
            )

    def _voxel_chunk_pairs(
        self, grid: torch.Tensor, chunks: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(voxel index, packed chunk) pairs for the dirty chunks, sorted by (chunk, voxel)."""
        voxels, chunk_keys = [], []
        for voxel, chunk in self._reached_chunks(grid):
            pos = torch.searchsorted(chunks, chunk).clamp_(max=chunks.shape[0] - 1)
            wanted = chunks[pos] == chunk
            voxels.append(voxel[wanted])
            chunk_keys.append(chunk[wanted])
        voxel, chunk = torch.cat(voxels), torch.cat(chunk_keys)
        order = torch.argsort(voxel)
        order = order[torch.argsort(chunk[order], stable=True)]
        return voxel[order], chunk[order]

    def _accumulate(
        self,
        level: int,
        halo: int,
        lattice: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        terms: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        decoder: Decoder,
        n_chunks: int,
        voxel_grid: torch.Tensor,
        pair_inv: torch.Tensor,
        pair_slot: torch.Tensor,
        pair_origin: torch.Tensor,
        needed: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Blend the decodes of all (voxel, node) pairs into dense per-chunk node arrays.

        ``level`` lattice cells per voxel edge, ``halo`` extra nodes on each side of a chunk;
        ``needed`` (flat bool over the arrays) restricts decoding to those nodes. Returns the
        flat sums ``num = sum b mean``, ``den = sum b``, ``sig = sum b sigma`` with
        ``b = tent / sigma``.
        """
        node_idx, q, tent = (t.to(voxel_grid.device) for t in lattice)
        n_side = self.chunk_voxels * level + 1 + 2 * halo
        n_nodes = n_side**3
        base = voxel_grid[pair_inv] * level - pair_origin * (self.chunk_voxels * level) + halo
        # a node's index in its chunk's array is linear in its lattice position: per pair and
        # per node offset, added; a node is inside when every axis is (one axis at a time)
        strides = torch.tensor([n_side * n_side, n_side, 1], device=base.device)
        flat = (pair_slot * n_nodes + base @ strides).unsqueeze(1) + node_idx @ strides  # (P, Q)
        inside = None
        for axis in range(3):
            position = base[:, axis : axis + 1] + node_idx[:, axis]
            ok = (position >= 0) & (position < n_side)
            inside = ok if inside is None else inside.logical_and_(ok)
        if needed is not None:
            inside.logical_and_(needed[flat.clamp(0, needed.numel() - 1)])
        entry_pair, entry_k = inside.nonzero(as_tuple=True)
        flat = flat[entry_pair, entry_k]
        voxel = pair_inv[entry_pair]
        code, A, latents = terms
        if needed is None:
            mean_u, sigma_u = decode_lattice(decoder, latents, q, (code, A))
            mean, sigma = mean_u[voxel, entry_k], sigma_u[voxel, entry_k]
        else:
            key = voxel * q.shape[0] + entry_k
            uniq, inv = torch.unique(key, return_inverse=True)
            m, sg = decode_indexed(
                decoder,
                code,
                A,
                q,
                torch.div(uniq, q.shape[0], rounding_mode="floor"),
                uniq % q.shape[0],
            )
            mean, sigma = m[inv], sg[inv]
        b = tent[entry_k] / sigma
        size = n_chunks * n_nodes
        num = torch.zeros(size, device=b.device).index_add_(0, flat, b * mean)
        den = torch.zeros(size, device=b.device).index_add_(0, flat, b)
        sig = torch.zeros(size, device=b.device).index_add_(0, flat, b * sigma)
        return num, den, sig

    def _mesh_batch(
        self,
        store: VoxelStore,
        decoder: Decoder,
        batch: torch.Tensor,
        grid: torch.Tensor,
        rows: torch.Tensor,
        pair_voxel: torch.Tensor,
        pair_chunk: torch.Tensor,
    ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray] | str | None]:
        n_chunks = batch.shape[0]
        if pair_voxel.numel() == 0:
            return [None] * n_chunks
        s = self.subdivisions
        cs = self.chunk_voxels
        n_fine = cs * s + 1
        voxels, inv = torch.unique(pair_voxel, return_inverse=True)
        latents = store.latents_at(rows[voxels])
        terms = (*voxel_query_terms(decoder, latents), latents)
        voxel_grid = grid[voxels]
        slot = torch.searchsorted(batch, pair_chunk)
        origin = unpack_keys(pair_chunk)
        common = (decoder, n_chunks, voxel_grid, inv, slot, origin)
        shape = (n_chunks, n_fine, n_fine, n_fine)
        if self._coarse is None:
            num, den, sig = self._accumulate(s, 0, self._fine, terms, *common, None)
            sdf, sigma, valid = normalise(num.view(shape), den.view(shape), sig.view(shape))
        else:
            n_coarse = cs * 2 + 3  # half-voxel lattice with one halo node on each side
            cshape = (n_chunks, n_coarse, n_coarse, n_coarse)
            c_num, c_den, c_sig = self._accumulate(2, 1, self._coarse, terms, *common, None)
            c_sdf, c_sigma, c_valid = normalise(
                c_num.view(cshape), c_den.view(cshape), c_sig.view(cshape)
            )
            needed = needed_fine_nodes(c_sdf, c_valid, self._coarse_factor, n_fine)
            num, den, sig = self._accumulate(s, 0, self._fine, terms, *common, needed.reshape(-1))
            f_sdf, f_sigma, f_valid = normalise(num.view(shape), den.view(shape), sig.view(shape))
            inner = (slice(None), slice(1, -1), slice(1, -1), slice(1, -1))
            i_sdf, i_sigma, i_valid = upsample(c_sdf[inner], c_sigma[inner], c_valid[inner], n_fine)
            sdf = torch.where(needed, f_sdf, i_sdf)
            sigma = torch.where(needed, f_sigma, i_sigma)
            valid = torch.where(needed, f_valid, i_valid)
        # the whole batch at once: a chunk marches when its observed nodes have both signs and
        # it has a cell whose 8 corners are all observed
        dims = (1, 2, 3)
        cell_ok = torch.ones_like(valid[:, 1:, 1:, 1:])
        for i in (0, 1):
            for j in (0, 1):
                for k in (0, 1):
                    cell_ok &= valid[:, i : n_fine - 1 + i, j : n_fine - 1 + j, k : n_fine - 1 + k]
        march = (
            (valid & (sdf <= 0)).any(dims)
            & (valid & (sdf >= 0)).any(dims)
            & cell_ok.flatten(1).any(1)
        ).tolist()
        # scikit-image tests the mask at a cell's upper corner (checked by tests/test_meshing.py)
        mask = torch.zeros_like(valid)
        mask[:, 1:, 1:, 1:] = cell_ok
        sdf = torch.where(valid, sdf.to(torch.float32), 1.0).cpu().numpy()
        sigma = torch.where(valid, sigma, 1e9).cpu().numpy()
        mask = mask.cpu().numpy()
        return [
            self._march(sdf[i], sigma[i], mask[i]) if march[i] else None for i in range(n_chunks)
        ]

    def _march(
        self, sdf: np.ndarray, sigma: np.ndarray, mask: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str | None:
        """One chunk's mesh ``(lattice vertices, faces, on-chunk-face mask)``, None when it has no
        surface, or the reason marching cubes failed; ``sdf``, ``sigma``: the node arrays (1 and
        1e9 where unobserved), ``mask``: the cells to march (at their upper corner). The vertices
        are marching cubes' own (float32, in lattice steps from the chunk's first node):
        :meth:`_assemble` makes world coordinates of them."""
        from scipy.ndimage import map_coordinates
        from skimage.measure import marching_cubes

        try:
            verts, faces, _, _ = marching_cubes(sdf, level=0.0, mask=mask, allow_degenerate=False)
        except RuntimeError as exc:
            if "No surface found" in str(exc):  # the sign changes are all in unobserved cells
                return None
            return f"{type(exc).__name__}: {exc}"
        except ValueError as exc:
            return f"{type(exc).__name__}: {exc}"
        if faces.shape[0] == 0:
            return None
        vert_sigma = map_coordinates(sigma, verts.T, order=1)
        keep = (vert_sigma[faces] <= self.max_sigma_vu).all(1)
        faces = faces[keep]
        if faces.shape[0] == 0:
            return None
        is_used = np.zeros(len(verts), dtype=bool)
        is_used[faces] = True
        used = np.flatnonzero(is_used)
        faces = (np.cumsum(is_used) - 1)[faces]  # the kept vertices renumbered in their order
        local = verts[used]
        # marching cubes puts a vertex on a lattice edge, so the coordinate across a chunk face
        # is exactly the face's node index
        on_face = ((local == 0) | (local == sdf.shape[0] - 1)).any(axis=1)
        index_type = np.min_scalar_type(max(len(used) - 1, 0))
        return local, faces.reshape(-1, 3).astype(index_type), on_face

    def mesh(self) -> trimesh.Trimesh:
        """All cached chunk meshes, concatenated, with the vertices on chunk faces welded (a new
        mesh on every call)."""
        mesh = self._assemble()
        release_freed_memory()
        return mesh

    def _assemble(self) -> trimesh.Trimesh:
        if not self._chunks:
            return trimesh.Trimesh(
                np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), process=False
            )
        keys = sorted(self._chunks)
        parts = [self._chunks[key] for key in keys]
        n_verts = np.array([v.shape[0] for v, _, _ in parts], dtype=np.int64)
        n_faces = np.array([f.shape[0] for _, f, _ in parts], dtype=np.int64)
        h = self.voxel_size_m / self.subdivisions
        # world vertex = (lattice vertex + chunk corner node) * h, in float64
        V = np.concatenate([v for v, _, _ in parts], dtype=np.float64)
        corners = unpack_keys(np.asarray(keys, dtype=np.int64)) * (
            self.chunk_voxels * self.subdivisions
        )
        for axis in range(3):
            V[:, axis] += np.repeat(corners[:, axis], n_verts)
        V *= h
        F = np.concatenate([f for _, f, _ in parts], dtype=np.int64)
        F += np.repeat(np.cumsum(n_verts) - n_verts, n_faces)[:, None]
        shared = np.flatnonzero(np.concatenate([b for _, _, b in parts]))
        del parts
        if len(shared):
            # weld on a 1/4096 lattice-step grid (the same vertex from two chunks differs only
            # by float rounding)
            quantised = np.round(V[shared] * (4096.0 / h)).astype(np.int64)
            _, first, inverse = np.unique(quantised, axis=0, return_index=True, return_inverse=True)
            del quantised
            target = np.arange(len(V))
            target[shared] = shared[first[inverse.reshape(-1)]]
            keep = np.ones(len(V), dtype=bool)
            keep[shared] = target[shared] == shared
            new_index = np.cumsum(keep) - 1
            remap = new_index[target]
            del target, new_index
            for start in range(0, len(F), FACE_ROWS):  # in place, a block at a time
                F[start : start + FACE_ROWS] = remap[F[start : start + FACE_ROWS]]
            del remap
            V = V[keep]
            good = (F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])
            if not good.all():
                F = F[good]
                used = np.zeros(len(V), dtype=bool)
                used[F.reshape(-1)] = True
                if not used.all():
                    V = V[used]
                    F = (np.cumsum(used) - 1)[F]
        return trimesh.Trimesh(V, F, process=False)
