"""The auxiliary heads of a GSMN read out as numpy arrays (`Heads`), and which of them were trained
(`trained_heads`): what failure attribution (`gsmn.attribution`) and the ground-truth figures
(`gsmn.analysis.truth`) read the model's maps with, away from any episode.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gsmn.model.losses import objectives_for


@dataclass(frozen=True)
class Heads:
    """The auxiliary heads as arrays, weight (K, C) and bias (K,); `*_trained` is False for a head whose objective
    the model was trained without (J_percept, J_ground, J_plan), which is its initialisation."""

    perception_w: np.ndarray
    perception_b: np.ndarray
    grounding_w: np.ndarray
    grounding_b: np.ndarray
    goal_w: np.ndarray
    goal_b: np.ndarray
    goal_trained: bool = True
    perception_trained: bool = True
    grounding_trained: bool = True
    grounding_filter: bool = True  # False: the model has no grounding filter (the original code's -J_ground)
    goal_filter: bool = True  # False: no goal filter (the original code's -J_goal); docs/model.md

    @classmethod
    def of(cls, model) -> Heads:
        """The heads of a GSMN (gsmn.model.gsmn.GSMN) as float32 arrays."""
        h = model.heads
        if h.goal is None:
            raise ValueError(f"a {model.kind!r} model has no goal head; attribution needs GSMN's maps")

        def arr(t) -> np.ndarray:
            return t.detach().cpu().float().numpy().copy()

        trained = trained_heads(model)
        return cls(arr(h.perception.weight), arr(h.perception.bias), arr(h.grounding.weight),
                   arr(h.grounding.bias), arr(h.goal.weight), arr(h.goal.bias), trained["goal"],
                   trained["perception"], trained["grounding"], model.config.model.grounding_filter,
                   model.config.model.goal_filter)


def trained_heads(model) -> dict[str, bool]:
    """Which of a GSMN's auxiliary heads were trained ("perception", "grounding", "goal"): those whose objective
    its configuration switches on with a weight above 0 ("gsmn-no-plan" switches J_plan off itself)."""
    loss = objectives_for(model.kind, model.config.loss)
    return {"perception": loss.perception and loss.perception_weight > 0,
            "grounding": loss.grounding and loss.grounding_weight > 0,
            "goal": model.heads.goal is not None and loss.goal and loss.goal_weight > 0}
