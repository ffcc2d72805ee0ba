"""The global sparse voxel storage with exact weighted-average fusion and removal
(docs/design.md §3.2).

Rows of data (latent, weight) live in growable arrays and never move; a sorted array of packed
int64 keys with their row numbers is the index (look-up by ``searchsorted``). Inserting ``k`` keys
merges them into the index in ``O(N log k)`` without moving any voxel data; freed rows are reused.

The store holds what decoding and meshing read: no Jacobians (only a submap's original encoding
needs them, to be transformed). It is the accumulator of fuse and remove, so it stays float32 for
latents and float64 for weights: removing a submap divides by ``w - w_k``, which amplifies the
rounding of the stored value by ``w / (w - w_k)`` (up to the number of fused submaps), and in
half precision that would leave errors of several per cent after a voxel's dominant contributor is
removed. A voxel whose weight falls to ``<= WEIGHT_TOLERANCE * previous weight`` is deleted; every
contribution is at least 1 (point counts, and convex blends of them), so this never drops a voxel
that another submap still holds.

The keys changed since the last :meth:`VoxelStore.take_dirty` are kept as a list of arrays, merged
into one array of unique keys whenever the list has grown by as many keys as the larger of the
merged array and the map (a run that never meshes before its end would otherwise hold
every fused and removed block's keys, remaps included, and concatenate them all at the end).
"""

from __future__ import annotations

import torch

from common.voxel_keys import unpack_keys
from mapping.voxel_block import VoxelBlock

WEIGHT_TOLERANCE = 1e-6
DIRTY_MERGE_MIN = 1 << 16  # pending changed keys below which they are never merged


def _canonical(block: VoxelBlock) -> tuple[VoxelBlock, torch.Tensor]:
    """The block with sorted keys and its packed keys; duplicate keys are an error."""
    keys = block.packed_keys()
    if keys.shape[0] < 2 or bool((keys[1:] > keys[:-1]).all()):
        return block, keys
    order = torch.argsort(keys)
    keys = keys[order]
    if bool((keys[1:] == keys[:-1]).any()):
        raise ValueError("VoxelBlock has duplicate voxel keys; a block holds each voxel once")
    return block.select(order), keys


class VoxelStore:
    """Sparse voxels keyed by packed int64 grid keys."""

    def __init__(self, channels: int, device: torch.device, capacity: int = 1024) -> None:
        self.channels = channels
        self.device = device
        self._reset(capacity)

    def _reset(self, capacity: int) -> None:
        device = self.device
        channels = self.channels
        self._keys = torch.zeros(0, dtype=torch.int64, device=device)
        self._rows = torch.zeros(0, dtype=torch.int64, device=device)
        self._latents = torch.zeros(capacity, channels, 3, device=device)
        self._weights = torch.zeros(capacity, dtype=torch.float64, device=device)
        self._free = torch.arange(capacity - 1, -1, -1, device=device)  # stack, top at the end
        self._dirty: list[torch.Tensor] = []
        self._dirty_count = 0  # keys in self._dirty
        self._dirty_merged = 0  # keys in its first array when that is the result of a merge

    # ------------------------------------------------------------------ queries
    @property
    def num_voxels(self) -> int:
        return int(self._keys.shape[0])

    def lookup(self, keys: torch.Tensor) -> torch.Tensor:
        """Rows of packed ``keys`` (any order), ``-1`` where absent."""
        if self._keys.numel() == 0:
            return torch.full_like(keys, -1)
        pos = torch.searchsorted(self._keys, keys).clamp_(max=self._keys.shape[0] - 1)
        found = self._keys[pos] == keys
        return torch.where(found, self._rows[pos], torch.full_like(pos, -1))

    def block(self) -> VoxelBlock:
        """All voxels as a block (sorted keys, no Jacobians), weights cast to float32."""
        rows = self._rows
        return VoxelBlock(
            keys=unpack_keys(self._keys),
            latents=self._latents[rows],
            weights=self._weights[rows].to(torch.float32),
        )

    def sorted_keys(self) -> torch.Tensor:
        return self._keys

    def rows(self) -> torch.Tensor:
        """Row numbers aligned with :meth:`sorted_keys`."""
        return self._rows

    def latents_at(self, rows: torch.Tensor) -> torch.Tensor:
        return self._latents[rows]

    def weights_at(self, rows: torch.Tensor) -> torch.Tensor:
        return self._weights[rows]

    def weights64(self) -> torch.Tensor:
        """Float64 weights aligned with :meth:`sorted_keys`."""
        return self._weights[self._rows]

    def memory_bytes(self) -> int:
        """Bytes of all allocated arrays (capacity included)."""
        tensors = (
            self._keys,
            self._rows,
            self._latents,
            self._weights,
            self._free,
        )
        return sum(t.element_size() * t.numel() for t in tensors)

    def take_dirty(self) -> torch.Tensor:
        """Packed keys changed since the last call (unique, sorted)."""
        if not self._dirty:
            return torch.zeros(0, dtype=torch.int64, device=self.device)
        dirty = torch.unique(torch.cat(self._dirty))
        self._dirty = []
        self._dirty_count = self._dirty_merged = 0
        return dirty

    def _mark_dirty(self, keys: torch.Tensor) -> None:
        """Record changed keys; merge the record when it has grown enough (amortised O(1) a key,
        the record stays below twice the keys it stands for plus the map)."""
        self._dirty.append(keys)
        self._dirty_count += keys.shape[0]
        grown = self._dirty_count - self._dirty_merged
        if grown >= max(self._dirty_merged, self.num_voxels, DIRTY_MERGE_MIN):
            merged = torch.unique(torch.cat(self._dirty))
            self._dirty = [merged]
            self._dirty_count = self._dirty_merged = merged.shape[0]

    # ------------------------------------------------------------------ updates
    def add(self, block: VoxelBlock) -> None:
        """Fuse: ``F <- (F w + F_k w_k) / (w + w_k)``, ``w <- w + w_k``."""
        if block.num_voxels == 0:
            return
        block, keys = _canonical(block.to(self.device))
        rows = self.lookup(keys)
        found = rows >= 0
        n_found = int(found.sum())
        w_new = block.weights.to(torch.float64)
        if n_found == keys.shape[0]:
            self._blend(rows, block.latents, w_new)
        else:
            hit = found.nonzero().squeeze(1)
            miss = (~found).nonzero().squeeze(1)
            if n_found:
                self._blend(rows[hit], block.latents[hit], w_new[hit])
            r = self._allocate(miss.shape[0])
            self._latents[r] = block.latents[miss]
            self._weights[r] = w_new[miss]
            self._insert(keys[miss], r)
        self._mark_dirty(keys)

    def subtract(self, block: VoxelBlock) -> None:
        """Remove: ``F <- (F w - F_k w_k) / (w - w_k)``, ``w <- w - w_k``; drop emptied voxels.

        The block must be one that was fused (every key present with at least its weight);
        anything else means broken bookkeeping and raises ``ValueError`` before changing the map.
        """
        if block.num_voxels == 0:
            return
        block, keys = _canonical(block.to(self.device))
        rows = self.lookup(keys)
        latents, w_k = block.latents, block.weights.to(torch.float64)
        missing = int((rows < 0).sum())
        if missing:
            raise ValueError(
                f"remove: {missing} of {keys.shape[0]} voxels of the block are not in the map; "
                "only a block that was fused can be removed"
            )
        w_old = self._weights[rows]
        excess = int((w_k > w_old * (1.0 + 1e-6) + 1e-6).sum())
        if excess:
            raise ValueError(
                f"remove: {excess} voxels of the block weigh more than the map holds there; "
                "only a block that was fused can be removed"
            )
        alive = (w_old - w_k) > WEIGHT_TOLERANCE * torch.clamp(w_old, min=1.0)
        if bool(alive.all()):
            self._blend(rows, latents, -w_k)
        else:
            live = alive.nonzero().squeeze(1)
            dead = (~alive).nonzero().squeeze(1)
            self._blend(rows[live], latents[live], -w_k[live])
            self._delete(keys[dead], rows[dead])
        self._mark_dirty(keys)

    def _blend(self, rows: torch.Tensor, latents: torch.Tensor, w_k: torch.Tensor) -> None:
        """``F <- (F w + F_k w_k) / (w + w_k)`` at ``rows``; a negative ``w_k`` removes.

        Written as ``lerp(F, F_k, w_k / (w + w_k))``; the caller guarantees ``w + w_k > 0``.
        """
        total = self._weights.index_select(0, rows) + w_k
        t = (w_k / total).to(torch.float32)
        old = self._latents.index_select(0, rows)
        self._latents.index_copy_(0, rows, old.lerp_(latents, t.view(-1, 1, 1)))
        self._weights.index_copy_(0, rows, total)

    def clear(self) -> None:
        """Drop every voxel (the changed keys are reported by :meth:`take_dirty`)."""
        dirty = self._keys
        self._reset(1024)
        self._mark_dirty(dirty)

    # ------------------------------------------------------------------ internals
    def _allocate(self, n: int) -> torch.Tensor:
        if n == 0:
            return torch.zeros(0, dtype=torch.int64, device=self.device)
        if n > self._free.shape[0]:
            self._grow(n - self._free.shape[0])
        rows = self._free[-n:].flip(0)
        self._free = self._free[:-n]
        return rows

    def _grow(self, extra: int) -> None:
        old = self._weights.shape[0]
        new = max(2 * old, old + extra)

        def grow(t: torch.Tensor) -> torch.Tensor:
            out = torch.zeros((new, *t.shape[1:]), dtype=t.dtype, device=t.device)
            out[:old] = t
            return out

        self._latents = grow(self._latents)
        self._weights = grow(self._weights)
        fresh = torch.arange(new - 1, old - 1, -1, device=self.device)
        self._free = torch.cat([fresh, self._free])

    def _insert(self, new_keys: torch.Tensor, new_rows: torch.Tensor) -> None:
        """Merge sorted, absent ``new_keys`` into the sorted index."""
        n_old = self._keys.shape[0]
        n_new = new_keys.shape[0]
        pos_new = torch.searchsorted(self._keys, new_keys) + torch.arange(n_new, device=self.device)
        pos_old = torch.arange(n_old, device=self.device) + torch.searchsorted(new_keys, self._keys)
        keys = torch.empty(n_old + n_new, dtype=torch.int64, device=self.device)
        rows = torch.empty_like(keys)
        keys[pos_old] = self._keys
        rows[pos_old] = self._rows
        keys[pos_new] = new_keys
        rows[pos_new] = new_rows
        self._keys, self._rows = keys, rows

    def _delete(self, dead_keys: torch.Tensor, dead_rows: torch.Tensor) -> None:
        pos = torch.searchsorted(self._keys, dead_keys)
        keep = torch.ones(self._keys.shape[0], dtype=torch.bool, device=self.device)
        keep[pos] = False
        self._keys = self._keys[keep]
        self._rows = self._rows[keep]
        self._latents[dead_rows] = 0.0
        self._weights[dead_rows] = 0.0
        self._free = torch.cat([self._free, dead_rows])
