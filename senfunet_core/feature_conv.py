"""The feature nets' inference on the CPU: their 3x3 convolutions of 4 channels and tanh as a numba kernel.

oneDNN is built for many channels; with the feature nets' 4 it spends most of a frame's feature
time on layout and dispatch, and torch's tanh (or sigmoid) is another pass over the image per
layer. Here each output row is one pass per input channel and pair of output channels with the
taps as scalars, which the compiler vectorises over the row, and the tanh is applied to the row
while it is in cache, from an exp written in plain arithmetic (a libm exp per value would not
vectorise). Float32; the sums
run in another order than oneDNN's and the tanh is within a few 1e-7 of torch's, so the features
equal torch's within 1e-5 (test_networks).
"""
from __future__ import annotations

import numba
import numpy as np

_NO_RESIDUAL = np.zeros((0, 0, 0), np.float32)


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _tanh(z: float) -> np.float32:
    """tanh(z) = (e - 1) / (e + 1), e = exp(2 z); exp(y) as exp(y / 32) ** 32 with a degree-9 Taylor
    polynomial on |y / 32| <= 0.5625, in float64 (the squarings would multiply float32's rounding)."""
    u = min(max(np.float64(z), -9.0), 9.0) * (2.0 / 32.0)  # tanh(9) is 1 in float32
    p = u * (1.0 / 362880.0) + 1.0 / 40320.0
    for c in (1.0 / 5040.0, 1.0 / 720.0, 1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0, 1.0):
        p = p * u + c
    for _ in range(5):
        p = p * p
    return np.float32((p - 1.0) / (p + 1.0))


# error_model numpy: no zero-division check per value (it would stop the vectorisation; e + 1 > 0 anyway)
@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})
def conv3x3_tanh(x_padded: np.ndarray, weight: np.ndarray, bias: np.ndarray, residual: np.ndarray,
                 out_padded: np.ndarray) -> None:
    """tanh of the zero-padded 3x3 convolution of one image, plus `residual` where it has any values:
    x_padded (Cin, H+2, W+2) float32 with a zero border, weight (Cout, Cin, 3, 3), bias (Cout,),
    residual (Cout, H+2, W+2) or empty -> out_padded[:, 1:H+1, 1:W+1] (its border untouched)."""
    n_in, h_padded, w_padded = x_padded.shape
    h, w = h_padded - 2, w_padded - 2
    n_out = weight.shape[0]
    acc = np.empty((n_out, w), np.float32)
    for y in range(h):
        for co in range(n_out):
            acc[co, :] = bias[co]
        for ci in range(n_in):
            # one pass over the row per input channel and pair of output channels, with the 9 taps
            # of both as scalars: the loop over x vectorises, and the two accumulators share each
            # loaded input (a pass per output channel loads every input once more)
            r0, r1, r2 = x_padded[ci, y], x_padded[ci, y + 1], x_padded[ci, y + 2]
            for co in range(0, n_out - 1, 2):
                k00, k01, k02 = weight[co, ci, 0, 0], weight[co, ci, 0, 1], weight[co, ci, 0, 2]
                k10, k11, k12 = weight[co, ci, 1, 0], weight[co, ci, 1, 1], weight[co, ci, 1, 2]
                k20, k21, k22 = weight[co, ci, 2, 0], weight[co, ci, 2, 1], weight[co, ci, 2, 2]
                m00, m01, m02 = weight[co + 1, ci, 0, 0], weight[co + 1, ci, 0, 1], weight[co + 1, ci, 0, 2]
                m10, m11, m12 = weight[co + 1, ci, 1, 0], weight[co + 1, ci, 1, 1], weight[co + 1, ci, 1, 2]
                m20, m21, m22 = weight[co + 1, ci, 2, 0], weight[co + 1, ci, 2, 1], weight[co + 1, ci, 2, 2]
                a, b = acc[co], acc[co + 1]
                for x in range(w):
                    v00, v01, v02 = r0[x], r0[x + 1], r0[x + 2]
                    v10, v11, v12 = r1[x], r1[x + 1], r1[x + 2]
                    v20, v21, v22 = r2[x], r2[x + 1], r2[x + 2]
                    a[x] += (k00 * v00 + k01 * v01 + k02 * v02 + k10 * v10 + k11 * v11 + k12 * v12
                             + k20 * v20 + k21 * v21 + k22 * v22)
                    b[x] += (m00 * v00 + m01 * v01 + m02 * v02 + m10 * v10 + m11 * v11 + m12 * v12
                             + m20 * v20 + m21 * v21 + m22 * v22)
            if n_out % 2:  # an odd last output channel: its pass alone
                co = n_out - 1
                k00, k01, k02 = weight[co, ci, 0, 0], weight[co, ci, 0, 1], weight[co, ci, 0, 2]
                k10, k11, k12 = weight[co, ci, 1, 0], weight[co, ci, 1, 1], weight[co, ci, 1, 2]
                k20, k21, k22 = weight[co, ci, 2, 0], weight[co, ci, 2, 1], weight[co, ci, 2, 2]
                a = acc[co]
                for x in range(w):
                    a[x] += (k00 * r0[x] + k01 * r0[x + 1] + k02 * r0[x + 2]
                             + k10 * r1[x] + k11 * r1[x + 1] + k12 * r1[x + 2]
                             + k20 * r2[x] + k21 * r2[x + 1] + k22 * r2[x + 2])
        for co in range(n_out):
            out = out_padded[co, y + 1]
            a = acc[co]
            if residual.size:
                res = residual[co, y + 1]
                for x in range(w):
                    out[x + 1] = _tanh(a[x]) + res[x + 1]
            else:
                for x in range(w):
                    out[x + 1] = _tanh(a[x])


def feature_net_forward(convs: list[tuple[np.ndarray, np.ndarray]], x: np.ndarray) -> np.ndarray:
    """The residual conv-tanh stack of a FeatureNet on one image: x (Cin, H, W) float32 ->
    (C, H, W) before normalisation. convs: each conv's (weight, bias) as float32 arrays, in order
    (conv_a, conv_b of block 1, ...)."""
    c_in, h, w = x.shape
    n_channels = convs[0][0].shape[0]
    padded_in = np.zeros((c_in, h + 2, w + 2), np.float32)
    padded_in[:, 1:-1, 1:-1] = x
    # three padded buffers in turn: a block's input (the previous block's output), its middle, its output
    buffers = [np.zeros((n_channels, h + 2, w + 2), np.float32) for _ in range(3)]
    current = padded_in
    for i in range(0, len(convs), 2):
        middle, out = [b for b in buffers if b is not current][:2]
        conv3x3_tanh(current, *convs[i], _NO_RESIDUAL, middle)
        # each block's output is added to the next block's output
        conv3x3_tanh(middle, *convs[i + 1], _NO_RESIDUAL if current is padded_in else current, out)
        current = out
    return np.ascontiguousarray(current[:, 1:-1, 1:-1])
