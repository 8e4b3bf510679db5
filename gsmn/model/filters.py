"""Language-conditioned filters (paper: Language Grounding and Goal Prediction; original code for the details).

Relevance (grounding): a 1x1 convolution whose kernel comes from the instruction,
    kernel = L2-normalise(act(W e + b)) reshaped to (3, C_f),   R = LeakyReLU(kernel * S)   (no conv bias).
Goal: two cascaded 3x3 convolutions whose kernels come from the instruction,
    [k1; k2] = act(W e + b), each L2-normalised, K1: 3 -> 3, K2: 3 -> 2,
    G = conv(K2, dilation 3)(InstanceNorm(LeakyReLU(conv(K1)(R)))).
act is the original code's sigmoid (`model.filter_activation = "sigmoid"`): every kernel weight is positive, so a
filter can only add channels, never subtract one from another. "none" is the paper's K = W e + b (signed), still
L2-normalised to keep the original's fixed scale. W ~ N(0, 0.001) and b = 0 at init: with the sigmoid every kernel
starts uniform (original code); without it every kernel starts as a random unit vector (docs/model.md).

Each sample has its own kernels. Inputs may carry extra leading dimensions after the batch, e.g. (B, T, C, H, W)
for a sequence sharing one instruction: the 1x1 filter is a batched matrix product, the 3x3 filters a grouped
convolution with one group per sample. Making the kernels (`kernels`) and applying them (`forward`) are apart:
the kernels depend on the instruction only, so a policy makes them once per episode (`InstructionKernels`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from gsmn.model.blocks import instance_norm


def _activate(x: torch.Tensor, activation: str) -> torch.Tensor:
    return torch.sigmoid(x) if activation == "sigmoid" else x


def _language_linear(embed_dim: int, out_features: int, init_std: float) -> nn.Linear:
    linear = nn.Linear(embed_dim, out_features)
    nn.init.normal_(linear.weight, 0.0, init_std)
    nn.init.zeros_(linear.bias)
    return linear


class RelevanceFilter(nn.Module):
    """Maps (B, ..., C_in, H, W) and sentence embeddings (B, E) -> relevance maps (B, ..., C_out, H, W)."""

    def __init__(self, embed_dim: int, channels_in: int, channels_out: int, init_std: float = 0.001,
                 slope: float = 0.01, activation: str = "none"):
        super().__init__()
        self.channels_in, self.channels_out, self.slope, self.activation = channels_in, channels_out, slope, activation
        self.linear = _language_linear(embed_dim, channels_in * channels_out, init_std)

    def kernels(self, sentence_embedding: torch.Tensor) -> torch.Tensor:
        """(B, C_out, C_in) unit-norm 1x1 kernels."""
        k = F.normalize(_activate(self.linear(sentence_embedding), self.activation), dim=-1)
        return k.view(-1, self.channels_out, self.channels_in)

    def forward(self, maps: torch.Tensor, kernels: torch.Tensor) -> torch.Tensor:
        """Maps (B, ..., C_in, H, W) through this filter's `kernels(e)` (B, C_out, C_in)."""
        B, lead, (H, W) = maps.shape[0], maps.shape[1:-3], maps.shape[-2:]
        k = kernels.view(B, *(1,) * len(lead), self.channels_out, self.channels_in)  # broadcast over lead dims
        out = torch.matmul(k, maps.flatten(-2))  # (B, ..., C_out, H*W); a batched einsum, with less overhead
        return F.leaky_relu(out.view(B, *lead, self.channels_out, H, W), self.slope)


class GoalFilter(nn.Module):
    """Relevance maps (B, ..., C_r, H, W) and sentence embeddings (B, E) -> goal maps (B, ..., C_g, H, W)."""

    def __init__(self, embed_dim: int, channels_in: int = 3, channels_out: int = 2, dilation: int = 3,
                 init_std: float = 0.001, slope: float = 0.01, activation: str = "none"):
        super().__init__()
        self.channels_in, self.channels_out, self.dilation, self.slope = channels_in, channels_out, dilation, slope
        self.activation = activation
        self.k1_size = channels_in * channels_in * 9
        self.k2_size = channels_out * channels_in * 9
        self.linear = _language_linear(embed_dim, self.k1_size + self.k2_size, init_std)

    def kernels(self, sentence_embedding: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """K1 (B, C_r, C_r, 3, 3) and K2 (B, C_g, C_r, 3, 3), each unit-norm per sample."""
        k = _activate(self.linear(sentence_embedding), self.activation)
        k1, k2 = k.split([self.k1_size, self.k2_size], dim=-1)
        k1 = F.normalize(k1, dim=-1).view(-1, self.channels_in, self.channels_in, 3, 3)
        k2 = F.normalize(k2, dim=-1).view(-1, self.channels_out, self.channels_in, 3, 3)
        return k1, k2

    def forward(self, maps: torch.Tensor, kernels: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
        """Maps (B, ..., C_r, H, W) through this filter's `kernels(e)` (K1, K2)."""
        k1, k2 = kernels
        B, H, W = maps.shape[0], maps.shape[-2], maps.shape[-1]
        lead = maps.shape[1:-3]  # extra leading dims shared by one sample's kernels
        x = maps.reshape(B, -1, self.channels_in, H, W).transpose(0, 1)  # (N, B, C_r, H, W)
        x = x.reshape(-1, B * self.channels_in, H, W)  # (N, B*C_r, H, W): one group per sample
        x = F.conv2d(x, k1.reshape(B * self.channels_in, self.channels_in, 3, 3), padding=1, groups=B)
        x = instance_norm(F.leaky_relu(x, self.slope, inplace=True))
        x = F.conv2d(x, k2.reshape(B * self.channels_out, self.channels_in, 3, 3), padding=self.dilation,
                     dilation=self.dilation, groups=B)  # (N, B*C_g, H, W)
        x = x.reshape(-1, B, self.channels_out, H, W).transpose(0, 1)  # (B, N, C_g, H, W)
        return x.reshape(B, *lead, self.channels_out, H, W)


@dataclass(frozen=True)
class InstructionKernels:
    """The language-conditioned kernels of B instructions: what the filters make of the sentence embeddings."""

    relevance: torch.Tensor | None  # (B, C_r, C_f) 1x1 kernels; None: no grounding filter (an identity)
    goal: tuple[torch.Tensor, torch.Tensor] | None  # K1 (B, C_r, C_r, 3, 3), K2 (B, C_g, C_r, 3, 3); None: no filter

    @staticmethod
    def of(relevance_filter: RelevanceFilter | None, goal_filter: GoalFilter | None, sentence_embedding: torch.Tensor
           ) -> InstructionKernels:
        """The kernels of both filters; a filter that is None (removed, as the original code's ablations) has none."""
        return InstructionKernels(relevance_filter.kernels(sentence_embedding) if relevance_filter else None,
                                  goal_filter.kernels(sentence_embedding) if goal_filter else None)
