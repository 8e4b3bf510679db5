"""The leaky-integrator semantic map (paper: Semantic Map Accumulation; original code: lambda = 0.2, S_1 = F_1).

    S_1 = F_1,    S_j = (1 - lambda M_j) S_{j-1} + lambda F_j

with M_j the coverage mask. Where M = 1 this is the paper's (1 - lambda) S + lambda F; where M = 0 (F = 0 there)
the cell is unchanged. Along the image border, where M is fractional, the projected features are the
zero-padded bilinear sample, i.e. M times the border features, so the blend weight is exactly M there too.
"""

from __future__ import annotations

import torch


def leaky_integrate(prev_semantic_map_w: torch.Tensor | None, projected_features_w: torch.Tensor,
                    coverage_w: torch.Tensor, lam: float) -> torch.Tensor:
    """One step: the new semantic map (N, C, n, n). `prev_semantic_map_w` None means the first step (S = F)."""
    if prev_semantic_map_w is None:
        return projected_features_w
    return prev_semantic_map_w + lam * (projected_features_w - coverage_w * prev_semantic_map_w)


def accumulate(projected_features_w: torch.Tensor, coverage_w: torch.Tensor, lam: float,
               initial_semantic_map_w: torch.Tensor | None = None) -> torch.Tensor:
    """Semantic maps (B, T, C, n, n) over a sequence, from projections (B, T, C, n, n) and coverage (B, T, 1, n, n).

    `initial_semantic_map_w` (B, C, n, n) continues an episode; None starts one."""
    S = initial_semantic_map_w
    maps = []
    # unbind once: indexing [:, t] in the loop would make backward zero-fill a full-size gradient at every step.
    for F_t, M_t in zip(projected_features_w.unbind(1), coverage_w.unbind(1), strict=True):
        S = leaky_integrate(S, F_t, M_t, lam)
        maps.append(S)
    return torch.stack(maps, dim=1)
