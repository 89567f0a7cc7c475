"""The weighting net G in 8-bit integer arithmetic (oneDNN's int8 convolutions), for the live node.

G's two 3x3x3 convolutions take most of its time; on a CPU without bfloat16 units their int8
form runs faster than float32 (`bench/engine.py` measures G both ways). What is quantized:
- the weights: per output channel, symmetric, 8 bits;
- G's input: per channel its value range mapped to -1..1 (folded into the first layer's weights and
  bias), then 8 bits with one step 1/127, written so by the windows' kernel (`alpha.weighting_windows`);
- the two hidden layers' outputs (after the ReLU): 0 to a maximum measured once per weights file
  on the bundled sample (`Int8Calibration`; `scripts/calibrate_int8.py`, and `senfunet train` for
  the weights it writes), 8 bits. A value above it saturates there.
The 1x1 output layer and the sigmoid stay float32. The fused mesh stays close to float32's
(`test_equivalence.py`); replay always runs G in float32.

oneDNN's int8 convolutions come through torch's quantized tensors (`torch.ao.nn.intrinsic.quantized`),
which torch marks deprecated; `int8_available` checks on a probe that they work on this torch and CPU.
"""
from __future__ import annotations

import functools
import hashlib
import json
import warnings
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import cast

import numpy as np
import torch
import torch.nn.functional as F

from .alpha import window_value_ranges
from .grid import INT8_STEP, INT8_ZERO
from .networks import N_FEATURES, WeightingNet

# torch warns of its quantized tensors' deprecation on first use; the pinned torch has them (`int8_available`)
warnings.filterwarnings("ignore", message=r".*quantize_per_tensor.*deprecated", category=UserWarning)


@dataclass(frozen=True)
class Int8Calibration:
    """The largest outputs of G's two hidden layers (after the ReLU) on the calibration data, for the
    weights file whose SHA-256 this names."""

    weights_sha256: str
    layer_1_max: float
    layer_2_max: float
    calibrated_on: str = ""  # what the maxima were measured on

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(asdict(self), indent=2) + "\n")


def calibration_path(weights: str | Path) -> Path:
    """Where the int8 calibration of a weights file lives: beside it, `<name>.int8.json`."""
    weights = Path(weights)
    return weights.with_name(weights.stem + ".int8.json")


def file_sha256(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def load_calibration(weights: str | Path) -> tuple[Int8Calibration | None, str]:
    """The calibration of this weights file, or None and why there is none."""
    path = calibration_path(weights)
    if not path.is_file():
        return None, f"no int8 calibration {path.name} beside the weights (make one with scripts/calibrate_int8.py)"
    try:
        calibration = Int8Calibration(**json.loads(path.read_text()))
    except (ValueError, TypeError) as err:
        return None, f"{path} is no int8 calibration ({err})"
    if calibration.weights_sha256 != file_sha256(weights):
        return None, f"{path} was measured for other weights than {Path(weights).name}; calibrate again"
    return calibration, ""


def calibrate(net: WeightingNet, windows: Iterable[torch.Tensor], *, weights_sha256: str, calibrated_on: str
              ) -> Int8Calibration:
    """The hidden layers' largest outputs over these input windows (B x C x 12^3 each, float32)."""
    layer_1_max = layer_2_max = 0.0
    with torch.inference_mode():
        for x in windows:
            hidden = F.conv3d(x.float(), net.conv1.weight, net.conv1.bias).relu_()
            layer_1_max = max(layer_1_max, float(hidden.max()))
            hidden = F.conv3d(hidden, net.conv2.weight, net.conv2.bias).relu_()
            layer_2_max = max(layer_2_max, float(hidden.max()))
    return Int8Calibration(weights_sha256, layer_1_max, layer_2_max, calibrated_on)


def input_ranges(net: WeightingNet, depth_max_m: tuple[float, ...]) -> np.ndarray:
    """Per input channel of G, the range its values lie in (C x 2, `alpha.window_value_ranges`), with
    the depths up to the sensors' largest depth_max_m (one range for both: the windows look depths
    up in one table)."""
    return window_value_ranges(N_FEATURES, with_tsdf=net.tsdf_input, depth_max_m=float(max(depth_max_m)))


class Int8WeightingNet:
    """G with its convolutions in int8 (see the module docstring); call it as `WeightingNet.infer`.
    Built from the net's weights as they are now: build it again when they change."""

    def __init__(self, net: WeightingNet, calibration: Int8Calibration, ranges: np.ndarray) -> None:
        """ranges: `input_ranges`, what G's inputs' 8-bit codes span."""
        import torch.ao.nn.intrinsic.quantized as nniq

        torch.backends.quantized.engine = "onednn"
        self.calibration = calibration
        self.depth_max_m = float(ranges[N_FEATURES - 1, 1])  # what the windows' depth codes span
        low, high = torch.from_numpy(ranges[:, 0]).float(), torch.from_numpy(ranges[:, 1]).float()
        self._centre = (0.5 * (low + high)).view(1, -1, 1, 1, 1)
        self._half = (0.5 * (high - low)).view(1, -1, 1, 1, 1)
        bias_1, bias_2, bias_3 = (cast(torch.Tensor, conv.bias) for conv in (net.conv1, net.conv2, net.conv3))
        self._layers = []
        with torch.no_grad():
            # x = centre + half x' (x' in -1..1): conv(x) = conv'(x') with W' = W half, b' = b + sum W centre
            weight_1 = net.conv1.weight * self._half
            bias_1 = bias_1 + (net.conv1.weight * self._centre).sum(dim=(1, 2, 3, 4))
            for weight, bias, out_max in ((weight_1, bias_1, calibration.layer_1_max),
                                          (net.conv2.weight, bias_2, calibration.layer_2_max)):
                scales = (weight.abs().amax(dim=(1, 2, 3, 4)) / 127.0).clamp(min=1e-12).double()
                zeros = torch.zeros(len(scales), dtype=torch.long)
                layer = nniq.ConvReLU3d(weight.shape[1], weight.shape[0], weight.shape[2])
                quantized = torch.quantize_per_channel(weight.detach().float(), scales, zeros, 0, torch.qint8)
                layer.set_weight_bias(quantized, bias.detach().float())
                layer.scale, layer.zero_point = max(out_max, 1e-6) / 255.0, 0
                self._layers.append(layer)
            self._out_weight = net.conv3.weight.detach().clone()
            self._out_bias = bias_3.detach().clone()

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """x: B x C x D x H x W (channels last, as the scheduler's windows), float32 values or their
        uint8 codes (`grid.as_stored` in this net's ranges) -> alpha B x 1 x (D-4) x (H-4) x (W-4)
        float32."""
        if x.dtype == torch.uint8:
            q = torch._make_per_tensor_quantized_tensor(x, INT8_STEP, INT8_ZERO)
        else:
            q = torch.quantize_per_tensor((x.float() - self._centre) / self._half, INT8_STEP, INT8_ZERO, torch.quint8)
        for layer in self._layers:
            q = layer(q)
        return torch.sigmoid(F.conv3d(q.dequantize(), self._out_weight, self._out_bias))


@functools.cache
def int8_available() -> bool:
    """Whether this torch has oneDNN's int8 3D convolutions and they compute what float32 does, to
    within 8-bit rounding, on a small probe."""
    try:
        if "onednn" not in torch.backends.quantized.supported_engines:
            return False
        generator = torch.Generator().manual_seed(0)
        net = WeightingNet(n_sensors=2)
        x = torch.rand(2, net.conv1.in_channels, 8, 8, 8, generator=generator)
        with torch.inference_mode():
            want = net.infer(x)
            calibration = calibrate(net, [x], weights_sha256="", calibrated_on="probe")
            got = Int8WeightingNet(net, calibration, np.array([[0.0, 1.0]] * net.conv1.in_channels))(x)
        return bool((got - want).abs().max() < 0.05)
    except Exception:  # the deprecated quantized ops: whatever way they fail here, float32 serves
        return False
