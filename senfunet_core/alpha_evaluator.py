"""The weighting net on a batch of blocks: where alpha matters in them, the net's inputs there, the
net, and alpha as the alpha pool stores it.

`AlphaEvaluator.evaluate` reads the grid without the data lock and writes nothing (see the threading
model in `engine`), so that the alpha threads evaluate batches side by side; the scheduler
(`alpha_scheduler`) chooses the batches and writes what they give.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from .alpha import WINDOW, evaluate_gathers, holds_surface_targets, surface_targets, target_gathers, weighting_windows
from .block_store import BlockStore
from .grid import BLOCK, encode_alpha
from .scratch import ThreadScratch
from .weighting_int8 import Int8WeightingNet

__all__ = ["AlphaBatch", "AlphaEvaluator", "surface_windows", "weighting_net_flops"]


@dataclass
class AlphaBatch:
    """The weighting net's output for a batch of blocks."""

    slots: np.ndarray  # B blocks checked
    holds: np.ndarray  # B bool: holds voxels alpha matters for (see EngineConfig.alpha_voxels)
    voxels: np.ndarray  # N flat voxel indices evaluated (slot * 512 + local)
    alpha: np.ndarray  # N values as the alpha pool stores them (8-bit codes, or float32)
    flops: int = 0  # the net's FLOPs for it (for the benchmark's fraction of peak)


class AlphaEvaluator:
    """The weighting net over a `BlockStore`'s grid (see the module docstring)."""

    def __init__(self, store: BlockStore, net: Any, *, alpha_voxels: str, alpha_dtype: str, tsdf_input: bool,
                 band_m: float, device: torch.device,
                 int8_net: Int8WeightingNet | None = None) -> None:
        """int8_net: G in int8 (`weighting_int8.Int8WeightingNet`), used for whole blocks on the CPU
        (alpha_dtype "int8"; surface_voxels' matrix products stay float32)."""
        self.store = store
        self.net = net
        self.int8_net = int8_net
        self.alpha_voxels = alpha_voxels
        self.dtype = torch.bfloat16 if alpha_dtype == "bfloat16" else torch.float32
        self.tsdf_input = tsdf_input
        self.tsdf_scale = 2.0 / band_m
        self.device = device
        self._scratch = ThreadScratch()  # per evaluating thread: its input windows' buffer

    @torch.inference_mode()  # grad mode is per thread, and evaluating threads may be new
    def evaluate(self, slots: np.ndarray) -> AlphaBatch:
        """The weighting net on these blocks, where alpha matters (`alpha_voxels`): "all", every voxel
        of every block; "surface", every voxel of the blocks that hold `alpha.surface_targets` (as
        blocks with a 2-voxel halo: convolutions); "surface_voxels", those targets alone (layer by
        layer, as matrix products). Reads the grid without the data lock (see `engine`) and writes
        nothing, so several threads may evaluate batches at once."""
        neighbours = self.store.neighbours(slots)
        holds = np.ones(len(slots), bool)
        if self.alpha_voxels != "all":
            if self.alpha_voxels == "surface_voxels":
                targets = surface_targets(neighbours, *self.store.views("tsdf0", "weight0", "tsdf1", "weight1"))
                holds = targets.any(axis=1)
            else:  # whole blocks: whether each holds a target is enough
                holds = self.holds_surface(neighbours)
            if not holds.any():
                return AlphaBatch(slots, holds, np.zeros(0, np.int64), np.zeros(0, np.float32))
        if self.alpha_voxels == "surface_voxels":
            inputs, gather_1, gather_2, voxels = target_gathers(neighbours[holds], targets[holds], *self.inputs())
            alpha = evaluate_gathers(self.net, inputs, gather_1, gather_2, dtype=self.dtype)
            flops = weighting_net_flops(self.net, layer_1_positions=len(gather_1), voxels=len(voxels),
                                        inputs=27 * inputs.shape[1])
            return AlphaBatch(slots, holds, voxels, self._as_stored(alpha), flops)
        slots_holding = slots[holds]
        if self.device.type == "cpu":  # the inputs written in the net's dtype, to this thread's buffer
            bfloat16 = self.dtype == torch.bfloat16
            stored = np.uint8 if self.int8_net is not None else np.uint16 if bfloat16 else np.float32
            windows = weighting_windows(neighbours[holds], *self.inputs(), out=self._scratch.array(
                "windows", len(slots_holding) * WINDOW**3 * self.net.conv1.in_channels, stored),
                depth_max_m=self.int8_net.depth_max_m if self.int8_net is not None else 1.0)
            x = torch.from_numpy(windows.view(np.int16)).view(torch.bfloat16) if bfloat16 else torch.from_numpy(windows)
            x = x.permute(0, 4, 1, 2, 3)  # channels last
            out = self.int8_net(x) if self.int8_net is not None else self.net.infer(x, self.dtype)
            alpha = out.reshape(-1).numpy()
        else:
            windows = self.windows(neighbours[holds])
            x = torch.from_numpy(windows).permute(0, 4, 1, 2, 3).to(self.device)  # B x C x 12^3, channels last
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.dtype == torch.bfloat16):
                alpha = self.net(x, pad=False).float().reshape(-1).cpu().numpy()
        voxels = (slots_holding[:, None] * BLOCK**3 + np.arange(BLOCK**3)).reshape(-1)
        flops = weighting_net_flops(self.net, layer_1_positions=len(slots_holding) * (WINDOW - 2) ** 3,
                                    voxels=len(voxels), inputs=27 * windows.shape[-1])
        return AlphaBatch(slots, holds, voxels, self._as_stored(alpha), flops)

    def holds_surface(self, neighbours: np.ndarray) -> np.ndarray:
        """Per block (`BlockStore.neighbours` rows), whether it holds voxels alpha matters for
        (`alpha.holds_surface_targets`)."""
        return holds_surface_targets(neighbours, *self.store.views("tsdf0", "weight0", "tsdf1", "weight1"))

    def _as_stored(self, alpha: np.ndarray) -> np.ndarray:
        """Alpha as the pool stores it: encoded here, by the evaluating thread, not by the scheduler's
        `write` under the data lock that integration waits for."""
        return encode_alpha(alpha) if self.store.grid.pools["alpha"].dtype == torch.uint8 else alpha

    def windows(self, neighbours: np.ndarray) -> np.ndarray:
        """The weighting net's B x 12^3 x C input windows of these blocks (alpha.weighting_windows)."""
        return weighting_windows(neighbours, *self.inputs())

    def release_buffers(self) -> None:
        """Let go of every thread's window buffer (after a bulk evaluation)."""
        self._scratch.release()

    def inputs(self) -> tuple:
        """The pools the weighting net reads (alpha.weighting_windows, alpha.target_gathers), with the
        sensors' TSDFs when the net reads them."""
        if self.tsdf_input:
            tsdf = self.store.views("tsdf0", "tsdf1")
        else:
            tsdf = [np.zeros(0, np.int16), np.zeros(0, np.int16)]  # float16 bits, as the pools
        return (*self.store.views("feat0", "weight0", "feat1", "weight1"), *tsdf, self.tsdf_scale)


def surface_windows(evaluator: AlphaEvaluator, *, batch_blocks: int = 64) -> Iterator[torch.Tensor]:
    """G's float32 input windows (B x C x 12^3, channels last) of every block in the grid that holds
    voxels alpha matters for ("surface"), batch by batch: what int8 calibration measures G on."""
    slots = np.arange(evaluator.store.grid.n_blocks)
    for start in range(0, len(slots), batch_blocks):
        neighbours = evaluator.store.neighbours(slots[start:start + batch_blocks])
        holds = evaluator.holds_surface(neighbours)
        if holds.any():
            yield torch.from_numpy(evaluator.windows(neighbours[holds])).permute(0, 4, 1, 2, 3)


def weighting_net_flops(net: Any, *, layer_1_positions: int, voxels: int, inputs: int) -> int:
    """The weighting net's FLOPs (2 per multiply-add) for `voxels` outputs whose first layer ran at
    layer_1_positions positions on `inputs` values each."""
    hidden_1, hidden_2 = net.conv1.out_channels, net.conv2.out_channels
    return 2 * (layer_1_positions * inputs * hidden_1 + voxels * (27 * hidden_1 * hidden_2 + hidden_2))
