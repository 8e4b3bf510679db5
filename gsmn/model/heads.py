"""The auxiliary classifiers (paper: Auxiliary Objectives; original code for their shapes).

- perception: Linear(C_f -> 63 landmark classes) on semantic-map (or FPV feature) cells at landmark centres;
- grounding: Linear(3 -> 2) on the relevance map at the same cells: is this the landmark the instruction names;
- goal: Linear(2 -> 2) on the world-frame goal map: is this the goal cell (GSMN only);
- language: Linear(E -> 63) landmark class and Linear(E -> 4) side, on the sentence embedding.

They are part of the model (trained with it, saved in its checkpoint) so the dashboard can show, e.g., the class
probabilities of any map cell.
"""

from __future__ import annotations

import numpy as np
import torch.nn as nn


class AuxiliaryHeads(nn.Module):
    def __init__(self, feature_channels: int, relevance_channels: int, goal_channels: int | None, embed_dim: int,
                 num_classes: int, num_sides: int):
        super().__init__()
        self.perception = nn.Linear(feature_channels, num_classes)
        self.grounding = nn.Linear(relevance_channels, 2)
        self.goal = nn.Linear(goal_channels, 2) if goal_channels else None
        self.language_landmark = nn.Linear(embed_dim, num_classes)
        self.language_side = nn.Linear(embed_dim, num_sides)


# -- the heads read on recorded maps (numpy: the dashboard, failure attribution) ---------------------------------
def softmax(logits: np.ndarray, axis: int = 0) -> np.ndarray:
    z = logits - logits.max(axis=axis, keepdims=True)
    e = np.exp(z)
    return e / e.sum(axis=axis, keepdims=True)


def positive_probability(maps: np.ndarray, weight: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """A binary head Linear(C -> 2) on every cell of maps (C, H, W) -> P(class 1) (H, W)."""
    C, H, W = maps.shape
    logits = np.einsum("kc,cn->kn", weight.astype(np.float32), maps.reshape(C, -1).astype(np.float32)) \
        + bias.astype(np.float32)[:, None]  # einsum, not @: threaded BLAS spins for ms on this tiny product
    return softmax(logits, axis=0)[1].reshape(H, W)
