"""The controller (paper: Control; original code for the layout).

GSMN: the robot-frame maps [G, R] (5 x 64 x 64) go through one strided residual block (stride 2) to 5 x 32 x 32,
are flattened (5120), dropped out (0.5), and a densely connected two-layer perceptron gives the action:
    h = LeakyReLU(W1 x + b1),   out = W2 [x; h] + b2.
The paper applies one residual block to R and one to G and appends the instruction embedding to x; the
original applies one block to [G, R] and appends nothing. We follow the original's block; the embedding is
the config switch `model.controller_uses_instruction` (docs/model.md).

The three outputs are squashed to the label ranges: v = sigmoid(o_1) in [0, 1], omega = tanh(o_2) in [-1, 1]
(normalised by the drone's limits 1.6 m/s and 2.44 rad/s), and o_3 is the STOP logit.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from gsmn.model.blocks import ResidualBlock


class DensePerceptron(nn.Module):
    """x = [dropout(maps); extra] -> out = W2 [x; LeakyReLU(W1 x)] (3 raw outputs)."""

    def __init__(self, map_features: int, extra_features: int, hidden: int, dropout: float, slope: float = 0.01,
                 outputs: int = 3):
        super().__init__()
        self.dropout = nn.Dropout(dropout)
        self.hidden = nn.Linear(map_features + extra_features, hidden)
        self.out = nn.Linear(map_features + extra_features + hidden, outputs)
        self.extra_features, self.slope = extra_features, slope

    def forward(self, map_features: torch.Tensor, extra: torch.Tensor | None = None) -> torch.Tensor:
        x = self.dropout(map_features)
        if self.extra_features:
            if extra is None:
                raise ValueError("this perceptron needs its extra input (e.g. the sentence embedding)")
            x = torch.cat([x, extra], dim=-1)
        h = F.leaky_relu(self.hidden(x), self.slope)
        return self.out(torch.cat([x, h], dim=-1))


def split_actions(raw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Raw outputs (..., 3) -> v in [0, 1], omega in [-1, 1], stop logit, each (...)."""
    return torch.sigmoid(raw[..., 0]), torch.tanh(raw[..., 1]), raw[..., 2]


class MapController(nn.Module):
    """Robot-frame maps (N, C, n, n) (+ sentence embeddings (N, E)) -> raw actions (N, 3)."""

    def __init__(self, channels: int, map_size: int, hidden: int, dropout: float, extra_features: int = 0,
                 slope: float = 0.01):
        super().__init__()
        self.block = ResidualBlock(channels, stride=2, slope=slope)
        map_features = channels * ((map_size + 1) // 2) ** 2
        self.perceptron = DensePerceptron(map_features, extra_features, hidden, dropout, slope)

    def forward(self, maps_r: torch.Tensor, extra: torch.Tensor | None = None) -> torch.Tensor:
        return self.perceptron(self.block(maps_r).flatten(1), extra)  # (N, C*(n/2)^2) -> (N, 3)
