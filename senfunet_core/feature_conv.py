"""The feature nets' inference on the CPU: their 3x3 convolutions of 4 channels and tanh as a numba kernel.

oneDNN is built for many channels; with the feature nets' 4 it spends most of a frame's feature
time on layout and dispatch, and torch's tanh (or sigmoid) is another pass over the image per
layer. Here each output row is one pass per input row and group of four output channels with the
taps as scalars, which the compiler vectorises over the row, and the tanh is applied to the row
while it is in cache, from a float32 exp written in plain arithmetic (a libm exp per value would
not vectorise). The last pass normalises each pixel's features and writes them, with the depth,
as the pixel rows integration reads (`feature_net_rows`). Float32; the sums run in another order
than oneDNN's and the tanh is within 1e-7 of the exact one, so the features equal torch's within
1e-4 (test_networks).
"""
from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

_NO_RESIDUAL = np.zeros((0, 0, 0), np.float32)


@intrinsic
def _f32_of_bits(typingctx, bits):  # noqa: ANN001 (numba intrinsic)
    """The float32 whose bits are the low 32 of the integer `bits`."""
    if not isinstance(bits, types.Integer):
        return None

    def codegen(context, builder, signature, args):  # noqa: ANN001
        word = args[0] if args[0].type.width == 32 else builder.trunc(args[0], ir.IntType(32))
        return builder.bitcast(word, ir.FloatType())
    return types.float32(bits), codegen


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _tanh(z: float) -> np.float32:
    """tanh(z) = sign(z) (1 - e) / (1 + e), e = exp(-2 |z|) in float32: -2 |z| = n ln2 + r with |r| <=
    ln2 / 2 (ln2 in two parts, so n ln2 is exact to float32), exp(r) by its degree-7 Taylor polynomial
    (error below 1e-8), 2^n from its exponent bits. Absolute error below 1e-7."""
    a = min(abs(np.float32(z)), np.float32(9.0))  # tanh(9) is 1 in float32
    y = np.float32(-2.0) * a
    n = np.rint(y * np.float32(1.4426950408889634))  # 1 / ln 2
    r = (y - n * np.float32(0.693145751953125)) - n * np.float32(1.4286067653e-06)
    p = np.float32(1.0 / 5040.0)
    for c in (1.0 / 720.0, 1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0, 1.0):
        p = p * r + np.float32(c)
    # int32, not int64: AVX2 converts float32 vectors to int32 only (an int64 conversion is scalar)
    e = p * _f32_of_bits((np.int32(n) + np.int32(127)) << np.int32(23))
    t = (np.float32(1.0) - e) / (np.float32(1.0) + e)
    return t if z >= 0 else -t


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
    n_quads = n_out // 4 * 4
    for y in range(h):
        for co in range(n_out):
            acc[co, :] = bias[co]
        for ci in range(n_in):
            for dy in range(3):
                # one pass over an input row per group of four output channels, with the row's 3 taps
                # of each as scalars: the loop over x vectorises, the four accumulators share each
                # loaded input, and the 12 taps stay in registers (all 9 taps of four channels would not)
                r = x_padded[ci, y + dy]
                for co in range(0, n_quads, 4):
                    k00, k01, k02 = weight[co, ci, dy, 0], weight[co, ci, dy, 1], weight[co, ci, dy, 2]
                    k10, k11, k12 = weight[co + 1, ci, dy, 0], weight[co + 1, ci, dy, 1], weight[co + 1, ci, dy, 2]
                    k20, k21, k22 = weight[co + 2, ci, dy, 0], weight[co + 2, ci, dy, 1], weight[co + 2, ci, dy, 2]
                    k30, k31, k32 = weight[co + 3, ci, dy, 0], weight[co + 3, ci, dy, 1], weight[co + 3, ci, dy, 2]
                    a0, a1, a2, a3 = acc[co], acc[co + 1], acc[co + 2], acc[co + 3]
                    for x in range(w):
                        v0, v1, v2 = r[x], r[x + 1], r[x + 2]
                        a0[x] += k00 * v0 + k01 * v1 + k02 * v2
                        a1[x] += k10 * v0 + k11 * v1 + k12 * v2
                        a2[x] += k20 * v0 + k21 * v1 + k22 * v2
                        a3[x] += k30 * v0 + k31 * v1 + k32 * v2
                for co in range(n_quads, n_out):  # the output channels beyond the last group of four
                    k0, k1, k2 = weight[co, ci, dy, 0], weight[co, ci, dy, 1], weight[co, ci, dy, 2]
                    a = acc[co]
                    for x in range(w):
                        a[x] += k0 * r[x] + k1 * r[x + 1] + k2 * r[x + 2]
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


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})
def _normalised_rows(features_padded: np.ndarray, depth_m: np.ndarray, rows: np.ndarray) -> None:
    """rows[v * W + u] = (features / their L2 norm (at least 1e-8), depth) of pixel (v, u):
    features_padded (C, H+2, W+2), depth_m (H, W) -> rows (H*W, C+1), as FeatureNet.forward's
    normalisation and concatenation, laid out per pixel."""
    n_channels, h, w = features_padded.shape[0], depth_m.shape[0], depth_m.shape[1]
    norm = np.empty(w, np.float32)
    for y in range(h):
        norm[:] = 0.0
        for c in range(n_channels):
            f = features_padded[c, y + 1]
            for x in range(w):
                norm[x] += f[x + 1] * f[x + 1]
        for x in range(w):
            norm[x] = np.float32(1.0) / max(np.sqrt(norm[x]), np.float32(1e-8))
        for c in range(n_channels):
            f = features_padded[c, y + 1]
            for x in range(w):
                rows[y * w + x, c] = f[x + 1] * norm[x]
        for x in range(w):
            rows[y * w + x, n_channels] = depth_m[y, x]


def _conv_stack(convs: list[tuple[np.ndarray, np.ndarray]], padded_in: np.ndarray) -> np.ndarray:
    """The residual conv-tanh stack of a FeatureNet on one image: padded_in (Cin, H+2, W+2) float32
    with a zero border -> (C, H+2, W+2) before normalisation, with a zero border."""
    n_channels = convs[0][0].shape[0]
    # three padded buffers in turn: a block's input (the previous block's output), its middle, its output
    buffers = [np.zeros((n_channels, *padded_in.shape[1:]), np.float32) for _ in range(3)]
    current = padded_in
    for i in range(0, len(convs), 2):
        middle, out = [b for b in buffers if b is not current][:2]
        conv3x3_tanh(current, *convs[i], _NO_RESIDUAL, middle)
        # each block's output is added to the next block's output
        conv3x3_tanh(middle, *convs[i + 1], _NO_RESIDUAL if current is padded_in else current, out)
        current = out
    return current


def feature_net_forward(convs: list[tuple[np.ndarray, np.ndarray]], x: np.ndarray) -> np.ndarray:
    """The residual conv-tanh stack of a FeatureNet on one image: x (Cin, H, W) float32 ->
    (C, H, W) before normalisation. convs: each conv's (weight, bias) as float32 arrays, in order
    (conv_a, conv_b of block 1, ...)."""
    padded_in = np.zeros((x.shape[0], x.shape[1] + 2, x.shape[2] + 2), np.float32)
    padded_in[:, 1:-1, 1:-1] = x
    return np.ascontiguousarray(_conv_stack(convs, padded_in)[:, 1:-1, 1:-1])


def feature_net_rows(convs: list[tuple[np.ndarray, np.ndarray]], depth_m: np.ndarray,
                     rgb: np.ndarray | None = None) -> np.ndarray:
    """A FeatureNet's output on one frame as pixel rows: depth_m (H, W) float32 and, for a net that
    takes colour (convs[0] with 4 input channels), rgb (H, W, 3) uint8 or None (black) -> (H*W, C+1)
    float32, each pixel's normalised features and its depth (pixel v * W + u)."""
    h, w = depth_m.shape
    padded_in = np.zeros((convs[0][0].shape[1], h + 2, w + 2), np.float32)
    padded_in[0, 1:-1, 1:-1] = depth_m
    if padded_in.shape[0] > 1 and rgb is not None:  # colour in 0..1, divided in float32 as torch divides
        np.divide(rgb.transpose(2, 0, 1), np.float32(255.0), out=padded_in[1:, 1:-1, 1:-1])
    stack = _conv_stack(convs, padded_in)
    rows = np.empty((h * w, stack.shape[0] + 1), np.float32)
    _normalised_rows(stack, depth_m, rows)
    return rows
