"""The networks' device decision and input checks."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from senfunet_core.engine import EngineConfig, SenFuNet
from senfunet_core.errors import InputError
from senfunet_core.networks import FeatureNet, choose_device


def test_cpu_is_chosen_as_asked_without_a_reason():
    choice = choose_device("cpu", cpu_fallback=True)
    assert choice.device == torch.device("cpu") and choice.fallback_reason is None


def test_missing_cuda_falls_back_only_where_a_fallback_is_promised(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    choice = choose_device("cuda:0", cpu_fallback=True)
    assert choice.device == torch.device("cpu")
    assert "cuda:0" in choice.fallback_reason and "using cpu" in choice.fallback_reason
    with pytest.raises(InputError, match="CUDA is not available"):
        choose_device("cuda", cpu_fallback=False)
    with pytest.raises(InputError, match="CUDA is not available"):  # the engine never falls back silently
        SenFuNet(EngineConfig(device="cuda"), weights=None)


def test_a_device_name_torch_does_not_know_is_an_input_error():
    with pytest.raises(InputError, match="not a torch device name"):
        choose_device("gpu0", cpu_fallback=True)


def test_colour_feature_net_without_colour_says_so():
    net = FeatureNet(uses_rgb=True)
    with pytest.raises(InputError, match="rgb01"):
        net(torch.zeros(1, 1, 8, 8))
    assert net(torch.zeros(1, 1, 8, 8), torch.zeros(1, 3, 8, 8)).shape == (1, 5, 8, 8)


def test_the_device_is_decided_in_networks_only():
    """One device decision: no other module of the packages asks torch whether CUDA is there."""
    from pathlib import Path

    repo = Path(__file__).resolve().parents[2]
    askers = sorted(str(path.relative_to(repo)) for package in ("senfunet_core", "senfunet_ros")
                    for path in (repo / package).rglob("*.py") if "cuda.is_available" in path.read_text())
    assert askers == ["senfunet_core/networks.py"]


@pytest.mark.parametrize("uses_rgb", [False, True])
def test_feature_net_inference_equals_its_training_forward(uses_rgb: bool, monkeypatch) -> None:
    """Without autograd, in float32 on the CPU, the feature net runs feature_conv's kernel (its own
    convolutions and tanh): the same features within float32 rounding as the autograd forward, which
    uses torch's convolutions and torch.tanh; image by image in a batch."""
    from senfunet_core import networks
    from senfunet_core.feature_conv import feature_net_forward

    feature_nets, weighting_net = networks.make_networks(
        (False, True), tsdf_input=networks.weights_tsdf_input(networks.DEFAULT_WEIGHTS))
    networks.load_weights(networks.DEFAULT_WEIGHTS, feature_nets, weighting_net)  # the shipped weights
    net = feature_nets[int(uses_rgb)]
    g = torch.Generator().manual_seed(0)
    depth = torch.rand(2, 1, 48, 40, generator=g) * 3
    depth[..., :5, :] = 0.0  # invalid pixels, as the engine passes them
    rgb = torch.rand(2, 3, 48, 40, generator=g) if uses_rgb else None
    with torch.enable_grad():
        reference = net(depth, rgb).detach()
    images = []
    monkeypatch.setattr(networks, "feature_net_forward",
                        lambda convs, image: images.append(image.shape) or feature_net_forward(convs, image))
    with torch.inference_mode():
        fast = net(depth, rgb)
    assert images == [(4 if uses_rgb else 1, 48, 40)] * 2  # the kernel ran, once per image
    assert fast.shape == reference.shape == (2, 5, 48, 40)
    assert not torch.equal(fast, torch.zeros_like(fast))
    # float32 summed in another order than oneDNN's (with FMA or not, as the CPU has it); the per-pixel
    # normalisation magnifies that rounding where a pixel's features are small
    torch.testing.assert_close(fast, reference, rtol=0, atol=1e-4)


@pytest.mark.parametrize("uses_rgb", [False, True])
def test_pixel_feature_rows_are_the_training_forward_per_pixel(uses_rgb: bool) -> None:
    """The engine's per-frame features (`pixel_feature_rows`: the kernel writes normalised rows and
    the depth) equal the autograd forward's output laid out one row per pixel, colour from uint8
    included; a module that is not a FeatureNet (an ablation's) runs its own forward."""
    from senfunet_core import networks

    feature_nets, weighting_net = networks.make_networks(
        (False, True), tsdf_input=networks.weights_tsdf_input(networks.DEFAULT_WEIGHTS))
    networks.load_weights(networks.DEFAULT_WEIGHTS, feature_nets, weighting_net)
    net = feature_nets[int(uses_rgb)]
    rng = np.random.default_rng(3)
    depth = (rng.random((48, 40)) * 3).astype(np.float32)
    depth[:5] = 0.0
    rgb = rng.integers(0, 256, (48, 40, 3), dtype=np.uint8)
    with torch.enable_grad():
        reference = net(torch.from_numpy(depth)[None, None],
                        torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255.0 if uses_rgb else None).detach()
    want = reference[0].reshape(5, -1).T.numpy()
    rows = networks.pixel_feature_rows(net, depth, rgb)
    assert rows.shape == (48 * 40, 5) and rows.dtype == np.float32
    np.testing.assert_allclose(rows, want, rtol=0, atol=1e-5)
    assert np.array_equal(rows[:, 4], depth.ravel())

    class Wrapped(torch.nn.Module):  # FeatureNet's forward, but not a FeatureNet
        def __init__(self) -> None:
            super().__init__()
            self.inner, self.uses_rgb = net, net.uses_rgb

        def forward(self, depth_m: torch.Tensor, rgb01: torch.Tensor | None = None) -> torch.Tensor:
            return self.inner(depth_m, rgb01)

    np.testing.assert_allclose(networks.pixel_feature_rows(Wrapped(), depth, rgb), want, rtol=0, atol=1e-5)


@pytest.mark.parametrize("n_out", [1, 3, 4, 6])
def test_feature_conv_kernel_equals_torch_for_any_number_of_output_channels(n_out: int) -> None:
    """The kernel takes output channels in groups of four: those beyond the last group run alone."""
    from senfunet_core.feature_conv import conv3x3_tanh

    g = torch.Generator().manual_seed(n_out)
    x = torch.rand(3, 20, 24, generator=g) - 0.5
    weight, bias = torch.randn(n_out, 3, 3, 3, generator=g), torch.randn(n_out, generator=g)
    residual = torch.randn(n_out, 22, 26, generator=g)
    expected = torch.tanh(torch.nn.functional.conv2d(x[None], weight, bias, padding=1))[0] + residual[:, 1:-1, 1:-1]
    out = np.zeros((n_out, 22, 26), np.float32)
    conv3x3_tanh(torch.nn.functional.pad(x, (1, 1, 1, 1)).numpy(), weight.numpy(), bias.numpy(), residual.numpy(), out)
    torch.testing.assert_close(torch.from_numpy(out[:, 1:-1, 1:-1]), expected, rtol=0, atol=1e-5)
    assert not out[:, 0].any() and not out[:, :, 0].any()  # the border untouched


@pytest.mark.parametrize("fused", [True, False])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_weighting_net_inference_equals_its_forward(dtype: torch.dtype, fused: bool, monkeypatch) -> None:
    """The scheduler's path (`WeightingNet.infer`: ReLUs fused into the convolutions where torch has
    oneDNN's fused kernel, else conv and in-place ReLU) gives the forward's alpha on halo-padded
    windows: float32 as the plain forward, bfloat16 as the forward under autocast."""
    from senfunet_core import networks
    from senfunet_core.networks import WeightingNet

    if not fused:
        monkeypatch.setattr(networks, "_fused_conv_relu_works", lambda dtype: False)
    torch.manual_seed(0)
    net = WeightingNet(tsdf_input=True).eval()
    x = torch.randn(3, 14, 12, 12, 12).contiguous(memory_format=torch.channels_last_3d)
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=dtype == torch.bfloat16):
        want = net(x, pad=False).float()
    got = net.infer(x, dtype)
    assert got.shape == want.shape == (3, 1, 8, 8, 8)
    tolerance = 1e-5 if dtype == torch.float32 else 1e-2
    torch.testing.assert_close(got, want, rtol=0, atol=tolerance)
    assert float(want.std()) > 0.01  # alpha varies: the comparison has something to compare
