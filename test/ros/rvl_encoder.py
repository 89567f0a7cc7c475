"""An RVL encoder for the tests, written from the codec's description (Wilson, ISS 2017) as
image_transport's compressedDepth rvl lays it out: uint32 columns, uint32 rows, then words."""
from __future__ import annotations

import numpy as np


def rvl_payload(depth: np.ndarray) -> bytes:
    """uint16 (rows, cols) -> the payload after compressedDepth's 12-byte header."""
    nibbles: list[int] = []

    def put(value: int) -> None:
        while True:
            digit, value = value & 7, value >> 3
            nibbles.append(digit | (8 if value else 0))
            if not value:
                return

    flat = [int(v) for v in np.asarray(depth, np.uint16).reshape(-1)]
    i, previous = 0, 0
    while i < len(flat):
        start = i
        while i < len(flat) and flat[i] == 0:
            i += 1
        put(i - start)
        start = i
        while i < len(flat) and flat[i] != 0:
            i += 1
        put(i - start)
        for current in flat[start:i]:
            delta = current - previous
            put((delta << 1) ^ (-1 if delta < 0 else 0))
            previous = current
    nibbles += [0] * (-len(nibbles) % 8)
    words = np.array(nibbles, np.uint32).reshape(-1, 8) << np.arange(28, -1, -4, dtype=np.uint32)
    rows, cols = depth.shape
    return np.array([cols, rows], "<u4").tobytes() + words.sum(axis=1, dtype=np.uint32).astype("<u4").tobytes()
