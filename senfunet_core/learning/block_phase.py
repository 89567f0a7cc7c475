"""The block phase (not the paper's training): G alone on whole blocks of integrated training grids."""
from __future__ import annotations

import numpy as np
import torch


def block_batch(data: list[dict[str, torch.Tensor]], size: int, mixed: bool,
                rng: np.random.Generator) -> dict[str, torch.Tensor]:
    """A batch of blocks for the block phase, drawn without replacement: from one random scene
    (mixed False), or uniformly from all scenes' blocks (mixed True; in scene order). data: per scene,
    tensors with the blocks along the first axis."""
    if not mixed:
        d = data[int(rng.integers(len(data)))]
        idx = torch.from_numpy(rng.choice(len(d["x"]), size=min(size, len(d["x"])), replace=False))
        return {k: v[idx] for k, v in d.items()}
    counts = np.array([len(d["x"]) for d in data])
    starts = np.concatenate([[0], np.cumsum(counts)])
    picks = np.sort(rng.choice(starts[-1], size=min(size, int(starts[-1])), replace=False))
    scene = np.searchsorted(starts, picks, side="right") - 1
    parts = [(d, torch.from_numpy(picks[scene == i] - starts[i])) for i, d in enumerate(data) if (scene == i).any()]
    return {k: torch.cat([d[k][idx] for d, idx in parts]) for k in data[0]}
