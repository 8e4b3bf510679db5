"""Image features: the original's "ResNet13" (paper: Instruction and Image Embedding, Fig. "ResNet").

A 3x3 stride-2 convolution (3 -> C_f), six residual blocks [strided s2, plain, strided s2, plain, strided s1,
plain] and a final InstanceNorm: 13 convolutions, all C_f = 32 channels, downscale 8, so a 256x144 image gives
an 18x32 feature map. Each image is first standardised by its own mean and standard deviation (one scalar each).

Speed (docs/model.md): the network runs in channels-last memory format when `channels_last` is set, except while
it trains on the CPU (train mode there keeps the weights and activations in NCHW: PyTorch's channels-last GroupNorm
backward is several times slower than its NCHW one at training scale); a uint8 (N, H, W, 3) image batch is already
channels-last once permuted, so no copy is made on the way in. The same maths in either format. With
`inference_bf16`, eval-mode forwards run in bfloat16 autocast (training always runs in float32); the features
come out as float32 either way.
"""

from __future__ import annotations

import torch
import torch.nn as nn

from gsmn.model.blocks import ResidualBlock, conv3x3, instance_norm

DOWNSCALE = 8


def standardise(images: torch.Tensor) -> torch.Tensor:
    """uint8 or float images (N, H, W, 3) -> float (N, 3, H, W), each image to zero mean and unit std."""
    x = images.float()  # (N, H, W, 3)
    flat = x.reshape(x.shape[0], -1)
    # Separate mean and var reductions over contiguous memory: ~4x faster than std_mean on CPU.
    mean = flat.mean(dim=1).view(-1, 1, 1, 1)
    std = flat.var(dim=1).sqrt().view(-1, 1, 1, 1)
    return ((x - mean) / (std + 1e-5)).permute(0, 3, 1, 2)  # (N, 3, H, W), channels-last strides


class ResNet13(nn.Module):
    """Standardised images (N, 3, H, W) -> features (N, C_f, H/8, W/8)."""

    def __init__(self, channels: int = 32, slope: float = 0.01, channels_last: bool = True,
                 inference_bf16: bool = False):
        super().__init__()
        self.conv = conv3x3(3, channels, 2, slope)
        self.blocks = nn.Sequential(
            ResidualBlock(channels, 2, slope=slope),
            ResidualBlock(channels, 1, slope=slope),
            ResidualBlock(channels, 2, slope=slope),
            ResidualBlock(channels, 1, slope=slope),
            ResidualBlock(channels, 1, pooled_skip=True, slope=slope),
            ResidualBlock(channels, 1, slope=slope),
        )
        self.channels_last = channels_last
        self.inference_bf16 = inference_bf16
        self.train(self.training)

    def memory_format(self) -> torch.memory_format:
        """Channels-last where `channels_last` is set, but for training on the CPU."""
        cpu = next(self.parameters()).device.type == "cpu"
        return torch.channels_last if self.channels_last and not (self.training and cpu) else torch.contiguous_format

    def train(self, mode: bool = True) -> ResNet13:
        """Also puts the weights in the memory format of the mode (a copy where it changes; the same Parameters, so
        an optimizer holding them goes on). Never as inference tensors, even when called under inference_mode. A
        model moved to another device keeps its format until the next train() or eval()."""
        super().train(mode)
        memory_format = self.memory_format()
        if not self.conv.weight.is_contiguous(memory_format=memory_format):  # every training step calls train()
            with torch.inference_mode(False):
                self.to(memory_format=memory_format)
        return self

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = images.contiguous(memory_format=self.memory_format())
        if self.inference_bf16 and not self.training:
            with torch.autocast(x.device.type, dtype=torch.bfloat16):
                return instance_norm(self.blocks(self.conv(x))).float().contiguous()
        return instance_norm(self.blocks(self.conv(x))).contiguous()
