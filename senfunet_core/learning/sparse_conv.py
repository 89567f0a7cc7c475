"""G evaluated only where the loss needs alpha: the 3^3 convolutions as gathers and matrix products
over the voxels within reach of the outputs (replicate padding at the box's faces)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .. import networks

_OFFSETS_27 = torch.tensor([(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)])


def _neighbours_27(index: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """Box-local indices (K,) -> their 3^3 neighbourhoods (K, 27), clamped to the box (replicate padding),
    in the order of a Conv3d kernel's (kx, ky, kz) taps."""
    sx, sy, sz = size
    ix, iy, iz = index // (sy * sz), (index // sz) % sy, index % sz
    nx = (ix.unsqueeze(1) + _OFFSETS_27[:, 0]).clamp_(0, sx - 1)
    ny = (iy.unsqueeze(1) + _OFFSETS_27[:, 1]).clamp_(0, sy - 1)
    nz = (iz.unsqueeze(1) + _OFFSETS_27[:, 2]).clamp_(0, sz - 1)
    return (nx * sy + ny) * sz + nz


def _compact(index: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Sorted unique values of `index` (all in 0..n-1) and each entry's position among them
    (torch.unique with return_inverse, by marking a dense table: no sort)."""
    flat = index.reshape(-1).numpy()
    mark = np.zeros(n, np.bool_)
    mark[flat] = True
    unique = np.flatnonzero(mark)
    position = np.empty(n, np.int64)
    position[unique] = np.arange(len(unique))
    return torch.from_numpy(unique), torch.from_numpy(position[flat]).reshape(index.shape)


@dataclass
class SparsePlan:
    """Where G must run to give alpha at `out` voxels of a box (replicate padding)."""

    inputs: torch.Tensor  # (K,) box-local indices of the input voxels conv1 reads
    conv1_taps: torch.Tensor  # (M1, 27) positions in `inputs` read by each conv1 output
    conv2_taps: torch.Tensor  # (M, 27) positions among the conv1 outputs read by each conv2 output


def sparse_plan(out_index: torch.Tensor, size: tuple[int, int, int]) -> SparsePlan:
    n = int(np.prod(size))
    middle, conv2_taps = _compact(_neighbours_27(out_index, size), n)  # conv1 outputs conv2 reads
    inputs, conv1_taps = _compact(_neighbours_27(middle, size), n)
    return SparsePlan(inputs, conv1_taps, conv2_taps)


def sparse_alpha_planned(net: networks.WeightingNet, x_inputs: torch.Tensor, plan: SparsePlan) -> torch.Tensor:
    """G at the plan's output voxels from its inputs x_inputs (K, C) (the box voxels plan.inputs)."""
    conv1, conv2, conv3 = net.conv1, net.conv2, net.conv3
    assert conv1.bias is not None and conv2.bias is not None and conv3.bias is not None
    w1 = conv1.weight.permute(2, 3, 4, 1, 0).reshape(-1, conv1.out_channels)  # (27 * C, 32), tap-major
    h1 = torch.relu(x_inputs.index_select(0, plan.conv1_taps.reshape(-1)).reshape(len(plan.conv1_taps), -1) @ w1
                    + conv1.bias)
    w2 = conv2.weight.permute(2, 3, 4, 1, 0).reshape(-1, conv2.out_channels)
    h2 = torch.relu(h1.index_select(0, plan.conv2_taps.reshape(-1)).reshape(len(plan.conv2_taps), -1) @ w2
                    + conv2.bias)
    return torch.sigmoid(h2 @ conv3.weight.reshape(conv3.out_channels, -1).T + conv3.bias).reshape(-1)


def sparse_alpha(net: networks.WeightingNet, x: torch.Tensor, size: tuple[int, int, int],
                 out_index: torch.Tensor) -> torch.Tensor:
    """G with replicate padding on a box, evaluated only at the voxels `out_index` (M,).

    x: (N, C) inputs of the box's voxels in box-local order ((x * size_y + y) * size_z + z).
    Equals `net(x as 1 x C x box, pad=True)` at those voxels: every 3^3 convolution reads its
    input at box-clamped neighbours (what replicate padding does), conv1 runs only where conv2
    reads it, and only the inputs conv1 reads are touched. A frame updates a small part of a 64^3
    chunk, so this costs far less than the dense pass, and gradients flow the same way."""
    size = (int(size[0]), int(size[1]), int(size[2]))
    plan = sparse_plan(out_index, size)
    return sparse_alpha_planned(net, x.index_select(0, plan.inputs), plan)
