"""RVL: the run-length / variable-length depth codec (Wilson, "Fast Lossless Depth Image Compression",
ISS 2017) behind image_transport's '<encoding>; compressedDepth rvl' format.

Layout after compressedDepth's 12-byte header: uint32 columns, uint32 rows (little-endian), then a
stream of little-endian 32-bit words read from their most significant nibble down. Each nibble
carries 3 value bits, least significant group first, and a continuation bit (0x8). The values
alternate: a count of zero pixels, a count of non-zero pixels, then that many zigzag-coded
differences to the previous non-zero pixel.
"""
from __future__ import annotations

import numba
import numpy as np

__all__ = ["MAX_PIXELS", "rvl_decode"]

MAX_PIXELS = 1 << 26  # 64 M pixels: past any depth camera; a larger size is a corrupt header

_NIBBLE_SHIFTS = np.arange(28, -1, -4, dtype=np.uint32)

# _decode's results
_OK, _ENDED, _OVERRUN, _TOO_LONG = 0, 1, 2, 3


@numba.njit(inline="always")
def _value(nibbles: np.ndarray, i: int) -> tuple[int, int]:
    """The variable-length value starting at nibble i -> (value, next i); value -1 if the stream
    ends inside it, -2 if it has more digits than a 31-bit value."""
    value, shift = 0, 0
    while True:
        if i >= nibbles.size:
            return -1, i
        nibble = nibbles[i]
        i += 1
        value |= int(nibble & 7) << shift
        if not nibble & 8:
            return value, i
        shift += 3
        if shift > 30:
            return -2, i


@numba.njit(cache=True, nogil=True)
def _decode(nibbles: np.ndarray, out: np.ndarray) -> tuple[int, int]:
    """Fill `out` (uint16) from the nibble stream; returns (_OK or the failure, pixels written)."""
    i, pixel, previous = 0, 0, 0
    while pixel < out.size:
        zeros, i = _value(nibbles, i)
        nonzeros, i = _value(nibbles, i)
        if zeros < 0 or nonzeros < 0:
            return (_ENDED if min(zeros, nonzeros) == -1 else _TOO_LONG), pixel
        if pixel + zeros + nonzeros > out.size:
            return _OVERRUN, pixel
        out[pixel:pixel + zeros] = 0
        pixel += zeros
        for _ in range(nonzeros):
            value, i = _value(nibbles, i)
            if value < 0:
                return (_ENDED if value == -1 else _TOO_LONG), pixel
            previous = (previous + ((value >> 1) ^ -(value & 1))) & 0xFFFF  # zigzag-coded difference
            out[pixel] = previous
            pixel += 1
    return _OK, pixel


def rvl_decode(payload: np.ndarray) -> np.ndarray:
    """compressedDepth's rvl payload (after its 12-byte header), uint8 -> uint16 (rows, cols).

    Raises ValueError naming what is wrong with a malformed payload; never reads past it.
    """
    payload = np.ascontiguousarray(payload, np.uint8).reshape(-1)
    if payload.size < 8:
        raise ValueError(f"compressedDepth rvl payload has {payload.size} B, less than its 8-byte size")
    cols, rows = (int(v) for v in payload[:8].view("<u4"))
    if rows == 0 or cols == 0 or rows * cols > MAX_PIXELS:
        raise ValueError(f"compressedDepth rvl payload says {cols}x{rows} pixels; the message is corrupt")
    words = payload[8: 8 + (payload.size - 8) // 4 * 4].view("<u4")
    nibbles = ((words[:, None] >> _NIBBLE_SHIFTS) & 0xF).astype(np.uint8).reshape(-1)
    out = np.empty(rows * cols, np.uint16)
    status, pixels = _decode(nibbles, out)
    if status == _ENDED:
        raise ValueError(f"compressedDepth rvl payload ends after {pixels} of {cols}x{rows} pixels; "
                         "the message is truncated")
    if status != _OK:
        raise ValueError(f"compressedDepth rvl payload is corrupt after {pixels} of {cols}x{rows} pixels "
                         f"({'a run overruns the image' if status == _OVERRUN else 'a value has too many digits'})")
    return out.reshape(rows, cols)
