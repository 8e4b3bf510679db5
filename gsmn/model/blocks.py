"""Residual blocks shared by the ResNet and the controller (paper: Fig. "ResNet architecture"; original code).

Plain block:   x + LeakyReLU(conv(IN(LeakyReLU(conv(IN(x))))))
Strided block: AvgPool(3, s, pad 1)(x) + the same path with the first conv strided by s.
3x3 convolutions, InstanceNorm without affine parameters, Kaiming init with zero bias.

InstanceNorm is computed as GroupNorm with one group per channel: the same normalisation, and PyTorch's
GroupNorm kernel is several times faster than its InstanceNorm (a reshaped BatchNorm) on CPU. Its
channels-last kernel is slow on small maps (about 100 us vs 10 us at 32x18x32, batch 1), so small
channels-last maps are copied to NCHW first (measurements in docs/model.md).

The AvgPool skip (3x3, zero padding counted, so always a ninth of a 3x3 sum) is computed, where autograd tracks
it, as a depthwise convolution with fixed weights 1/9: the same maths, and on CPU its forward and backward take
about a fifth of PyTorch's avg_pool2d's at training scale. Without gradients (inference, batch 1, channels-last)
avg_pool2d is the faster one and stays (docs/model.md, "Speed").
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

EPS = 1e-5


SMALL_MAP = 1024  # H * W at or below which channels-last maps are normalised in NCHW


def instance_norm(x: torch.Tensor) -> torch.Tensor:
    """Per-sample, per-channel normalisation over space, no affine: (N, C, H, W) -> same."""
    if x.shape[-1] * x.shape[-2] <= SMALL_MAP and not x.is_contiguous():
        x = x.contiguous()
    return F.group_norm(x, x.shape[1], eps=EPS)


class AvgPool3x3(nn.Module):
    """AvgPool2d(3, stride, padding=1), the padding counted; as a depthwise convolution with weights 1/9 where
    autograd tracks it (faster to train on CPU), as avg_pool2d where not."""

    def __init__(self, stride: int):
        super().__init__()
        self.stride = stride

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not (x.requires_grad and torch.is_grad_enabled()):
            return F.avg_pool2d(x, 3, self.stride, 1)
        weight = torch.full((x.shape[1], 1, 3, 3), 1 / 9, dtype=x.dtype, device=x.device)
        return F.conv2d(x, weight, stride=self.stride, padding=1, groups=x.shape[1])

    def extra_repr(self) -> str:
        return f"stride={self.stride}"


def conv3x3(channels_in: int, channels_out: int, stride: int, slope: float) -> nn.Conv2d:
    conv = nn.Conv2d(channels_in, channels_out, 3, stride=stride, padding=1)
    nn.init.kaiming_normal_(conv.weight, a=slope, nonlinearity="leaky_relu")
    nn.init.zeros_(conv.bias)
    return conv


class ResidualBlock(nn.Module):
    """A plain (stride 1, identity skip) or strided (AvgPool skip) residual block."""

    def __init__(self, channels: int, stride: int = 1, pooled_skip: bool | None = None, slope: float = 0.01):
        super().__init__()
        self.conv1 = conv3x3(channels, channels, stride, slope)
        self.conv2 = conv3x3(channels, channels, 1, slope)
        self.slope = slope
        # The original's "strided" blocks pool the skip path even at stride 1 (a 3x3 blur).
        pooled = stride > 1 if pooled_skip is None else pooled_skip
        self.skip = AvgPool3x3(stride) if pooled else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # In place on the convolutions' fresh outputs (autograd keeps LeakyReLU's output, which is all it needs).
        y = F.leaky_relu(self.conv1(instance_norm(x)), self.slope, inplace=True)
        y = F.leaky_relu(self.conv2(instance_norm(y)), self.slope, inplace=True)
        return self.skip(x) + y
