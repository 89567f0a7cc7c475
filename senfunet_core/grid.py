"""Sparse voxel grid: 8^3-voxel blocks allocated on demand, found through sorted int64 keys.

Memory follows the observed surface: only blocks that some ray sample touched exist. Every
per-voxel quantity is a "channel": a pool tensor of shape (capacity, 512, *channel_shape), where
row `slot` holds one block's voxels in x-major order (local index = 64*x + 8*y + z).

Convention: voxel (i, j, k) has its centre at (i, j, k) * voxel_size_m; block (a, b, c) holds the
voxels 8a..8a+7, 8b..8b+7, 8c..8c+7.
"""
from __future__ import annotations

import torch

from .errors import InputError

BLOCK = 8
BLOCK_VOXELS = BLOCK**3
_COORD_BITS = 17  # per axis: +-65,536 blocks, i.e. +-5 km at 1 cm voxels
_COORD_OFFSET = 1 << (_COORD_BITS - 1)
_COORD_MASK = (1 << _COORD_BITS) - 1


def block_keys(block_coords: torch.Tensor) -> torch.Tensor:
    """Nx3 int64 block coordinates -> N int64 keys whose order is lexicographic in (a, b, c)."""
    shifted = block_coords + _COORD_OFFSET
    if shifted.numel() and (int(shifted.min()) < 0 or int(shifted.max()) > _COORD_MASK):
        raise InputError("points lie more than 5 km from the origin; check the pose's units (metres) and frame")
    return (shifted[:, 0] << (2 * _COORD_BITS)) | (shifted[:, 1] << _COORD_BITS) | shifted[:, 2]


def keys_to_coords(keys: torch.Tensor) -> torch.Tensor:
    a = (keys >> (2 * _COORD_BITS)) & _COORD_MASK
    b = (keys >> _COORD_BITS) & _COORD_MASK
    c = keys & _COORD_MASK
    return torch.stack([a, b, c], dim=1) - _COORD_OFFSET


def voxel_keys(voxels: torch.Tensor) -> torch.Tensor:
    """Nx3 int64 voxel indices -> keys sorted first by block, then by local index (block_key*512+local)."""
    blocks = torch.div(voxels, BLOCK, rounding_mode="floor")
    local = voxels - blocks * BLOCK
    return block_keys(blocks) * BLOCK_VOXELS + (local[:, 0] * 64 + local[:, 1] * 8 + local[:, 2])


def local_grid(lo: int, size: int, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """For a cube of local voxel coordinates lo..lo+size-1 per axis around a block: the neighbour
    block offset code (0..26, for offsets -1..1 per axis) and the local index inside that neighbour."""
    r = torch.arange(lo, lo + size, device=device)
    offset = torch.div(r, BLOCK, rounding_mode="floor")  # -1, 0 or 1
    if int(offset.min()) < -1 or int(offset.max()) > 1:
        raise ValueError("neighbourhoods may reach at most one block beyond the centre block")
    local = r - offset * BLOCK
    ox, oy, oz = torch.meshgrid(offset, offset, offset, indexing="ij")
    lx, ly, lz = torch.meshgrid(local, local, local, indexing="ij")
    code = ((ox + 1) * 9 + (oy + 1) * 3 + (oz + 1)).reshape(-1)
    index = (lx * 64 + ly * 8 + lz).reshape(-1)
    return code, index


NEIGHBOUR_OFFSETS = torch.stack(
    torch.meshgrid(torch.arange(-1, 2), torch.arange(-1, 2), torch.arange(-1, 2), indexing="ij"), dim=-1
).reshape(27, 3)


class BlockGrid:
    """Blocks and their channels. Slots are never freed except by `clear`."""

    def __init__(self, channels: dict[str, tuple[int, ...]], device: torch.device | str = "cpu",
                 initial_capacity: int = 256, dtypes: dict[str, torch.dtype] | None = None,
                 growth: float = 1.5) -> None:
        self.device = torch.device(device)
        self.channel_shapes = dict(channels)
        self.channel_dtypes = {name: (dtypes or {}).get(name, torch.float32) for name in self.channel_shapes}
        self.growth = max(float(growth), 1.1)  # capacity factor when the pools grow (memory slack vs. copies)
        self._initial_capacity = initial_capacity
        self.clear()

    def clear(self) -> None:
        cap = self._initial_capacity
        self.capacity = cap
        self.n_blocks = 0
        self.coords = torch.zeros((cap, 3), dtype=torch.int64, device=self.device)
        self._sorted_keys = torch.zeros(0, dtype=torch.int64, device=self.device)
        self._sorted_slots = torch.zeros(0, dtype=torch.int64, device=self.device)
        self.pools = {name: torch.zeros((cap, BLOCK_VOXELS, *shape), dtype=self.channel_dtypes[name], device=self.device)
                      for name, shape in self.channel_shapes.items()}

    # -- lookup and allocation ------------------------------------------------------------
    def lookup_keys(self, keys: torch.Tensor) -> torch.Tensor:
        """Slots of the given block keys, -1 where the block does not exist."""
        if self._sorted_keys.numel() == 0:
            return torch.full_like(keys, -1)
        pos = torch.searchsorted(self._sorted_keys, keys).clamp_(max=self._sorted_keys.numel() - 1)
        found = self._sorted_keys[pos] == keys
        return torch.where(found, self._sorted_slots[pos], torch.full_like(keys, -1))

    def lookup(self, block_coords: torch.Tensor) -> torch.Tensor:
        return self.lookup_keys(block_keys(block_coords))

    def allocate_keys(self, unique_keys: torch.Tensor) -> torch.Tensor:
        """Slots of the given (unique) block keys, allocating the missing blocks."""
        slots = self.lookup_keys(unique_keys)
        missing = slots < 0
        n_new = int(missing.sum())
        if n_new:
            new_keys = unique_keys[missing]
            self._reserve(self.n_blocks + n_new)
            new_slots = torch.arange(self.n_blocks, self.n_blocks + n_new, device=self.device)
            self.coords[new_slots] = keys_to_coords(new_keys)
            self.n_blocks += n_new
            keys = torch.cat([self._sorted_keys, new_keys])
            order = torch.argsort(keys)
            self._sorted_keys = keys[order]
            self._sorted_slots = torch.cat([self._sorted_slots, new_slots])[order]
            slots[missing] = new_slots
        return slots

    def _reserve(self, n_blocks: int) -> None:
        if n_blocks <= self.capacity:
            return
        cap = max(n_blocks, int(self.growth * self.capacity) + 1)
        for name, pool in self.pools.items():
            grown = torch.zeros((cap, *pool.shape[1:]), dtype=pool.dtype, device=self.device)
            grown[: self.n_blocks] = pool[: self.n_blocks]
            self.pools[name] = grown
        coords = torch.zeros((cap, 3), dtype=torch.int64, device=self.device)
        coords[: self.n_blocks] = self.coords[: self.n_blocks]
        self.coords = coords
        self.capacity = cap

    # -- neighbourhoods ---------------------------------------------------------------------
    def neighbour_slots(self, slots: torch.Tensor) -> torch.Tensor:
        """Bx27 slots of each block's 26 neighbours and itself (-1 where absent)."""
        coords = self.coords[slots].unsqueeze(1) + NEIGHBOUR_OFFSETS.to(self.device).unsqueeze(0)
        return self.lookup(coords.reshape(-1, 3)).reshape(-1, 27)

    def gather(self, slots: torch.Tensor, names: list[str], lo: int, size: int) -> list[torch.Tensor]:
        """For each block, the cube of voxels lo..lo+size-1 (local coordinates, may reach into the
        neighbours) of each named channel: B x size^3 x *channel_shape, zeros where no block exists."""
        code, index = local_grid(lo, size, self.device)
        neighbours = self.neighbour_slots(slots)  # Bx27
        voxel_slot = neighbours[:, code]  # B x size^3
        present = voxel_slot >= 0
        flat = voxel_slot.clamp(min=0) * BLOCK_VOXELS + index.unsqueeze(0)
        out = []
        for name in names:
            pool = self.pools[name]
            values = pool.reshape(-1, *pool.shape[2:])[flat.reshape(-1)]
            values = values.reshape(*flat.shape, *pool.shape[2:])
            mask = present.reshape(*present.shape, *([1] * (values.dim() - 2)))
            out.append(torch.where(mask, values, torch.zeros((), dtype=values.dtype, device=values.device)))
        return out

    def dilate(self, slots: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
        """Existing slots of the blocks at `slots` + each offset (Kx3), unique and sorted."""
        if slots.numel() == 0:
            return slots
        coords = self.coords[slots].unsqueeze(1) + offsets.to(self.device).unsqueeze(0)
        found = self.lookup(coords.reshape(-1, 3))
        return torch.unique(found[found >= 0])

    def voxel_centres(self, slots: torch.Tensor, voxel_size_m: float) -> torch.Tensor:
        """B x 512 x 3 world positions of the voxel centres of the given blocks."""
        r = torch.arange(BLOCK, device=self.device)
        lx, ly, lz = torch.meshgrid(r, r, r, indexing="ij")
        local = torch.stack([lx, ly, lz], dim=-1).reshape(1, BLOCK_VOXELS, 3)
        return ((self.coords[slots] * BLOCK).unsqueeze(1) + local).to(torch.float32) * voxel_size_m

    # -- state ---------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        n = self.n_blocks
        return {"coords": self.coords[:n].cpu(), **{f"pool.{k}": v[:n].cpu() for k, v in self.pools.items()}}

    def load_state_dict(self, state: dict) -> None:
        self.clear()
        coords = state["coords"].to(self.device)
        slots = self.allocate_keys(block_keys(coords))
        for name in self.pools:
            self.pools[name][slots] = state[f"pool.{name}"].to(self.device, self.pools[name].dtype)

    def nbytes(self) -> int:
        """Bytes held by the pools and index (allocated capacity)."""
        total = self.coords.numel() * 8 + self._sorted_keys.numel() * 16
        return total + sum(p.numel() * p.element_size() for p in self.pools.values())
