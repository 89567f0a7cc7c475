"""The two learned parts of SenFuNet: a 2D feature net per sensor and the 3D weighting net G.

Architectures follow the paper (section 3 b, c) and the released checkpoints:
- FeatureNet: 6 residual blocks of conv3x3-tanh-conv3x3-tanh with 4 channels, zero padding;
  input depth (1 channel) or depth + RGB (4 channels); per-pixel L2 normalisation; the raw
  depth appended -> 5 channels.
- WeightingNet: Conv3d 12->32 k3, ReLU, Conv3d 32->16 k3, ReLU, Conv3d 16->1 k1, sigmoid.
  The paper pads with replication; on sparse blocks we evaluate the same weights without
  padding on a 2-voxel halo (see `alpha_on_blocks`), which equals the padded whole-grid
  evaluation wherever the grid has a margin of unobserved (all-zero) voxels.
"""
from __future__ import annotations

import functools
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from .errors import InputError
from .feature_conv import feature_net_forward, feature_net_rows

N_FEATURE_CHANNELS = 4  # learned channels; the depth is appended to make n = 5
N_FEATURES = N_FEATURE_CHANNELS + 1
N_RESIDUAL_BLOCKS = 6
WEIGHTING_HALO = 2  # receptive field 5^3: alpha depends on inputs within 2 voxels
DEFAULT_WEIGHTS = Path(__file__).resolve().parent / "weights" / "tof_stereo.pt"
# shipped weights files by name (the `weights` parameter and `--weights` accept these names or a path)
NAMED_WEIGHTS = {"default": DEFAULT_WEIGHTS, "paper": DEFAULT_WEIGHTS.with_name("tof_stereo_paper.pt")}


@dataclass(frozen=True)
class DeviceChoice:
    device: torch.device  # where the networks run
    fallback_reason: str | None = None  # set when this is not the device asked for: say it to the user


def choose_device(requested: str, *, cpu_fallback: bool) -> DeviceChoice:
    """The one decision of the torch device the networks run on (the grids stay in CPU memory).

    requested: a torch device name, "cpu", "cuda" or "cuda:N". When CUDA is asked for and there is
    none: the CPU with a fallback_reason when cpu_fallback (the node, whose parameter promises a
    fallback), else InputError (the library: a caller that names a device gets it or an error).
    """
    try:
        device = torch.device(requested)
    except (RuntimeError, TypeError) as err:
        raise InputError(f"device '{requested}' is not a torch device name; use 'cpu' or 'cuda'") from err
    if device.type != "cuda" or torch.cuda.is_available():
        return DeviceChoice(device)
    if not cpu_fallback:
        raise InputError(f"device '{requested}' requested but CUDA is not available; use device 'cpu'")
    return DeviceChoice(torch.device("cpu"), f"device '{requested}' requested but CUDA is not available: using cpu")


def _conv_tanh(conv: nn.Conv2d, x: torch.Tensor) -> torch.Tensor:
    """tanh(conv(x)). Without autograd as 2 sigmoid(2 conv(x)) - 1, with the 2 in the weights (scaling
    by a power of 2 is exact): torch's CPU tanh costs several times its sigmoid, and in the feature
    nets as much as the 4-channel convolutions themselves. Equal to tanh within float32 rounding.
    Computed in x's dtype (float32, or bfloat16: `FeatureNet.compute_dtype`)."""
    if torch.is_grad_enabled():
        return torch.tanh(conv(x))
    bias = None if conv.bias is None else (conv.bias * 2).to(x.dtype)
    return torch.sigmoid(F.conv2d(x, (conv.weight * 2).to(x.dtype), bias, padding=conv.padding)).mul_(2).sub_(1)


class FeatureNet(nn.Module):
    """Per-sensor 2D feature extractor: depth (+RGB) image -> 5 features per pixel."""

    def __init__(self, uses_rgb: bool) -> None:
        super().__init__()
        self.uses_rgb = uses_rgb
        # arithmetic of the convolutions in inference (autograd always runs float32): bfloat16 runs
        # faster on CPUs with native bfloat16 instructions; the output stays float32
        self.compute_dtype = torch.float32
        in_channels = 4 if uses_rgb else 1
        c = N_FEATURE_CHANNELS
        self.blocks = nn.ModuleList(
            nn.ModuleList([nn.Conv2d(in_channels if i == 0 else c, c, 3, padding=1), nn.Conv2d(c, c, 3, padding=1)])
            for i in range(N_RESIDUAL_BLOCKS)
        )

    def forward(self, depth_m: torch.Tensor, rgb01: torch.Tensor | None = None) -> torch.Tensor:
        """depth_m: Bx1xHxW (invalid pixels 0); rgb01: Bx3xHxW in 0..1 -> Bx5xHxW."""
        if not self.uses_rgb:
            x = depth_m
        elif rgb01 is None:
            raise InputError("this feature net takes depth and colour: pass rgb01 (Bx3xHxW in 0..1)")
        else:
            x = torch.cat([depth_m, rgb01], dim=1)
        if not torch.is_grad_enabled() and self.compute_dtype == torch.float32 and x.device.type == "cpu":
            x = self._conv_stack_kernel(x)
        else:
            x = self._conv_stack_torch(x)
        # per-pixel L2 normalisation, written out: F.normalize's strided norm over dim 1 is slower here
        x = x / torch.sqrt((x * x).sum(dim=1, keepdim=True)).clamp(min=1e-8)
        return torch.cat([x, depth_m], dim=1)

    def conv_arrays(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each convolution's (weight, bias) as float32 arrays, in order (`feature_conv`'s kernels)."""
        return [(conv.weight.detach().float().numpy(), cast(torch.Tensor, conv.bias).detach().float().numpy())
                for conv in self._convs()]

    def _convs(self) -> list[nn.Conv2d]:
        return [cast(nn.Conv2d, conv) for block in self.blocks for conv in cast(nn.ModuleList, block)]

    def _conv_stack_kernel(self, x: torch.Tensor) -> torch.Tensor:
        """The residual conv-tanh stack in float32 inference on the CPU: `feature_conv`'s kernel, image
        by image."""
        convs = self.conv_arrays()
        return torch.stack([torch.from_numpy(feature_net_forward(convs, image.float().contiguous().numpy()))
                            for image in x])

    def _conv_stack_torch(self, x: torch.Tensor) -> torch.Tensor:
        """The residual conv-tanh stack with torch's convolutions (training, bfloat16, GPUs)."""
        # channels last: oneDNN's 4-channel convolutions are faster in that layout on the CPU. A
        # 1-channel input is laid out the same either way, so the first output is converted too
        # (else the depth-only net stays in the slower layout throughout).
        x = x.contiguous(memory_format=torch.channels_last)
        if not torch.is_grad_enabled():
            x = x.to(self.compute_dtype)
        previous = None
        for block in self.blocks:
            conv_a, conv_b = cast(tuple[nn.Conv2d, nn.Conv2d], tuple(cast(nn.ModuleList, block)))
            x = _conv_tanh(conv_a, x).contiguous(memory_format=torch.channels_last)
            x = _conv_tanh(conv_b, x)
            if previous is not None:  # each block's output is added to the next block's output
                x = x + previous
            previous = x
        return x.to(torch.float32).contiguous()


def pixel_feature_rows(net: nn.Module, depth_m: np.ndarray, rgb: np.ndarray | None = None) -> np.ndarray:
    """A feature net's inference on one frame: depth_m (H, W) float32 metres (invalid pixels 0), rgb
    (H, W, 3) uint8 or None (black where the net takes colour) -> (H*W, 5) float32, pixel v * W + u's
    row of its output. For a FeatureNet on the CPU in float32 the kernel of `feature_conv` writes the
    rows directly; any other module with FeatureNet's forward (say an ablation's) runs that."""
    device = next(iter(net.parameters()), torch.empty(0)).device
    if isinstance(net, FeatureNet) and device.type == "cpu" and net.compute_dtype == torch.float32:
        return feature_net_rows(net.conv_arrays(), depth_m.astype(np.float32, copy=False),
                                rgb if net.uses_rgb else None)
    depth = torch.from_numpy(depth_m).float().to(device)[None, None]
    rgb01 = None
    if net.uses_rgb:
        rgb01 = (torch.zeros((1, 3, *depth_m.shape), device=device) if rgb is None
                 else torch.from_numpy(rgb).to(device).permute(2, 0, 1)[None].float() / 255.0)
    with torch.inference_mode():
        out = net(depth, rgb01)[0]
    return np.ascontiguousarray(out.reshape(out.shape[0], -1).T.cpu().numpy(), np.float32)


def _fused_conv_relu(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """oneDNN's convolution with its ReLU fused (the op torch's own compiler emits): no padding, stride 1."""
    return torch.ops.mkldnn._convolution_pointwise(x, weight, bias, [0, 0, 0], [1, 1, 1], [1, 1, 1], 1, "relu", [],
                                                   "")


@functools.cache
def _fused_conv_relu_works(dtype: torch.dtype) -> bool:
    """Whether this torch has `_fused_conv_relu` for 3D CPU tensors of `dtype` and it gives what the
    two steps give, on a small probe."""
    if not torch.backends.mkldnn.is_available() or not hasattr(torch.ops.mkldnn, "_convolution_pointwise"):
        return False
    generator = torch.Generator().manual_seed(0)
    # laid out as the scheduler's windows are (channels last), the layout the fused kernel must handle
    x = torch.randn(2, 6, 6, 6, 5, generator=generator).to(dtype).permute(0, 4, 1, 2, 3)
    weight, bias = torch.randn(3, 5, 3, 3, 3, generator=generator).to(dtype), torch.randn(3).to(dtype)
    try:
        with torch.inference_mode():
            got = _fused_conv_relu(x, weight, bias)
            want = F.conv3d(x, weight, bias).relu_()
    except Exception:  # a private op: whatever way it fails on this torch or CPU, the two steps serve
        return False
    return bool(torch.allclose(got.float(), want.float(), rtol=1e-2, atol=1e-2))


def conv3d_relu(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """relu(conv3d(x, weight, bias)), no padding, stride 1, for inference: on the CPU one oneDNN call
    with the ReLU fused where torch provides it (the ReLU as a separate pass over the output costs
    a third of the convolution), else the convolution and an in-place ReLU."""
    if x.device.type == "cpu" and _fused_conv_relu_works(x.dtype):
        return _fused_conv_relu(x, weight, bias)
    return F.conv3d(x, weight, bias).relu_()


class WeightingNet(nn.Module):
    """G: per-voxel [F_1, tanh(W_1), F_2, tanh(W_2)] (12 channels) -> sensor weighting alpha.

    tsdf_input (a departure from the paper, off by default): the sensors' TSDF values, scaled by
    2 / band to -1..1, are appended as n_sensors more channels ([..., V_1, V_2]: 14 channels)."""

    def __init__(self, n_sensors: int = 2, tsdf_input: bool = False) -> None:
        super().__init__()
        self.tsdf_input = bool(tsdf_input)
        in_channels = n_sensors * (N_FEATURES + 1) + (n_sensors if tsdf_input else 0)
        self.conv1 = nn.Conv3d(in_channels, 32, 3)
        self.conv2 = nn.Conv3d(32, 16, 3)
        self.conv3 = nn.Conv3d(16, 1, 1)

    def forward(self, x: torch.Tensor, pad: bool = True) -> torch.Tensor:
        """x: BxCxDxHxW -> alpha Bx1xDxHxW (pad=True, the paper's replicate padding)
        or Bx1x(D-4)x(H-4)x(W-4) (pad=False, for halo-padded sparse blocks)."""
        for conv in (self.conv1, self.conv2):
            if pad:
                x = F.pad(x, (1, 1, 1, 1, 1, 1), mode="replicate")
            # in inference, in place: a second large tensor per layer costs more than the ReLU itself
            x = F.relu(conv(x), inplace=not torch.is_grad_enabled())
        return torch.sigmoid(self.conv3(x))

    @torch.inference_mode()
    def infer(self, x: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """forward(x, pad=False) computed in `dtype` (inputs and weights cast, as autocast would),
        with each convolution's ReLU fused into it (`conv3d_relu`); alpha as float32."""
        x = x.to(dtype)
        for conv in (self.conv1, self.conv2):
            x = conv3d_relu(x, conv.weight.to(dtype), cast(torch.Tensor, conv.bias).to(dtype))
        return torch.sigmoid(F.conv3d(x, self.conv3.weight.to(dtype), cast(torch.Tensor, self.conv3.bias).to(dtype))
                             ).float()


def weighting_input(features: list[torch.Tensor], weights: list[torch.Tensor],
                    tsdfs: list[torch.Tensor] | None = None, band_m: float = 0.1) -> torch.Tensor:
    """Concatenate [F_i, tanh(W_i)] over sensors along the last axis: (..., 5) + (...) -> (..., 12);
    with tsdfs (WeightingNet.tsdf_input), then [V_i * 2 / band_m] over sensors: (..., 14)."""
    parts = []
    for feature, weight in zip(features, weights):
        parts += [feature, torch.tanh(weight).unsqueeze(-1)]
    if tsdfs is not None:
        parts += [(tsdf * (2.0 / band_m)).unsqueeze(-1) for tsdf in tsdfs]
    return torch.cat(parts, dim=-1)


def make_networks(sensor_uses_rgb: tuple[bool, ...], seed: int = 0,
                  tsdf_input: bool = False) -> tuple[nn.ModuleList, WeightingNet]:
    """Freshly initialised (untrained) networks, reproducible from `seed`."""
    generator_state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    try:
        feature_nets = nn.ModuleList(FeatureNet(uses_rgb) for uses_rgb in sensor_uses_rgb)
        weighting_net = WeightingNet(len(sensor_uses_rgb), tsdf_input)
    finally:
        torch.random.set_rng_state(generator_state)
    return feature_nets, weighting_net


def save_weights(path: str | Path, sensors: tuple[str, ...], feature_nets: nn.ModuleList, weighting_net: WeightingNet,
                 meta: dict | None = None) -> None:
    state = {
        "sensors": list(sensors),
        "sensor_uses_rgb": [net.uses_rgb for net in feature_nets],
        "feature_nets": [net.state_dict() for net in feature_nets],
        "weighting_net": weighting_net.state_dict(),
        "weighting_tsdf_input": bool(getattr(weighting_net, "tsdf_input", False)),
        "meta": meta or {},
    }
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    torch.save(state, path)


def weights_tsdf_input(path: str | Path) -> bool:
    """Whether a weights file's weighting net takes the sensors' TSDFs as inputs (False when unknown)."""
    try:
        state = torch.load(Path(path), map_location="cpu", weights_only=True)
        return bool(state.get("weighting_tsdf_input", False))
    except Exception:
        return False


def load_weights(path: str | Path, feature_nets: nn.ModuleList, weighting_net: WeightingNet) -> dict:
    """Load a weights file into existing networks; returns its metadata. Raises ValueError on mismatch."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"weights file {path} does not exist; pass a trained .pt file or weights=None for random init")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 (torch's words advise loading it unsafely, or say only "101")
        if not zipfile.is_zipfile(path):
            reason = "not a zip archive, as torch.save writes"
        elif "Weights only load failed" in str(err):
            reason = "it holds Python objects beyond tensors and plain values"
        else:
            reason = str(err).strip().splitlines()[0][:200] if str(err).strip() else type(err).__name__
        raise InputError(f"{path} is not a SenFuNet weights file ({reason}); pass default, paper, none or a .pt file "
                         "that senfunet train wrote") from None
    try:
        if not isinstance(state, dict) or "feature_nets" not in state:
            raise InputError(f"{path} is a torch file but not SenFuNet weights (no feature_nets); pass default, "
                             "paper, none or a .pt file that senfunet train wrote")
        if len(state["feature_nets"]) != len(feature_nets):
            raise InputError(f"{path} holds {len(state['feature_nets'])} feature nets, "
                             f"the engine has {len(feature_nets)} sensors")
        trained_rgb = [bool(uses_rgb) for uses_rgb in state.get("sensor_uses_rgb") or []]
        engine_rgb = [bool(net.uses_rgb) for net in feature_nets]
        if trained_rgb and trained_rgb != engine_rgb:
            # the nets are per position (sensor 1 is the one alpha weights): sensors listed in another order, or
            # another choice of colour sensors, would otherwise fail on a tensor shape deep in torch
            def inputs(flags: list[bool]) -> str:
                return ", ".join(f"sensor {i + 1} {'depth and colour' if rgb else 'depth only'}"
                                 for i, rgb in enumerate(flags))

            raise InputError(f"{path} was trained with {inputs(trained_rgb)} (its sensors, in order: "
                             f"{state.get('sensors')}), this engine has {inputs(engine_rgb)}: list the sensors in "
                             "the weights' order and give colour to the same ones (the node's sensors and "
                             "rgb_sensors), or train weights for this set-up")
        for net, net_state in zip(feature_nets, state["feature_nets"]):
            net.load_state_dict(net_state)
        weighting_net.load_state_dict(state["weighting_net"])
    except InputError:
        raise
    except Exception as err:  # corrupt file, wrong architecture
        raise InputError(f"cannot load weights from {path}: {err}") from err
    return {"sensors": state.get("sensors"), "sensor_uses_rgb": state.get("sensor_uses_rgb"), **state.get("meta", {})}


def resolve_weights(name_or_path: str | Path | None) -> Path | None:
    """A shipped weights name ("default": 14-input G; "paper": the paper-exact 12-input G) or a
    path -> the file's path; None or "none" -> None (untrained networks). InputError when the file
    does not exist."""
    from .errors import InputError

    if name_or_path is None or str(name_or_path).lower() == "none":
        return None
    path = NAMED_WEIGHTS.get(str(name_or_path), Path(name_or_path))
    if not Path(path).is_file():
        names = ", ".join(f"{k} ({v.name})" for k, v in NAMED_WEIGHTS.items())
        raise InputError(f"weights {name_or_path!r}: no such file; pass a .pt path or one of: {names}, none")
    return Path(path)
