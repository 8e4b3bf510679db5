"""Instruction encoder (paper: Instruction and Image Embedding; original code: 20-d word embeddings, one-layer
LSTM with 30 hidden units, the sentence embedding is the last output).

Padded batches are safe: the LSTM runs left to right, so its output at each instruction's last real token
(index length - 1) does not see the padding after it.
"""

from __future__ import annotations

import torch
import torch.nn as nn


class InstructionEncoder(nn.Module):
    """Token ids (B, L) and lengths (B,) -> sentence embeddings (B, hidden)."""

    def __init__(self, vocabulary_size: int, embedding_dim: int = 20, hidden: int = 30, pad_id: int = 0):
        super().__init__()
        self.embedding = nn.Embedding(vocabulary_size, embedding_dim, padding_idx=pad_id)
        self.lstm = nn.LSTM(embedding_dim, hidden, num_layers=1, batch_first=True)

    def forward(self, tokens: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        outputs, _ = self.lstm(self.embedding(tokens))  # (B, L, hidden)
        last = (lengths.to(outputs.device).long() - 1).clamp(min=0)
        return outputs[torch.arange(outputs.shape[0], device=outputs.device), last]  # (B, hidden)
