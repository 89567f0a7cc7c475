"""Sparse voxel grid: 8^3-voxel blocks allocated on demand, found through an open-addressing hash.

Memory follows the observed surface: only blocks that some ray sample touched exist. Every
per-voxel quantity is a "channel": a pool tensor of shape (capacity, 512, *channel_shape), where
row `slot` holds one block's voxels in x-major order (local index = 64*x + 8*y + z). Pools live
on the CPU: the compiled kernels (integrator, alpha windows, mesher) read and write them through
zero-copy numpy views; float16 channels are handed to the kernels as their int16 bit patterns
(`f16_to_f32` / `f32_to_f16` convert one value, in hardware where the CPU can; `load_f32` /
`store_f32` read and write a channel of either storage). A feature channel may be int8, features
packed per voxel (`FEATURE_SCALE`, `encode_depth`; `load_feature` / `store_feature` in kernels, `decode_features`
/ `encode_features` in torch). Alpha may be 8-bit codes (`encode_alpha` / `load_alpha` /
`decode_alpha`).

`BlockGrid` keeps the blocks by slot: their keys and coordinates, the `HashTable` that finds a
key's slot, the allocation and removal of blocks and the hand-back of spilled ones; `ChannelPools`
stores their channels (grown, moved and released row by row). Geometry of a block's voxels:
`voxel_centres`.

Convention: voxel (i, j, k) has its centre at (i, j, k) * voxel_size_m; block (a, b, c) holds the
voxels 8a..8a+7, 8b..8b+7, 8c..8c+7.
"""
from __future__ import annotations

import math
import mmap
import platform
import sys
from collections.abc import Iterable
from typing import NamedTuple

import numba
import numpy as np
import torch
from llvmlite import binding as llvm
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic, overload

from .errors import InputError
from .spill import BlockSpill

BLOCK = 8
BLOCK_VOXELS = BLOCK**3
_COORD_BITS = 17  # per axis: +-65,536 blocks, i.e. +-5 km at 1 cm voxels
_COORD_OFFSET = 1 << (_COORD_BITS - 1)
_COORD_MASK = (1 << _COORD_BITS) - 1
EMPTY_KEY = -1  # free hash-table entry (real keys are >= 0)
_MAX_LOAD = 0.5  # hash-table load factor before it doubles
_INITIAL_TABLE = 1 << 12

# -- keys -------------------------------------------------------------------------------------------


def block_keys(block_coords: torch.Tensor) -> torch.Tensor:
    """Nx3 int64 block coordinates -> N int64 keys (>= 0) whose order is lexicographic in (a, b, c)."""
    shifted = block_coords + _COORD_OFFSET
    if shifted.numel() and (int(shifted.min()) < 0 or int(shifted.max()) > _COORD_MASK):
        raise InputError("points lie more than 5 km from the origin; check the pose's units (metres) and frame")
    return (shifted[:, 0] << (2 * _COORD_BITS)) | (shifted[:, 1] << _COORD_BITS) | shifted[:, 2]


def within_key_range(block_coords: np.ndarray) -> np.ndarray:
    """N bools: whether each of these Nx3 block coordinates (integers, or whole floats of any size) has a
    key (`block_keys`: within about 5 km of the origin at 1 cm voxels)."""
    shifted = np.asarray(block_coords) + _COORD_OFFSET
    return np.asarray(((shifted >= 0) & (shifted <= _COORD_MASK)).all(axis=1))


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


@numba.njit(inline="always")
def coords_key(a: int, b: int, c: int) -> int:
    """The key of block (a, b, c), or -1 when it lies outside the key range (numba)."""
    a += _COORD_OFFSET
    b += _COORD_OFFSET
    c += _COORD_OFFSET
    if a < 0 or b < 0 or c < 0 or a > _COORD_MASK or b > _COORD_MASK or c > _COORD_MASK:
        return -1
    return (a << (2 * _COORD_BITS)) | (b << _COORD_BITS) | c


# -- the hash table (numba) ---------------------------------------------------------------------------


@numba.njit(inline="always")
def _bucket(key: int, mask: int) -> int:
    # Fibonacci hashing: the product's high half depends on every bit of the key (all three axis
    # fields), so neighbouring blocks spread over the table whatever its size
    return int(np.int64((np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(32))) & mask


@numba.njit(inline="always")
def _probe(table_keys: np.ndarray, key: int) -> int:
    """The entry holding `key`, or the free entry where it would go (linear probing)."""
    mask = table_keys.shape[0] - 1
    i = _bucket(key, mask)
    while table_keys[i] != key and table_keys[i] != EMPTY_KEY:
        i = (i + 1) & mask
    return i


@numba.njit(inline="always")
def hash_find(table_keys: np.ndarray, table_slots: np.ndarray, key: int) -> int:
    """Slot of `key`, -1 when absent."""
    i = _probe(table_keys, key)
    return table_slots[i] if table_keys[i] == key else -1


@numba.njit(inline="always")
def hash_find_or_add(table_keys: np.ndarray, table_slots: np.ndarray, key: int, state: np.ndarray,
                     slot_keys: np.ndarray) -> int:
    """Slot of `key`, adding the block with the next free slot when absent. state = [n_blocks,
    n_entries_max]; returns -1 (nothing changed) when the table or the slot arrays are full."""
    i = _probe(table_keys, key)
    if table_keys[i] == key:
        return table_slots[i]
    slot = state[0]
    if slot >= state[1] or slot >= slot_keys.shape[0]:
        return -1
    table_keys[i] = key
    table_slots[i] = slot
    slot_keys[slot] = key
    state[0] = slot + 1
    return slot


@numba.njit(inline="always")
def hash_remove(table_keys: np.ndarray, table_slots: np.ndarray, key: int) -> None:
    """Remove `key` (if present) by backward-shift deletion: later entries of its probe run that
    may sit in the freed entry move back, so linear probing still finds every key without tombstones."""
    mask = table_keys.shape[0] - 1
    i = _probe(table_keys, key)
    if table_keys[i] != key:
        return
    j = i
    while True:
        j = (j + 1) & mask
        if table_keys[j] == EMPTY_KEY:
            break
        home = _bucket(table_keys[j], mask)
        # the entry at j stays where it is when its home lies cyclically in (i, j]
        stays = (i < home <= j) if i <= j else (home > i or home <= j)
        if not stays:
            table_keys[i] = table_keys[j]
            table_slots[i] = table_slots[j]
            i = j
    table_keys[i] = EMPTY_KEY
    table_slots[i] = -1


@numba.njit(cache=True, nogil=True)
def drop_new_blocks(table_keys: np.ndarray, table_slots: np.ndarray, slot_keys: np.ndarray, n_before: int,
                    keep: np.ndarray) -> np.ndarray:
    """Undo part of an allocation that `hash_find_or_add` made but nobody committed yet: of the
    blocks in slots n_before..n_before+len(keep)-1, those with keep False leave the hash table and
    the kept ones move down to stay contiguous (order kept). Returns each of those slots' new slot,
    -1 where dropped; the caller commits n_before + keep.sum() blocks."""
    new_slot = np.full(keep.shape[0], -1, np.int64)
    next_slot = n_before
    for n in range(keep.shape[0]):
        if keep[n]:
            new_slot[n] = next_slot
            next_slot += 1
        else:
            hash_remove(table_keys, table_slots, slot_keys[n_before + n])
    for n in range(keep.shape[0]):  # ascending: a slot is overwritten only after its own key moved or left
        target = new_slot[n]
        if target >= 0 and target != n_before + n:
            key = slot_keys[n_before + n]
            slot_keys[target] = key
            table_slots[_probe(table_keys, key)] = target
    slot_keys[next_slot:n_before + keep.shape[0]] = EMPTY_KEY
    return new_slot


@numba.njit(cache=True, nogil=True)
def _find_many(table_keys: np.ndarray, table_slots: np.ndarray, keys: np.ndarray, out: np.ndarray) -> None:
    for n in range(keys.shape[0]):
        out[n] = hash_find(table_keys, table_slots, keys[n]) if keys[n] >= 0 else -1


@numba.njit(cache=True, nogil=True)
def _add_many(table_keys: np.ndarray, table_slots: np.ndarray, keys: np.ndarray, state: np.ndarray,
              slot_keys: np.ndarray, out: np.ndarray) -> int:
    for n in range(keys.shape[0]):
        slot = hash_find_or_add(table_keys, table_slots, keys[n], state, slot_keys)
        if slot < 0:
            return n
        out[n] = slot
    return keys.shape[0]


@numba.njit(cache=True, nogil=True)
def _rehash(slot_keys: np.ndarray, n_blocks: int, table_keys: np.ndarray, table_slots: np.ndarray) -> None:
    for slot in range(n_blocks):
        i = _probe(table_keys, slot_keys[slot])
        table_keys[i] = slot_keys[slot]
        table_slots[i] = slot


@numba.njit(cache=True, nogil=True)
def _move_rows(rows: np.ndarray, src: np.ndarray, dst: np.ndarray) -> None:
    """rows[dst[i]] = rows[src[i]], in place: an eviction moves ~10^4 rows of 1-5 KB per pool, and
    torch's gather-then-scatter first allocates and faults in a temporary as large as all of them."""
    for i in range(src.shape[0]):
        rows[dst[i]] = rows[src[i]]


ALL_NEIGHBOURS = np.arange(27)


def neighbour_table(table_keys: np.ndarray, table_slots: np.ndarray, slot_keys: np.ndarray, slots: np.ndarray,
                    codes: np.ndarray = ALL_NEIGHBOURS) -> np.ndarray:
    """B x 27 slots of each block's neighbours at offsets (dx, dy, dz) in -1..1, index
    9*(dx+1) + 3*(dy+1) + (dz+1) (13 is the block itself); -1 where absent. Only the neighbours
    `codes` are looked up (a caller that reads fewer saves their hash probes); the others are -1."""
    out = np.full((slots.shape[0], 27), -1, np.int64)
    _fill_neighbour_table(table_keys, table_slots, slot_keys, slots, np.asarray(codes, np.int64), out)
    return out


@numba.njit(cache=True, nogil=True)
def _fill_neighbour_table(table_keys: np.ndarray, table_slots: np.ndarray, slot_keys: np.ndarray,
                          slots: np.ndarray, codes: np.ndarray, out: np.ndarray) -> None:
    for n in range(slots.shape[0]):
        key = slot_keys[slots[n]]
        for code in codes:
            out[n, code] = _neighbour_slot(table_keys, table_slots, key, code)


@numba.njit(inline="always")
def _neighbour_slot(table_keys: np.ndarray, table_slots: np.ndarray, key: int, code: int) -> int:
    """Slot of the neighbour at `code` (as in `neighbour_table`) of the block with `key`, -1 when absent."""
    k = coords_key(((key >> (2 * _COORD_BITS)) & _COORD_MASK) - _COORD_OFFSET + code // 9 - 1,
                   ((key >> _COORD_BITS) & _COORD_MASK) - _COORD_OFFSET + (code // 3) % 3 - 1,
                   (key & _COORD_MASK) - _COORD_OFFSET + code % 3 - 1)
    return hash_find(table_keys, table_slots, k) if k >= 0 else -1


def masked_neighbours(table_keys: np.ndarray, table_slots: np.ndarray, slot_keys: np.ndarray, slots: np.ndarray,
                      masks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The neighbours each block's 27-bit mask names (bit `code`, as in `neighbour_table`) that
    exist, as (index into `slots`, code, the neighbour's slot): block by block, codes ascending.
    Without a B x 27 table: a caller that reaches a few neighbours of many blocks looks up those only."""
    masks = masks.astype(np.int64)
    n_bits = int(np.bitwise_count(masks & ((1 << 27) - 1)).sum())
    sources, codes, targets = (np.empty(n_bits, np.int64) for _ in range(3))
    found = _fill_masked_neighbours(table_keys, table_slots, slot_keys, slots, masks, sources, codes, targets)
    return sources[:found], codes[:found], targets[:found]


@numba.njit(cache=True, nogil=True)
def _fill_masked_neighbours(table_keys: np.ndarray, table_slots: np.ndarray, slot_keys: np.ndarray,
                            slots: np.ndarray, masks: np.ndarray, sources: np.ndarray, codes: np.ndarray,
                            targets: np.ndarray) -> int:
    found = 0
    for n in range(slots.shape[0]):
        mask = masks[n]
        if mask == 0:
            continue
        key = slot_keys[slots[n]]
        for code in range(27):
            if (mask >> code) & 1 == 0:
                continue
            slot = _neighbour_slot(table_keys, table_slots, key, code)
            if slot >= 0:
                sources[found] = n
                codes[found] = code
                targets[found] = slot
                found += 1
    return found


# -- half precision in kernels (numba has no float16 type) ------------------------------------------


@intrinsic
def _f32_to_f16_hw(typingctx, x):  # noqa: ANN001 (numba intrinsic)
    """float32 -> float16 bits in one instruction (x86 F16C, AArch64), through LLVM's half type."""
    def codegen(context, builder, signature, args):  # noqa: ANN001
        return builder.bitcast(builder.fptrunc(args[0], ir.HalfType()), ir.IntType(16))
    return types.int16(types.float32), codegen


@intrinsic
def _f16_to_f32_hw(typingctx, bits):  # noqa: ANN001
    def codegen(context, builder, signature, args):  # noqa: ANN001
        return builder.fpext(builder.bitcast(args[0], ir.HalfType()), ir.FloatType())
    return types.float32(types.int16), codegen


@intrinsic
def prefetch(typingctx, array, index):  # noqa: ANN001 (numba intrinsic)
    """Start loading the cache line of array[index] (a 1-D array) without waiting for it: kernels
    that update scattered voxels issue these early, so that the memory accesses overlap instead of
    stalling one after another. A hint only; a no-op where the CPU has no prefetch."""
    if not (isinstance(array, types.Array) and array.ndim == 1 and isinstance(index, types.Integer)):
        return None

    def codegen(context, builder, signature, args):  # noqa: ANN001
        array_type = signature.args[0]
        view = context.make_array(array_type)(context, builder, args[0])
        pointer = cgutils.get_item_pointer(context, builder, array_type, view, [args[1]], wraparound=False)
        byte_pointer = builder.bitcast(pointer, ir.IntType(8).as_pointer())
        i32 = ir.IntType(32)
        function = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [byte_pointer.type, i32, i32, i32]), "llvm.prefetch.p0")
        builder.call(function, [byte_pointer, i32(0), i32(3), i32(1)])  # read, keep in all caches, data
        return context.get_dummy_value()
    return types.none(array, index), codegen


def _int8_pointer_as_u32(context, builder, signature, args):  # noqa: ANN001, ANN202
    array_type = signature.args[0]
    view = context.make_array(array_type)(context, builder, args[0])
    pointer = cgutils.get_item_pointer(context, builder, array_type, view, [args[1]], wraparound=False)
    return builder.bitcast(pointer, ir.IntType(32).as_pointer())


@intrinsic
def _load_row32(typingctx, array, index):  # noqa: ANN001 (numba intrinsic)
    """The 4 bytes array[index:index + 4] of an int8 array as one little-endian unsigned word
    (int64): a packed feature row of 4 bytes in one load instead of four."""
    if not (isinstance(array, types.Array) and array.dtype == types.int8 and isinstance(index, types.Integer)):
        return None

    def codegen(context, builder, signature, args):  # noqa: ANN001
        word = builder.load(_int8_pointer_as_u32(context, builder, signature, args), align=1)
        return builder.zext(word, ir.IntType(64))
    return types.int64(array, index), codegen


@intrinsic
def _store_row32(typingctx, array, index, word):  # noqa: ANN001 (numba intrinsic)
    """array[index:index + 4] = the low 4 bytes of word, little-endian (`_load_row32`'s inverse)."""
    if not (isinstance(array, types.Array) and array.dtype == types.int8 and isinstance(index, types.Integer)
            and isinstance(word, types.Integer)):
        return None

    def codegen(context, builder, signature, args):  # noqa: ANN001
        value = builder.trunc(context.cast(builder, args[2], signature.args[2], types.int64), ir.IntType(32))
        builder.store(value, _int8_pointer_as_u32(context, builder, signature, args), align=1)
        return context.get_dummy_value()
    return types.none(array, index, word), codegen


@intrinsic
def _f32_bits(typingctx, x):  # noqa: ANN001 (numba intrinsic)
    def codegen(context, builder, signature, args):  # noqa: ANN001
        return builder.bitcast(args[0], ir.IntType(32))
    return types.uint32(types.float32), codegen


@numba.njit(inline="always")
def f32_to_bf16(x: float) -> np.uint16:
    """float32 -> bfloat16 bits, rounded to nearest even as torch's conversion (finite values)."""
    bits = _f32_bits(np.float32(x))
    return np.uint16((bits + np.uint32(0x7FFF) + ((bits >> np.uint32(16)) & np.uint32(1))) >> np.uint32(16))


# the float32 value of every float16 bit pattern
F16_VALUES = np.arange(1 << 16, dtype=np.uint16).view(np.float16).astype(np.float32)


@numba.njit(inline="always")
def _f16_to_f32_soft(bits: int) -> float:
    return F16_VALUES[bits & 0xFFFF]


@numba.njit(inline="always")
def _f32_to_f16_soft(x: float) -> int | np.int64:
    """Rounds to nearest even like numpy's astype (x is exact in float64, so no double rounding)."""
    if x != x:
        return 0x7E00
    negative = x < 0.0 or (x == 0.0 and math.copysign(1.0, x) < 0.0)
    a = abs(np.float64(x))
    if a == np.inf:
        h: int | np.int64 = 0x7C00
    elif a == 0.0:
        h = 0
    else:
        m, e = math.frexp(a)  # a = m * 2^e, m in [0.5, 1)
        exponent = e + 14
        if exponent >= 1:
            mantissa: int | np.int64 = np.int64(np.rint((2.0 * m - 1.0) * 1024.0))
            if mantissa == 1024:
                exponent, mantissa = exponent + 1, 0
            h = 0x7C00 if exponent >= 31 else (exponent << 10) | mantissa
        else:  # subnormal; 1024 rounds up into the smallest normal, which is the right encoding
            h = np.int64(np.rint(a * 16777216.0))
    if negative:
        h |= 0x8000
    return h - 0x10000 if h >= 0x8000 else h


def _hardware_half() -> bool:
    machine = platform.machine().lower()
    if machine in ("aarch64", "arm64"):
        return True
    if machine in ("x86_64", "amd64"):
        return bool(llvm.get_host_cpu_features().get("f16c", False))
    return False


# float16 bit pattern (int16) <-> float32 value, chosen once for this CPU
if _hardware_half():
    f32_to_f16, f16_to_f32 = _f32_to_f16_hw, _f16_to_f32_hw
else:  # pragma: no cover - CPUs without half conversions
    f32_to_f16, f16_to_f32 = _f32_to_f16_soft, _f16_to_f32_soft


def load_f32(array: np.ndarray, index: int) -> np.float32:
    """array[index] as float32, whether the array holds float32 values or float16 bit patterns
    (int16, `kernel_view`): kernels read channels through this and `store_f32` so that they work on
    either storage (compiled per dtype; this Python body is only the reference)."""
    value = array[index]
    if array.dtype == np.int16:
        return np.float32(np.array(value, np.int16).view(np.float16))
    return np.float32(value)


def store_f32(array: np.ndarray, index: int, value: float | np.float32) -> None:
    """array[index] = value, rounded (to nearest even) to float16 where the array holds float16 bits
    (int16), to bfloat16 where it holds bfloat16 bits (uint16: `f32_to_bf16`)."""
    if array.dtype == np.int16:
        array[index] = np.array(value, np.float16).view(np.int16)
    elif array.dtype == np.uint16:
        array[index] = torch.tensor([value], dtype=torch.float32).to(torch.bfloat16).view(torch.int16).numpy()[0]
    else:
        array[index] = value


@overload(load_f32, inline="always")
def _load_f32(array, index):  # noqa: ANN001, ANN202 (numba overload)
    if isinstance(array, types.Array) and array.dtype == types.int16:
        return lambda array, index: f16_to_f32(array[index])
    return lambda array, index: np.float32(array[index])


@overload(store_f32, inline="always")
def _store_f32(array, index, value):  # noqa: ANN001, ANN202 (numba overload)
    if isinstance(array, types.Array) and array.dtype == types.int16:
        def store_half(array, index, value):  # noqa: ANN001, ANN202
            array[index] = f32_to_f16(np.float32(value))
        return store_half
    if isinstance(array, types.Array) and array.dtype == types.uint16:
        def store_bfloat16(array, index, value):  # noqa: ANN001, ANN202
            array[index] = f32_to_bf16(np.float32(value))
        return store_bfloat16

    def store(array, index, value):  # noqa: ANN001, ANN202
        array[index] = value
    return store


# -- feature channels: 6-bit learned features, 8-bit depth ---------------------------------------
# A feature channel of dtype int8 packs a voxel's n features (n - 1 a multiple of 4) in 3 (n - 1) / 4 + 1
# bytes: the learned ones (L2-normalised per pixel, so in [-1, 1], and so are their running
# averages) as round(FEATURE_SCALE * f) in 6-bit two's complement, 4 to each 3 bytes (feature
# k of a group in bits 6k..6k+5 of their little-endian 24-bit word), then the depth (metres) as
# an unsigned 8-bit float (`encode_depth`).
FEATURE_SCALE = 31.0
_SIX_BITS = 63

# The depth feature's code: 3 exponent bits, 5 mantissa bits. Codes 32..255 are 2^(e - 3) * (1 + m/32)
# for code = 32 e + m, [0.25, 31.5] m in steps of 1/32 of an octave (a relative error of at most
# 1/64 after rounding, below the sensors' depth noise at range); codes 0..32 are steps of 1/128 m
# from 0 (so a zeroed pool holds depth 0). Larger depths saturate at 31.5 m.
DEPTH_MAX_M = 31.5
_DEPTH_CODES = np.arange(256)
DEPTH_OF_CODE = np.where(_DEPTH_CODES < 32, _DEPTH_CODES / 128.0,
                         2.0 ** ((_DEPTH_CODES >> 5) - 3.0) * (1.0 + (_DEPTH_CODES & 31) / 32.0)).astype(np.float32)
_DEPTH_OF_CODE_T = torch.from_numpy(DEPTH_OF_CODE)


@numba.njit(cache=True, inline="always")
def encode_depth(depth_m: float) -> np.int8:
    """The 8-bit code of a depth (metres), rounded to the nearest representable depth (ties to even),
    stored in an int8 (read it back with `DEPTH_OF_CODE[code & 0xFF]`)."""
    return np.int8(((_depth_code(depth_m) & 0xFF) ^ 0x80) - 0x80)


@numba.njit(inline="always")
def _depth_code(depth_m: float) -> np.int64:
    """`encode_depth` as an integer 0..255, from the float's bits (no libm frexp call per voxel in
    the integration kernel): d = 2^e (1 + m / 2^23) is code 32 (e + 3) + m / 2^18 rounded, which
    carries into the next octave."""
    d = min(max(np.float32(depth_m), np.float32(0.0)), np.float32(DEPTH_MAX_M))
    if d < np.float32(0.25):
        return np.int64(np.rint(d * np.float32(128.0)))
    bits = np.int64(_f32_bits(d))
    mantissa = bits & 0x7FFFFF
    step, rest = mantissa >> 18, mantissa & 0x3FFFF
    if rest > 0x20000 or (rest == 0x20000 and step & 1):
        step += 1
    return 32 * ((bits >> 23) - 124) + step


def feature_storage_shape(n_features: int, dtype: torch.dtype) -> tuple[int]:
    """A voxel's row in a feature pool: n float values, or 3 (n - 1) / 4 + 1 packed bytes (int8)."""
    if dtype != torch.int8:
        return (n_features,)
    if (n_features - 1) % 4:
        raise ValueError(f"packed feature pools hold 4, 8, ... learned features, not {n_features - 1}")
    return (3 * (n_features - 1) // 4 + 1,)


def decode_features(rows: torch.Tensor) -> torch.Tensor:
    """Float32 features (..., n) of feature-pool rows (..., 3 (n - 1) / 4 + 1 packed int8, or n float values)."""
    if rows.dtype != torch.int8:
        return rows.float()
    groups = rows[..., :-1].view(torch.uint8).to(torch.int32).unflatten(-1, (-1, 3))
    words = groups[..., 0] | (groups[..., 1] << 8) | (groups[..., 2] << 16)
    six = (words.unsqueeze(-1) >> torch.arange(0, 24, 6, dtype=torch.int32)) & _SIX_BITS
    learned = (six - ((six >> 5) << 6)).flatten(-2).float() / FEATURE_SCALE  # two's complement
    depth = _DEPTH_OF_CODE_T[rows[..., -1:].view(torch.uint8).long()]
    return torch.cat([learned, depth], dim=-1)


def encode_features(values: torch.Tensor) -> torch.Tensor:
    """Packed int8 rows of features (..., n): `decode_features`' inverse up to rounding (to
    nearest, ties to even, as the kernels' `store_feature`)."""
    values = values.float()
    learned = torch.round(values[..., :-1] * FEATURE_SCALE).clamp(-FEATURE_SCALE, FEATURE_SCALE).to(torch.int32)
    six = (learned & _SIX_BITS).unflatten(-1, (-1, 4)) << torch.arange(0, 24, 6, dtype=torch.int32)
    words = six.sum(dim=-1)
    groups = torch.stack([words & 0xFF, (words >> 8) & 0xFF, words >> 16], dim=-1).flatten(-2)
    depth = values[..., -1:].clamp(0.0, DEPTH_MAX_M)
    mantissa, exponent = torch.frexp(depth)
    code = torch.where(depth < 0.25, torch.round(depth * 128.0), 32.0 * (exponent + 1) + torch.round(64.0 * mantissa))
    return torch.cat([groups.to(torch.uint8), code.to(torch.uint8)], dim=-1).view(torch.int8)


def decode_saved_features(rows: torch.Tensor, n_features: int) -> torch.Tensor:
    """Float32 features (..., n) of a feature pool as any version saved it: float values; packed
    with the learned features as int8 (steps of 1/127) and the depth as float16 bits (n + 1 bytes)
    or as its 8-bit code (n bytes); or packed as now."""
    if rows.dtype != torch.int8:
        return rows.float()
    if rows.shape[-1] in (n_features, n_features + 1):
        learned = rows[..., :n_features - 1].float() / 127.0
        if rows.shape[-1] == n_features:
            depth = _DEPTH_OF_CODE_T[rows[..., -1:].view(torch.uint8).long()]
        else:
            depth = rows[..., -2:].contiguous().view(torch.int16).view(torch.float16).float()
        return torch.cat([learned, depth], dim=-1)
    return decode_features(rows)


# the features in one packed 4-byte row (`packed_words`): four 6-bit codes, then the depth code
WORD_FEATURES = 5


def features_per_voxel(features: np.ndarray, n_voxels: int) -> int:
    """n, the features per voxel of a flat feature-pool view of n_voxels voxels (numba too)."""
    if features.dtype == np.uint32:  # `packed_words`
        return WORD_FEATURES
    stride = features.shape[0] // max(n_voxels, 1)
    return 4 * (stride - 1) // 3 + 1 if features.dtype == np.int8 else stride


@overload(features_per_voxel, inline="always")
def _features_per_voxel(features, n_voxels):  # noqa: ANN001, ANN202 (numba overload)
    if isinstance(features, types.Array) and features.dtype == types.uint32:
        return lambda features, n_voxels: WORD_FEATURES
    if isinstance(features, types.Array) and features.dtype == types.int8:
        return lambda features, n_voxels: 4 * (features.shape[0] // max(n_voxels, 1) - 1) // 3 + 1
    return lambda features, n_voxels: features.shape[0] // max(n_voxels, 1)


@numba.njit(inline="always")
def _packed_word(features: np.ndarray, at: int) -> np.int64:
    """The 24-bit little-endian word of 4 packed 6-bit features at byte `at`."""
    return ((np.int64(features[at]) & 0xFF) | ((np.int64(features[at + 1]) & 0xFF) << 8)
            | ((np.int64(features[at + 2]) & 0xFF) << 16))


@numba.njit(inline="always")
def _store_word(features: np.ndarray, at: int, word: np.int64) -> None:
    for i in range(3):
        features[at + i] = np.int8((((word >> (8 * i)) & 0xFF) ^ 0x80) - 0x80)


@numba.njit(inline="always")
def _six_bit(word: np.int64, k: int) -> np.int64:
    """Feature k (0..3) of a packed word, as the signed integer stored."""
    return (((word >> (6 * k)) & _SIX_BITS) ^ 32) - 32  # sign-extended


# a 6-bit code's feature value (code / FEATURE_SCALE, sign-extended), looked up: kernels that read
# every feature of many voxels (the weighting net's windows) would otherwise divide for each
_FEATURE_OF_CODE = (((np.arange(64) ^ 32) - 32).astype(np.float32) / np.float32(FEATURE_SCALE)).astype(np.float32)


def load_feature(features: np.ndarray, n_features: int, voxel: int, c: int) -> np.float32:
    """Feature c of a voxel from a flat feature-pool view: float32, float16 bits (int16) or packed
    int8 (see FEATURE_SCALE). Kernels compile this per dtype; this body is the reference."""
    if features.dtype != np.int8:
        return load_f32(features, voxel * n_features + c)
    stride = 3 * (n_features - 1) // 4 + 1
    if c < n_features - 1:
        word = _packed_word(features, voxel * stride + 3 * (c // 4))
        return np.float32(_six_bit(word, c % 4) / np.float32(FEATURE_SCALE))
    return DEPTH_OF_CODE[int(features[voxel * stride + stride - 1]) & 0xFF]


def store_feature(features: np.ndarray, n_features: int, voxel: int, c: int, value: float) -> None:
    """Feature c of a voxel = value, rounded to the storage (`load_feature` reads it back)."""
    if features.dtype != np.int8:
        store_f32(features, voxel * n_features + c, value)
        return
    stride = 3 * (n_features - 1) // 4 + 1
    if c < n_features - 1:
        at = voxel * stride + 3 * (c // 4)
        q = int(np.clip(np.rint(np.float32(value) * np.float32(FEATURE_SCALE)), -FEATURE_SCALE, FEATURE_SCALE))
        shift = 6 * (c % 4)
        word = (int(_packed_word(features, at)) & ~(_SIX_BITS << shift)) | ((q & _SIX_BITS) << shift)
        _store_word(features, at, np.int64(word))
    else:
        features[voxel * stride + stride - 1] = encode_depth(value)


@overload(load_feature, inline="always")
def _load_feature(features, n_features, voxel, c):  # noqa: ANN001, ANN202 (numba overload)
    if not (isinstance(features, types.Array) and features.dtype == types.int8):
        return lambda features, n_features, voxel, c: load_f32(features, voxel * n_features + c)

    def load_packed(features, n_features, voxel, c):  # noqa: ANN001, ANN202
        stride = 3 * (n_features - 1) // 4 + 1
        if c < n_features - 1:
            word = _packed_word(features, voxel * stride + 3 * (c // 4))
            return _FEATURE_OF_CODE[(word >> (6 * (c % 4))) & _SIX_BITS]
        return DEPTH_OF_CODE[np.int64(features[voxel * stride + stride - 1]) & 0xFF]
    return load_packed


@overload(store_feature, inline="always")
def _store_feature(features, n_features, voxel, c, value):  # noqa: ANN001, ANN202 (numba overload)
    if not (isinstance(features, types.Array) and features.dtype == types.int8):
        return lambda features, n_features, voxel, c, value: store_f32(features, voxel * n_features + c, value)

    def store_packed(features, n_features, voxel, c, value):  # noqa: ANN001, ANN202
        stride = 3 * (n_features - 1) // 4 + 1
        if c < n_features - 1:
            at = voxel * stride + 3 * (c // 4)
            q = np.rint(np.float32(value) * np.float32(FEATURE_SCALE))
            q = np.int64(min(max(q, np.float32(-FEATURE_SCALE)), np.float32(FEATURE_SCALE)))
            shift = 6 * (c % 4)
            word = (_packed_word(features, at) & ~(np.int64(_SIX_BITS) << shift)) | ((q & _SIX_BITS) << shift)
            _store_word(features, at, word)
        else:
            features[voxel * stride + stride - 1] = encode_depth(value)
    return store_packed


def load_features(features: np.ndarray, n_features: int, voxel: int, values: np.ndarray) -> None:
    """values[:n] = every feature of a voxel (`load_feature` for each; a packed row is read once).
    Kernels compile this per dtype; this body is the reference."""
    for c in range(n_features):
        values[c] = load_feature(features, n_features, voxel, c)


@overload(load_features, inline="always")
def _load_features(features, n_features, voxel, values):  # noqa: ANN001, ANN202 (numba overload)
    if not (isinstance(features, types.Array) and features.dtype == types.int8):
        def load_each(features, n_features, voxel, values):  # noqa: ANN001, ANN202
            for c in range(n_features):
                values[c] = load_f32(features, voxel * n_features + c)
        return load_each

    def load_packed_row(features, n_features, voxel, values):  # noqa: ANN001, ANN202
        stride = 3 * (n_features - 1) // 4 + 1
        base = voxel * stride
        for group in range(stride // 3):
            word = _packed_word(features, base + 3 * group)
            for k in range(4):
                values[4 * group + k] = _FEATURE_OF_CODE[(word >> (6 * k)) & _SIX_BITS]
        values[n_features - 1] = DEPTH_OF_CODE[np.int64(features[base + stride - 1]) & 0xFF]
    return load_packed_row


def copy_features(features: np.ndarray, n_features: int, voxel: int, out: np.ndarray, at: int,
                  feature_of_code: np.ndarray, depth_of_code: np.ndarray) -> None:
    """out[at:at + n] = every feature of a voxel, as out stores values (`store_f32`). Packed rows
    (int8 bytes, or `packed_words`) are decoded by lookup in feature_of_code (64 6-bit codes) and
    depth_of_code (256), tables of their values as out stores them (`feature_code_tables`): no
    conversion per value. Kernels compile this per dtype; this body is the reference (int8 rows)."""
    values = np.empty(n_features, np.float32)
    load_features(features, n_features, voxel, values)
    for c in range(n_features):
        store_f32(out, at + c, values[c])


def packed_words(features: np.ndarray, n_voxels: int) -> np.ndarray:
    """A flat feature-pool view of n_voxels voxels whose packed rows are 4 bytes (WORD_FEATURES) as
    one little-endian uint32 word per voxel, which `copy_features` reads with one load; any other
    view as it is."""
    if (features.dtype == np.int8 and features.shape[0] == 4 * n_voxels and sys.byteorder == "little"
            and features.flags.c_contiguous and features.ctypes.data % 4 == 0):
        return features.view(np.uint32)
    return features


def feature_code_tables(dtype: np.dtype | type, *, depth_range_m: tuple[float, float] = (-1.0, 1.0)
                        ) -> tuple[np.ndarray, np.ndarray]:
    """`copy_features`' tables for an out of this dtype: float32 values, bfloat16 bits (uint16), or
    8-bit codes (uint8, `as_stored`: the learned features' range -1..1, the depths' depth_range_m)."""
    return as_stored(_FEATURE_OF_CODE, dtype), as_stored(DEPTH_OF_CODE, dtype, value_range=depth_range_m)


# an 8-bit code (`as_stored` to uint8) of a value v in the range (low, high):
# (v - centre) / half = (code - INT8_ZERO) * INT8_STEP, centre and half the range's middle and half its width
INT8_STEP = 1.0 / 127.0
INT8_ZERO = 128


def as_stored(values: np.ndarray, dtype: np.dtype | type, *, value_range: tuple[float, float] = (-1.0, 1.0)
              ) -> np.ndarray:
    """float32 values as an array of this dtype stores them (`store_f32`): float32, bfloat16 bits
    (uint16, rounded to nearest even), or uint8 codes of their place in value_range (INT8_STEP,
    INT8_ZERO; rounded, saturated outside it; NaN and inf as the range's middle)."""
    if np.dtype(dtype) == np.uint8:
        centre, half = 0.5 * (value_range[0] + value_range[1]), 0.5 * (value_range[1] - value_range[0])
        shares = np.nan_to_num((np.asarray(values, np.float64) - centre) / half, nan=0.0, posinf=0.0, neginf=0.0)
        return np.clip(np.rint(shares / INT8_STEP) + INT8_ZERO, 0, 255).astype(np.uint8)
    if np.dtype(dtype) == np.uint16:
        bits = torch.from_numpy(np.asarray(values, np.float32)).to(torch.bfloat16).view(torch.int16)
        return bits.numpy().view(np.uint16)
    return np.asarray(values, np.float32)


@overload(copy_features, inline="always")
def _copy_features(features, n_features, voxel, out, at, feature_of_code, depth_of_code):  # noqa: ANN001, ANN202
    if isinstance(features, types.Array) and features.dtype == types.uint32:  # `packed_words`
        def copy_word(features, n_features, voxel, out, at, feature_of_code, depth_of_code):  # noqa: ANN001, ANN202
            word = np.int64(features[voxel])
            for k in range(4):
                out[at + k] = feature_of_code[(word >> (6 * k)) & _SIX_BITS]
            out[at + WORD_FEATURES - 1] = depth_of_code[word >> 24]
        return copy_word
    if not (isinstance(features, types.Array) and features.dtype == types.int8):
        def copy_each(features, n_features, voxel, out, at, feature_of_code, depth_of_code):  # noqa: ANN001, ANN202
            for c in range(n_features):
                store_f32(out, at + c, load_f32(features, voxel * n_features + c))
        return copy_each

    def copy_packed_row(features, n_features, voxel, out, at, feature_of_code, depth_of_code):  # noqa: ANN001, ANN202
        stride = 3 * (n_features - 1) // 4 + 1
        base = voxel * stride
        for group in range(stride // 3):
            word = _packed_word(features, base + 3 * group)
            for k in range(4):
                out[at + 4 * group + k] = feature_of_code[(word >> (6 * k)) & _SIX_BITS]
        out[at + n_features - 1] = depth_of_code[np.int64(features[base + stride - 1]) & 0xFF]
    return copy_packed_row


@numba.njit(inline="always")
def _blend_six_bits(word: np.int64, sums: np.ndarray, first: int, keep: float, add: float,
                    inv_count: float) -> tuple[np.int64, np.float32]:
    """The running average of 4 packed 6-bit features (bits 0..23 of word) with the sums
    sums[first:first + 4], worked in units of the stored integers (no division, no re-read): the new
    24-bit word and the largest change, in those units."""
    scale = np.float32(FEATURE_SCALE)
    new_word = np.int64(0)
    steps = np.float32(0.0)
    for k in range(4):
        old = np.float32(_six_bit(word, k))
        q = np.rint(keep * old + add * scale * (sums[first + k] * inv_count))
        q = min(max(q, -scale), scale)
        new_word |= (np.int64(q) & _SIX_BITS) << (6 * k)
        steps = max(steps, abs(q - old))
    return new_word, steps


def blend_features(features: np.ndarray, n_features: int, voxel: int, keep: float | np.float32,
                   add: float | np.float32, sums: np.ndarray, inv_count: float | np.float32) -> float:
    """A voxel's features = keep * old + add * sums * inv_count (a running average), rounded to the
    storage; returns the largest change of a feature as stored. Kernels compile this per dtype
    (packed int8 without a decode and re-read); this body is the reference."""
    change = 0.0
    for c in range(n_features):
        old = load_feature(features, n_features, voxel, c)
        store_feature(features, n_features, voxel, c, keep * old + add * (sums[c] * inv_count))
        change = max(change, float(abs(load_feature(features, n_features, voxel, c) - old)))
    return change


@overload(blend_features, inline="always")
def _blend_features(features, n_features, voxel, keep, add, sums, inv_count):  # noqa: ANN001, ANN202 (numba)
    if not (isinstance(features, types.Array) and features.dtype == types.int8):
        def blend(features, n_features, voxel, keep, add, sums, inv_count):  # noqa: ANN001, ANN202
            change = np.float32(0.0)
            for c in range(n_features):
                old = load_feature(features, n_features, voxel, c)
                store_feature(features, n_features, voxel, c, keep * old + add * (sums[c] * inv_count))
                change = max(change, abs(load_feature(features, n_features, voxel, c) - old))
            return change
        return blend

    def blend_packed(features, n_features, voxel, keep, add, sums, inv_count):  # noqa: ANN001, ANN202
        stride = 3 * (n_features - 1) // 4 + 1
        base = voxel * stride
        if stride == 4:  # 4 learned features and the depth (the engine's): the row as one word
            row = _load_row32(features, base)
            new_row, steps = _blend_six_bits(row, sums, 0, keep, add, inv_count)
            old_depth = DEPTH_OF_CODE[row >> 24]
            code = _depth_code(keep * old_depth + add * (sums[4] * inv_count))
            _store_row32(features, base, new_row | (code << 24))
            return max(steps / np.float32(FEATURE_SCALE), abs(DEPTH_OF_CODE[code] - old_depth))
        steps = np.float32(0.0)
        for group in range(stride // 3):
            new_word, group_steps = _blend_six_bits(_packed_word(features, base + 3 * group), sums, 4 * group, keep,
                                                    add, inv_count)
            _store_word(features, base + 3 * group, new_word)
            steps = max(steps, group_steps)
        c = n_features - 1
        old = load_feature(features, n_features, voxel, c)
        store_feature(features, n_features, voxel, c, keep * old + add * (sums[c] * inv_count))
        return max(steps / np.float32(FEATURE_SCALE), abs(load_feature(features, n_features, voxel, c) - old))
    return blend_packed


# -- 8-bit channel: alpha -------------------------------------------------------------------------------
# Alpha (the sensor weighting, in [0, 1]) as code = round(254 * alpha), so 0.5 is code 127 exactly;
# a value on one side of 0.5 keeps its side (the outlier filter tests alpha < 0.5 and > 0.5).
# ALPHA_UNKNOWN: not evaluated yet (NaN). A channel of another dtype holds alpha values as they are.
ALPHA_UNKNOWN = 255
_ALPHA_STEPS = 254


def encode_alpha(alpha: np.ndarray) -> np.ndarray:
    """uint8 codes of alpha values (float, NaN = not evaluated)."""
    alpha = np.asarray(alpha, np.float32)
    code = np.rint(np.clip(np.nan_to_num(alpha, nan=0.5), 0.0, 1.0) * _ALPHA_STEPS).astype(np.uint8)
    code[(alpha < 0.5) & (code > _ALPHA_STEPS // 2 - 1)] = _ALPHA_STEPS // 2 - 1
    code[(alpha > 0.5) & (code < _ALPHA_STEPS // 2 + 1)] = _ALPHA_STEPS // 2 + 1
    code[np.isnan(alpha)] = ALPHA_UNKNOWN
    return code


def decode_alpha(codes: torch.Tensor) -> torch.Tensor:
    """Float32 alpha (NaN: not evaluated) of an alpha channel's entries (uint8 codes, or values)."""
    if codes.dtype != torch.uint8:
        return codes.float()
    alpha = codes.float().div_(_ALPHA_STEPS)  # in place: on a whole map, each copy is 4 bytes a voxel
    return alpha.masked_fill_(codes == ALPHA_UNKNOWN, float("nan"))


def load_alpha(alpha: np.ndarray, voxel: int) -> np.float32:
    """Alpha of a voxel from an alpha channel's kernel view (uint8 codes, or float16 bits / float32
    values through `load_f32`); NaN where not evaluated. Compiled per dtype; this body is the reference."""
    if alpha.dtype != np.uint8:
        return load_f32(alpha, voxel)
    code = alpha[voxel]
    return np.float32(np.nan) if code == ALPHA_UNKNOWN else np.float32(code) / np.float32(_ALPHA_STEPS)


@overload(load_alpha, inline="always")
def _load_alpha(alpha, voxel):  # noqa: ANN001, ANN202 (numba overload)
    if not (isinstance(alpha, types.Array) and alpha.dtype == types.uint8):
        return lambda alpha, voxel: load_f32(alpha, voxel)

    def load_code(alpha, voxel):  # noqa: ANN001, ANN202
        code = alpha[voxel]
        if code == ALPHA_UNKNOWN:
            return np.float32(np.nan)
        return np.float32(code) / np.float32(_ALPHA_STEPS)
    return load_code


def kernel_view(pool: torch.Tensor) -> np.ndarray:
    """The numpy view a kernel works on: float32 as is, float16 as int16 bit patterns."""
    if pool.dtype == torch.float16:
        return pool.view(torch.int16).numpy()
    return pool.numpy()


def _zeros(shape: tuple[int, ...], dtype: torch.dtype) -> tuple[torch.Tensor, mmap.mmap]:
    """A zero pool whose memory is committed only where it is written: an anonymous mapping (the
    kernel hands out zero pages on first touch), so a generous capacity costs address space, not
    memory, and pools rarely need to grow (a copy of everything). Transparent huge pages are
    requested for it: 512x fewer page faults and TLB misses when frames touch new blocks.
    Returns the pool and its mapping (`_release_rows` gives pages back through it)."""
    numpy_dtype = {torch.float32: np.float32, torch.float16: np.float16, torch.int64: np.int64,
                   torch.int8: np.int8, torch.uint8: np.uint8}[dtype]
    nbytes = max(int(np.prod(shape)) * np.dtype(numpy_dtype).itemsize, 1)
    memory = mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    if hasattr(mmap, "MADV_HUGEPAGE"):
        memory.madvise(mmap.MADV_HUGEPAGE)
    array = np.frombuffer(memory, dtype=numpy_dtype, count=int(np.prod(shape))).reshape(shape)
    with torch.inference_mode(False):  # grid state must stay writable outside inference mode
        return torch.from_numpy(array), memory


def _release_rows(pool: torch.Tensor, memory: mmap.mmap, start: int, stop: int) -> None:
    """Zero rows start..stop-1 of a pool made by `_zeros` and give their whole pages back to the OS
    (an anonymous mapping reads zeros again where it was released). Only the rows that share a page
    with rows outside the range are written: the released pages need no zeroing (on the large
    benchmark room that halves the cost of an eviction)."""
    row = pool[0].numel() * pool.element_size()
    first = -(-start * row // mmap.PAGESIZE) * mmap.PAGESIZE  # whole pages inside the rows
    last = stop * row // mmap.PAGESIZE * mmap.PAGESIZE
    if last <= first:
        pool[start:stop] = 0
        return
    pool[start:-(-first // row)] = 0  # rows (partly) before the first whole page
    pool[last // row:stop] = 0  # rows (partly) after the last one
    memory.madvise(mmap.MADV_DONTNEED, first, last - first)


class HashTable(NamedTuple):
    """The open-addressing table from block keys to slots: entry i holds the key keys[i] (EMPTY_KEY:
    free) of the block in slot slots[i]. A table that grows or is rebuilt is replaced by a complete
    new one, never filled in place while readers without the writers' lock may probe it (kernels
    under that lock add blocks to it in place: `hash_find_or_add`)."""

    keys: np.ndarray  # int64 entries, a power of two
    slots: np.ndarray  # int64, -1 where free

    def max_blocks(self) -> int:
        """Blocks it holds before it must grow (its load limit)."""
        return int(_MAX_LOAD * len(self.keys))


def _hash_table(slot_keys: np.ndarray, n_blocks: int, size: int) -> HashTable:
    """A new hash table of `size` entries holding blocks 0..n_blocks-1."""
    table = HashTable(np.full(size, EMPTY_KEY, np.int64), np.full(size, -1, np.int64))
    _rehash(slot_keys, n_blocks, table.keys, table.slots)
    return table


def warm_up_lookups() -> None:
    """Compile (or load from numba's cache) the table kernel integration does not call: the lookups
    (the rehash a growing table runs already ran when the first table was made)."""
    nothing = np.zeros(0, np.int64)
    _find_many(nothing, nothing, nothing, nothing)


def voxel_centres(block_coords: torch.Tensor, voxel_size_m: float) -> torch.Tensor:
    """B x 512 x 3 world positions (metres) of the voxel centres of blocks at these B x 3 coordinates."""
    r = torch.arange(BLOCK)
    lx, ly, lz = torch.meshgrid(r, r, r, indexing="ij")
    local = torch.stack([lx, ly, lz], dim=-1).reshape(1, BLOCK_VOXELS, 3)
    return ((block_coords * BLOCK).unsqueeze(1) + local).to(torch.float32) * voxel_size_m


class ChannelPools:
    """The storage of a grid's channels: per channel a pool of (capacity, 512, *storage shape), row
    `slot` holding one block's voxels, in memory committed only where written (`_zeros`). `pools`
    (channel name -> pool) is one dict for the pools' life, updated in place when they grow: the
    grid hands it out as `BlockGrid.pools`."""

    def __init__(self, shapes: dict[str, tuple[int, ...]], *, dtypes: dict[str, torch.dtype], capacity: int,
                 fill: dict[str, float]) -> None:
        self.fill = fill  # value of a channel in a new block (default 0)
        self.pools: dict[str, torch.Tensor] = {}
        self._memory: dict[str, mmap.mmap] = {}  # each pool's mapping (to give memory back)
        for name, shape in shapes.items():
            dtype = dtypes[name]
            if dtype == torch.int8:  # packed features (FEATURE_SCALE)
                shape = feature_storage_shape(shape[0], dtype)
            self.pools[name], self._memory[name] = _zeros((capacity, BLOCK_VOXELS, *shape), dtype)

    def grow(self, capacity: int, *, rows_in_use: int) -> None:
        """Pools of `capacity` rows, the first rows_in_use copied (a copy of everything: rarely)."""
        for name, pool in self.pools.items():
            grown, self._memory[name] = _zeros((capacity, *pool.shape[1:]), pool.dtype)
            grown[:rows_in_use] = pool[:rows_in_use]
            self.pools[name] = grown

    def fill_new_rows(self, start: int, stop: int) -> None:
        """Rows start..stop-1, of new blocks: each channel's fill value (zero rows need nothing)."""
        for name, value in self.fill.items():
            self.pools[name][start:stop] = value

    def move_rows(self, from_rows: np.ndarray, to_rows: np.ndarray, *, rows_kept: int, rows_in_use: int) -> None:
        """rows[to] = rows[from] in every pool (to_rows < rows_kept <= from_rows), then rows
        rows_kept..rows_in_use-1 emptied and their memory given back to the OS."""
        for name, pool in self.pools.items():
            _move_rows(pool.numpy().reshape(len(pool), -1).view(np.uint8), from_rows, to_rows)
            _release_rows(pool, self._memory[name], rows_kept, rows_in_use)

    def release(self, names: Iterable[str]) -> None:
        """Zero these channels in every row and give their memory back to the OS (for a map about
        to be forgotten, whose last reader does not need them)."""
        for name in names:
            _release_rows(self.pools[name], self._memory[name], 0, len(self.pools[name]))

    def row_bytes(self) -> int:
        """Bytes of one block's rows, all pools together."""
        return sum(p[0].numel() * p.element_size() for p in self.pools.values())


_SLOT_BYTES = 3 * 8 + 8  # a block's coordinates and key, besides its pool rows


class BlockGrid:
    """Blocks by slot: their keys and coordinates, the hash table that finds them, and their
    channels (`pools`, stored by `ChannelPools`). Slots are never freed except by `clear` and
    `remove_blocks`, which keeps them 0..n_blocks-1.

    Not thread-safe by itself: the engine serialises writers (allocation, integration) against
    readers that hold on to pool views. A reader without the writers' lock (the engine's alpha
    threads and meshing) takes the hash table as one `hash_table`: a table that grows or is
    rebuilt is replaced by a complete new one, never filled in place while readers may probe it.
    """

    def __init__(self, channels: dict[str, tuple[int, ...]], device: torch.device | str = "cpu",
                 initial_capacity: int = 1 << 18, dtypes: dict[str, torch.dtype] | None = None,
                 growth: float = 2.0, fill: dict[str, float] | None = None) -> None:
        if torch.device(device).type != "cpu":
            raise InputError("voxel grids live in CPU memory; run the networks on CUDA through the engine's device")
        self.device = torch.device("cpu")
        self.channel_shapes = dict(channels)
        self.channel_dtypes = {name: (dtypes or {}).get(name, torch.float32) for name in self.channel_shapes}
        self.growth = max(float(growth), 1.1)  # capacity factor when the pools grow (memory slack vs. copies)
        self.fill = dict(fill or {})  # value of a channel in a new block (default 0)
        # Evicted blocks' rows (spill.BlockSpill), taken back when they are allocated again; their
        # slots are kept until `take_restored_slots` (the engine marks their surroundings as changed).
        self.spill: BlockSpill | None = None
        self._restored_slots: list[np.ndarray] = []
        self._initial_capacity = initial_capacity
        self.clear()

    def clear(self) -> None:
        if self.spill is not None:
            self.spill.clear()
        cap = self._initial_capacity
        self.capacity = cap
        self.n_blocks = 0
        self._restored_slots = []
        self.slot_keys = np.full(cap, EMPTY_KEY, np.int64)
        self.coords = _zeros((cap, 3), torch.int64)[0]
        self.hash_table = _hash_table(self.slot_keys, 0, _INITIAL_TABLE)
        self.channel_pools = ChannelPools(self.channel_shapes, dtypes=self.channel_dtypes, capacity=cap,
                                          fill=self.fill)
        self.pools = self.channel_pools.pools  # the same dict, grown in place

    # -- lookup and allocation ------------------------------------------------------------
    def lookup_keys(self, keys: torch.Tensor) -> torch.Tensor:
        """Slots of the given block keys, -1 where the block does not exist."""
        out = np.empty(keys.numel(), np.int64)
        table = self.hash_table
        _find_many(table.keys, table.slots, np.ascontiguousarray(keys.reshape(-1).numpy(), np.int64), out)
        return torch.from_numpy(out).reshape(keys.shape)

    def lookup(self, block_coords: torch.Tensor) -> torch.Tensor:
        return self.lookup_keys(block_keys(block_coords))

    def allocate_keys(self, unique_keys: torch.Tensor) -> torch.Tensor:
        """Slots of the given block keys, allocating the missing blocks."""
        keys = np.ascontiguousarray(unique_keys.reshape(-1).numpy(), np.int64)
        out = np.empty(len(keys), np.int64)
        done = 0
        while done < len(keys):
            self.reserve(self.n_blocks + len(keys) - done)
            table = self.hash_table
            state = np.array([self.n_blocks, table.max_blocks()], np.int64)
            done += _add_many(table.keys, table.slots, keys[done:], state, self.slot_keys, out[done:])
            self.commit_new_blocks(int(state[0]))
        return torch.from_numpy(out)

    def commit_new_blocks(self, n_blocks: int) -> None:
        """Record blocks a kernel added through `hash_find_or_add` (slots n_blocks_before..n_blocks-1);
        those the spill holds get their rows back."""
        start = self.n_blocks
        if n_blocks > start:
            new = torch.from_numpy(self.slot_keys[start:n_blocks])
            self.coords[start:n_blocks] = keys_to_coords(new)
            self.channel_pools.fill_new_rows(start, n_blocks)
            if self.spill is not None and len(self.spill):
                try:
                    restored = self.spill.take(self.slot_keys[start:n_blocks],
                                               [pool[start:n_blocks].numpy() for pool in self.pools.values()])
                except BaseException:  # (a disk that fails a read) the blocks stay spilled and are not added:
                    # left in the hash table past the committed slots, the next frame reaching them crashed
                    self.slot_keys[start:n_blocks] = EMPTY_KEY
                    self.coords[start:n_blocks] = 0
                    self.hash_table = _hash_table(self.slot_keys, start, len(self.hash_table.keys))
                    raise
                self._restored_slots.append(start + np.flatnonzero(restored))
            self.n_blocks = n_blocks

    def on_disk(self, keys: np.ndarray) -> np.ndarray:
        """Which of these block keys the spill holds."""
        if self.spill is None or not len(self.spill):
            return np.zeros(len(keys), np.bool_)
        return self.spill.holds(keys)

    def take_restored_slots(self) -> np.ndarray:
        """The slots of blocks taken back from the spill since the last call (before any removal)."""
        slots, self._restored_slots = self._restored_slots, []
        return np.concatenate(slots) if slots else np.zeros(0, np.int64)

    def reserve(self, n_blocks: int, *, added: int = 0) -> None:
        """Room for n_blocks: pools, slot arrays and a hash table below its load limit. `added`: blocks
        a kernel added (`hash_find_or_add`) after the committed ones and not committed yet; they keep
        their slots and keys (their rows hold nothing before the commit)."""
        n_keys = self.n_blocks + added
        if n_blocks > self.capacity:
            cap = max(n_blocks, int(self.growth * self.capacity) + 1)
            self.channel_pools.grow(cap, rows_in_use=self.n_blocks)
            coords = _zeros((cap, 3), torch.int64)[0]
            coords[: self.n_blocks] = self.coords[: self.n_blocks]
            self.coords = coords
            slot_keys = np.full(cap, EMPTY_KEY, np.int64)
            slot_keys[:n_keys] = self.slot_keys[:n_keys]
            self.slot_keys = slot_keys
            self.capacity = cap
        if n_blocks > self.hash_table.max_blocks():
            size = len(self.hash_table.keys)
            while n_blocks > _MAX_LOAD * size:
                size *= 2
            self.hash_table = _hash_table(self.slot_keys, n_keys, size)

    def remove_blocks(self, victims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Drop these blocks. Slots stay 0..n_blocks-1: survivors in the last slots move into the
        freed ones; the memory of the slots given up goes back to the OS. Returns the moves
        (from_slots, to_slots), for whoever keeps per-slot data of its own."""
        victims = np.unique(np.asarray(victims, np.int64))
        n_old = self.n_blocks
        n_new = n_old - len(victims)
        holes = victims[victims < n_new]
        tail = np.arange(n_new, n_old)
        movers = tail[~np.isin(tail, victims)]  # as many as holes
        self.channel_pools.move_rows(movers, holes, rows_kept=n_new, rows_in_use=n_old)
        self.coords[holes] = self.coords[movers]
        self.coords[n_new:n_old] = 0
        self.slot_keys[holes] = self.slot_keys[movers]
        self.slot_keys[n_new:n_old] = EMPTY_KEY
        self.n_blocks = n_new
        self.hash_table = _hash_table(self.slot_keys, self.n_blocks, len(self.hash_table.keys))
        return movers, holes

    # -- memory ----------------------------------------------------------------------------
    def nbytes(self) -> int:
        """Bytes of the blocks in use and the index (pool pages beyond them are never committed)."""
        table = self.hash_table
        return self.n_blocks * (self.channel_pools.row_bytes() + _SLOT_BYTES) + table.keys.nbytes + table.slots.nbytes

    def bytes_per_block(self) -> int:
        """Memory one more block costs at most: its pool rows, coordinates and key, and its share of
        the hash table (which doubles at load factor 0.5, so up to 4 entries a block)."""
        entry = self.hash_table.keys.itemsize + self.hash_table.slots.itemsize
        return self.channel_pools.row_bytes() + _SLOT_BYTES + int(4 * entry)
